"""Tests of mbtsr.metrics against closed forms and hand-written loops."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from mbtsr import LinearDynamics, Trajectory
from mbtsr.metrics import (
    jacobian_eigenvalues,
    jacobian_error,
    jacobian_rms_per_entry,
    k_step_rms,
    prediction_rms,
    simulation_rms,
)


def rotation_system(r=0.98, theta=0.3):
    """2-state system with eigenvalues r exp(+-i theta), one input."""
    A = r * np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
    return A, np.array([[0.0], [0.1]])


def simulate(A, B, x0, u):
    x = [x0]
    for ut in u:
        x.append(A @ x[-1] + B @ ut)
    return np.array(x)


def make_trajs(A, B, T=50, count=3, seed=0):
    rng = np.random.default_rng(seed)
    trajs = []
    for _ in range(count):
        u = rng.normal(size=(T, B.shape[1]))
        trajs.append(Trajectory(simulate(A, B, rng.normal(size=A.shape[0]), u), u))
    return trajs


# ------------------------------------------------------------------------------------------
# prediction and simulation
# ------------------------------------------------------------------------------------------


def test_prediction_rms_is_zero_for_the_true_model_and_closed_form_for_a_wrong_one():
    A, B = rotation_system()
    trajs = make_trajs(A, B)
    assert prediction_rms(LinearDynamics(A, B), trajs) == pytest.approx(0.0, abs=1e-14)
    dA = np.array([[0.01, 0.0], [0.0, -0.02]])
    wrong = LinearDynamics(A + dA, B)
    x = np.concatenate([tr.x[:-1] for tr in trajs])
    err = x @ dA.T  # one-step error of the wrong model
    assert prediction_rms(wrong, trajs) == pytest.approx(np.sqrt(np.mean(err**2)), rel=1e-12)
    per_dim = prediction_rms(wrong, trajs, per_dimension=True)
    np.testing.assert_allclose(per_dim, np.sqrt(np.mean(err**2, 0)), rtol=1e-12)
    assert np.sqrt(np.mean(per_dim**2)) == pytest.approx(prediction_rms(wrong, trajs), rel=1e-12)


def test_simulation_rms_matches_a_hand_written_loop_and_counts_no_divergence():
    A, B = rotation_system()
    trajs = make_trajs(A, B, T=40, count=3) + make_trajs(A, B, T=25, count=1, seed=1)
    A_hat = A + np.array([[0.0, 0.01], [0.0, 0.0]])
    model = LinearDynamics(A_hat, B)
    errs = [simulate(A_hat, B, tr.x[0], tr.u)[1:] - tr.x[1:] for tr in trajs]
    expected = np.sqrt(np.mean(np.concatenate(errs) ** 2))
    rms, diverged = simulation_rms(model, trajs)
    assert rms == pytest.approx(expected, rel=1e-12)
    assert diverged == 0
    assert simulation_rms(LinearDynamics(A, B), trajs)[0] == pytest.approx(0.0, abs=1e-12)


def test_simulation_divergence_is_counted():
    A, B = rotation_system(r=0.95)
    trajs = make_trajs(A, B, T=200, count=3)
    rms, diverged = simulation_rms(LinearDynamics(1.3 * A, B), trajs)  # |eig| 1.235: blows up
    assert diverged == 3 and rms > 1e6
    rms, diverged = simulation_rms(LinearDynamics(1e30 * A, B), trajs)  # overflows to inf/NaN
    assert diverged == 3 and rms == np.inf
    # a threshold above the actual excursion counts none
    A_hat = A + 0.01
    rms_ok, none = simulation_rms(LinearDynamics(A_hat, B), trajs, divergence_threshold=1e6)
    assert none == 0 and np.isfinite(rms_ok)


# ------------------------------------------------------------------------------------------
# Jacobian errors
# ------------------------------------------------------------------------------------------


def test_jacobian_error_closed_forms():
    rng = np.random.default_rng(0)
    T, n, m = 7, 3, 2
    J = rng.normal(size=(T, n, n + m))
    c = 0.3
    # a constant offset c on every entry: ||.||_F = |c| sqrt(n (n+m)) at every t
    assert jacobian_error(J, J + c) == pytest.approx(c * np.sqrt(n * (n + m)), rel=1e-12)
    assert jacobian_rms_per_entry(J, J + c) == pytest.approx(c, rel=1e-12)
    # members whose deviations cancel in the ensemble mean give zero error
    d = rng.normal(size=(T, n, n + m))
    members = np.stack([J + d, J - d, J + 2 * d, J - 2 * d])
    assert jacobian_error(J, members) == pytest.approx(0.0, abs=1e-12)
    # an error only at one time step: sqrt(||D||_F^2 / T)
    D = np.zeros_like(J)
    D[3] = rng.normal(size=(n, n + m))
    assert jacobian_error(J, J + D) == pytest.approx(np.linalg.norm(D[3]) / np.sqrt(T), rel=1e-12)
    # (A, B) pairs and stacked arrays are the same thing, for truth and members
    A_m, B_m = members[..., :n], members[..., n:]
    assert jacobian_error((J[..., :n], J[..., n:]), (A_m, B_m)) == jacobian_error(J, members)


@settings(max_examples=40, deadline=None)
@given(
    J=hnp.arrays(np.float64, (4, 2, 3), elements=st.floats(-10, 10)),
    D=hnp.arrays(np.float64, (4, 2, 3), elements=st.floats(-10, 10)),
    s=st.floats(-5, 5),
)
def test_jacobian_error_properties(J, D, s):
    e = jacobian_error(J, J + D)
    assert e >= 0
    assert e == pytest.approx(jacobian_error(J + D, J), rel=1e-12, abs=1e-12)  # symmetric
    assert jacobian_error(J, J + s * D) == pytest.approx(abs(s) * e, rel=1e-9, abs=1e-9)
    assert jacobian_rms_per_entry(J, J + D) == pytest.approx(e / np.sqrt(6), rel=1e-12, abs=1e-12)


def test_jacobian_eigenvalues_of_known_matrices_and_of_a_model():
    A, B = rotation_system(r=0.9, theta=0.4)
    ev = jacobian_eigenvalues(np.stack([A, np.diag([0.5, -2.0])]))
    np.testing.assert_allclose(ev[0], [0.9 * np.exp(-0.4j), 0.9 * np.exp(0.4j)], atol=1e-12)
    np.testing.assert_allclose(ev[1], [-2.0, 0.5], atol=1e-12)  # decreasing modulus
    x, u = np.zeros((5, 2)), np.zeros((5, 1))
    ev_model = jacobian_eigenvalues(LinearDynamics(A, B), x, u)
    assert ev_model.shape == (5, 2) and np.iscomplexobj(ev_model)
    np.testing.assert_allclose(ev_model, np.broadcast_to(ev[0], (5, 2)), atol=1e-12)
    np.testing.assert_allclose(jacobian_eigenvalues(A), ev[:1], atol=1e-12)


# ------------------------------------------------------------------------------------------
# bad input
# ------------------------------------------------------------------------------------------


def test_metrics_reject_bad_inputs():
    A, B = rotation_system()
    model = LinearDynamics(A, B)
    trajs = make_trajs(A, B, T=10, count=1)
    J = np.zeros((4, 2, 3))
    with pytest.raises(ValueError, match="non-empty"):
        prediction_rms(model, [])
    with pytest.raises(ValueError, match="Trajectory"):
        prediction_rms(model, [(trajs[0].x, trajs[0].u)])
    with pytest.raises(ValueError, match=r"\(n, m\)"):
        prediction_rms(model, [Trajectory(np.zeros((4, 3)), np.zeros((3, 1)))])
    with pytest.raises(ValueError, match="DynamicsModel"):
        simulation_rms(object(), trajs)
    with pytest.raises(ValueError, match="divergence_threshold"):
        simulation_rms(model, trajs, divergence_threshold=0.0)
    with pytest.raises(ValueError, match="J_hat must match"):
        jacobian_error(J, np.zeros((5, 2, 3)))
    with pytest.raises(ValueError, match="J_true must be"):
        jacobian_error(np.zeros((4, 2, 2)), J)  # no input columns
    with pytest.raises(ValueError, match="non-finite"):
        jacobian_error(J, np.full((4, 2, 3), np.nan))
    with pytest.raises(ValueError, match="A must be"):
        jacobian_error((np.zeros((4, 2, 3)), np.zeros((4, 2, 1))), J)
    with pytest.raises(ValueError, match="A must be"):
        jacobian_eigenvalues(np.zeros((4, 2, 3)))
    with pytest.raises(ValueError, match="x \\[T, n\\] and u"):
        jacobian_eigenvalues(model)
    with pytest.raises(ValueError, match="only used with a model"):
        jacobian_eigenvalues(A, np.zeros((1, 2)), np.zeros((1, 1)))


def test_k_step_rms_matches_the_closed_form_of_a_wrong_linear_model():
    """A model ``(A', B)`` of data from ``(A, B)``: ``k`` steps ahead its prediction is
    ``A'^k x_t + sum_j A'^(k-1-j) B u_(t+j)``, written here with matrix powers; ``k = 1`` is
    ``prediction_rms``, the true model's error is 0 at every ``k``."""
    A, B = rotation_system()
    trajs = make_trajs(A, B, T=20, count=2) + make_trajs(A, B, T=7, count=1, seed=3)
    A_hat = 1.05 * A
    for k in (1, 3, 8):
        errs = []
        for tr in trajs:
            for t in range(tr.T - k + 1):
                pred = np.linalg.matrix_power(A_hat, k) @ tr.x[t] + sum(
                    np.linalg.matrix_power(A_hat, k - 1 - j) @ B @ tr.u[t + j] for j in range(k))
                errs.append(tr.x[t + k] - pred)
        want = np.sqrt(np.mean(np.square(errs)))
        got = k_step_rms(LinearDynamics(A_hat, B), trajs, k)
        assert got == pytest.approx(want, rel=1e-12)
        assert k_step_rms(LinearDynamics(A, B), trajs, k) == pytest.approx(0.0, abs=1e-12)
    assert k_step_rms(LinearDynamics(A_hat, B), trajs, 1) == pytest.approx(
        prediction_rms(LinearDynamics(A_hat, B), trajs), rel=1e-12)
    assert k_step_rms(LinearDynamics(A_hat, B), trajs, 8, per_dimension=True).shape == (2,)


def test_k_step_rms_of_a_diverging_model_is_inf():
    """Predictions that overflow are reported (``inf``), not a validation error of the model's
    own next input."""
    A, B = rotation_system()
    trajs = make_trajs(A, B, T=20, count=1)
    blown = LinearDynamics(np.array([[1e100, 0.0], [0.0, 1.0]]), B)
    assert np.isfinite(k_step_rms(blown, trajs, 1))  # errors of about 1e100
    assert k_step_rms(blown, trajs, 4) == np.inf  # the states overflow at the 4th step


@pytest.mark.parametrize("k", [0, -1, 2.0, True, 21])
def test_k_step_rms_refuses_a_bad_k(k):
    A, B = rotation_system()
    with pytest.raises(ValueError, match="k"):
        k_step_rms(LinearDynamics(A, B), make_trajs(A, B, T=20, count=1), k)
