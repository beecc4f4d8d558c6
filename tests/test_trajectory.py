from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from mbtsr import LinearDynamics, Trajectory, load_trajectories, rollout, save_trajectories
from mbtsr.trajectory import stack_trajectories


def test_trajectory_regressors_and_targets():
    x = np.arange(12.0).reshape(4, 3)
    u = np.ones((3, 2))
    tr = Trajectory(x, u, dt=0.1)
    assert (tr.T, tr.n, tr.m) == (3, 3, 2)
    np.testing.assert_array_equal(tr.inputs[0], x[:-1])
    np.testing.assert_array_equal(tr.targets, x[1:])
    with pytest.raises(ValueError):
        tr.x[0, 0] = 5.0  # read-only


@pytest.mark.parametrize(
    "x, u, msg",
    [
        (np.zeros((4, 3)), np.zeros((4, 2)), "len\\(x\\) == len\\(u\\) \\+ 1"),
        (np.zeros(4), np.zeros((3, 2)), "2-dimensional"),
        (np.full((4, 3), np.nan), np.zeros((3, 2)), "non-finite"),
        (np.zeros((1, 3)), np.zeros((0, 2)), "T >= 1"),
    ],
)
def test_trajectory_rejects_bad_input(x, u, msg):
    with pytest.raises(ValueError, match=msg):
        Trajectory(x, u)


@given(st.floats(allow_nan=True, allow_infinity=True))
def test_trajectory_dt_must_be_positive_finite(dt):
    if np.isfinite(dt) and dt > 0:
        assert Trajectory(np.zeros((2, 1)), np.zeros((1, 1)), dt=dt).dt == dt
    else:
        with pytest.raises(ValueError, match="dt"):
            Trajectory(np.zeros((2, 1)), np.zeros((1, 1)), dt=dt)


def test_save_load_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    trajs = [Trajectory(rng.normal(size=(6, 2)), rng.normal(size=(5, 1)), dt=0.02)]
    trajs.append(Trajectory(rng.normal(size=(3, 2)), rng.normal(size=(2, 1))))
    save_trajectories(tmp_path / "d.npz", trajs)
    back = load_trajectories(tmp_path / "d.npz")
    assert len(back) == 2 and back[1].dt is None and back[0].dt == 0.02
    for a, b in zip(trajs, back):
        np.testing.assert_array_equal(a.x, b.x)
        np.testing.assert_array_equal(a.u, b.u)


def test_stack_requires_aligned():
    a = Trajectory(np.zeros((3, 2)), np.zeros((2, 1)))
    b = Trajectory(np.zeros((4, 2)), np.zeros((3, 1)))
    X, U = stack_trajectories([a, a])
    assert X.shape == (2, 3, 2) and U.shape == (2, 2, 1)
    with pytest.raises(ValueError, match="share"):
        stack_trajectories([a, b])


def test_linear_rollout_matches_closed_form():
    rng = np.random.default_rng(1)
    A = 0.9 * np.eye(3) + 0.05 * rng.normal(size=(3, 3))
    B = rng.normal(size=(3, 2))
    model = LinearDynamics(A, B)
    x0 = rng.normal(size=3)
    u = rng.normal(size=(10, 2))
    X = rollout(model, x0, u)
    # closed form: x_T = A^T x0 + sum_k A^(T-1-k) B u_k
    xT = np.linalg.matrix_power(A, 10) @ x0 + sum(
        np.linalg.matrix_power(A, 9 - k) @ B @ u[k] for k in range(10)
    )
    np.testing.assert_allclose(X[-1], xT, rtol=1e-12)
    Aj, Bj = model.jacobians(X[:-1], u)
    assert Aj.shape == (10, 3, 3) and Bj.shape == (10, 3, 2)


def test_rollout_flags_divergence_with_nan():
    model = LinearDynamics(np.array([[1e200]]), np.array([[1.0]]))
    X = rollout(model, np.array([1e200]), np.zeros((5, 1)))
    assert np.isnan(X[-1]).all()


def test_step_validates_dimensions():
    model = LinearDynamics(np.eye(2), np.ones((2, 1)))
    with pytest.raises(ValueError, match="last dimension n=2"):
        model.step(np.zeros(3), np.zeros(1))
    with pytest.raises(ValueError, match="batch"):
        model.step(np.zeros((4, 2)), np.zeros((3, 1)))
    with pytest.raises(ValueError, match="non-finite"):
        model.step(np.array([np.inf, 0.0]), np.zeros(1))


class _TouchOnLoad:
    """Unpickling this object creates a file: proof that something was unpickled."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (Path.touch, (self.marker,))


@pytest.mark.parametrize("arrays, message", [
    (lambda m: {"trajs": np.array([_TouchOnLoad(m), None], dtype=object)},
     "{p} is not a file of save_trajectories: it has no array 'count' and holds trajs: object "
     "[2]; arrays of Python objects are never unpickled (they could run code)"),
    (lambda m: {"count": np.array(1), "x0": np.array([_TouchOnLoad(m), 1.0], dtype=object),
                "u0": np.zeros((1, 1)), "dt0": np.array(0.1)},
     "{p} holds an array of Python objects, 'x0' (object [2]), which is never unpickled (it "
     "could run code): save trajectories with mbtsr.save_trajectories (numeric arrays)"),
    (lambda m: {"count": np.array(2), "x0": np.zeros((3, 2)), "u0": np.zeros((2, 1)),
                "dt0": np.array(0.1)},
     "{p} is not a file of save_trajectories: it has no array 'dt1' and holds count: int64 [], "
     "x0: float64 [3, 2], u0: float64 [2, 1], dt0: float64 []"),
])
def test_load_trajectories_names_the_file_and_what_it_holds_and_unpickles_nothing(
        tmp_path, arrays, message):
    path, marker = tmp_path / "data.npz", tmp_path / "unpickled"
    np.savez(path, **arrays(marker))
    with pytest.raises(ValueError) as err:
        load_trajectories(path)
    assert str(err.value) == message.format(p=path)
    assert not marker.exists()


def test_load_trajectories_on_a_file_that_is_not_an_archive(tmp_path):
    np.save(tmp_path / "one.npy", np.zeros(3))
    with pytest.raises(ValueError, match=r"one\.npy holds a single array float64 \[3\] \(a \.npy "
                                         r"file\), not the \.npz archive"):
        load_trajectories(tmp_path / "one.npy")
    (tmp_path / "text.npz").write_text("not numpy")
    with pytest.raises(ValueError, match=r"text\.npz is neither an \.npz archive .* a pickle is "
                                         r"never loaded here"):
        load_trajectories(tmp_path / "text.npz")


def test_as_trajectory_list_takes_one_a_list_or_an_iterable_and_names_what_is_wrong():
    from mbtsr.trajectory import as_trajectory_list

    trs = [Trajectory(np.zeros((3, 2)), np.zeros((2, 1)), dt=0.1) for _ in range(2)]
    assert as_trajectory_list(trs[0]) == [trs[0]]
    assert as_trajectory_list(trs) == trs
    assert as_trajectory_list(t for t in trs) == trs  # a generator is read once, in order
    for bad in ([], (), "x", np.zeros(3), None):
        with pytest.raises(ValueError, match=r"^data must be a Trajectory or a non-empty"):
            as_trajectory_list(bad, name="data")
    with pytest.raises(ValueError, match=r"^data\[1\] must be a Trajectory, got int"):
        as_trajectory_list([trs[0], 3], name="data")
