"""Predicted termination in the planners: the episode's own cost (PETS's convention, stage
costs after the first terminal state dropped, ``termination_cost`` paid once) in
:func:`mbtsr.costs.truncated_total`, in CEM's ranking and in iLQR's line search."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from lqr_reference import NaNOffNominal

from mbtsr.cem import cem
from mbtsr.costs import quadratic_cost, truncated_total
from mbtsr.dynamics import LinearDynamics
from mbtsr.ilqr import ILQROptions, ilqr


def truncated_by_loop(stage, terminal, done, termination_cost):
    out = []
    for ls, lT, d in zip(stage, terminal, done):
        J = 0.0
        for t in range(len(ls)):
            J += ls[t]
            if d[t]:  # x_{t+1} is terminal: no later stage, no terminal cost
                J += termination_cost
                break
        else:
            J += lT
        out.append(J)
    return np.array(out)


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 4), st.integers(1, 6), st.data())
def test_truncated_total_matches_an_episode_loop(S, T, data):
    floats = st.floats(-10, 10, allow_nan=False)
    stage = data.draw(arrays(float, (S, T), elements=floats))
    terminal = data.draw(arrays(float, (S,), elements=floats))
    done = data.draw(arrays(bool, (S, T)))
    c = data.draw(floats)
    np.testing.assert_allclose(truncated_total(stage, terminal, done, c),
                               truncated_by_loop(stage, terminal, done, c), atol=1e-12)


def test_ilqr_cost_is_the_episode_cost_under_termination():
    """x stays at 1 (A = I, B = 0): with every x_t, t >= 1 terminal only stage 0 counts, as CEM."""
    cost = quadratic_cost(np.eye(1), np.zeros((1, 1)), np.zeros(1), Qf=np.eye(1))
    model = LinearDynamics(np.eye(1), np.zeros((1, 1)))
    U0 = np.zeros((5, 1))
    kw = dict(u_min=-1, u_max=1, options=ILQROptions(max_iter=2, termination_cost=0.5))
    always = ilqr(cost, model, np.ones(1), U0, **kw,
                  terminated=lambda X: np.ones(X.shape[:-1], dtype=bool))
    never = ilqr(cost, model, np.ones(1), U0, **kw,
                 terminated=lambda X: np.zeros(X.shape[:-1], dtype=bool))
    plain = ilqr(cost, model, np.ones(1), U0, **kw)
    sampled = cem(cost, model, np.ones(1), U0, u_min=-1, u_max=1,
                  options={"iterations": 1, "termination_cost": 0.5},
                  terminated=lambda X: np.ones(X.shape[:-1], dtype=bool))
    assert always.cost == pytest.approx(1.5) == pytest.approx(sampled.cost)
    assert never.cost == pytest.approx(6.0) == pytest.approx(plain.cost)


def integrator_to_five(terminated=None):
    """x+ = x + u, |u| <= 1, stage (x - 5)^2 + 0.01 u^2 from x0 = 0 over 10 steps."""
    cost = quadratic_cost(np.eye(1), 0.01 * np.eye(1), np.array([5.0]), Qf=np.eye(1))
    model = LinearDynamics(np.eye(1), np.eye(1))
    opts = ILQROptions(max_iter=50, termination_cost=1000.0)
    return ilqr(cost, model, np.zeros(1), np.zeros((10, 1)), u_min=-1, u_max=1,
                options=opts, terminated=terminated), cost


def test_ilqr_line_search_refuses_steps_that_end_the_episode():
    """Beyond x = 3 the episode ends at a cost of 1000: the smooth cost pulls towards x = 5, the
    line search accepts only steps that lower the episode's cost, so the plan stays below 3.
    (It creeps up to 3 rather than jumping there: the direction ignores the termination.)"""
    free, cost = integrator_to_five()
    assert free.X.max() > 4.5
    ended = lambda X: X[..., 0] > 3.0  # noqa: E731
    res, _ = integrator_to_five(ended)
    assert res.X.max() <= 3.0
    assert res.cost < 10 * 25.0 + 25.0  # it still improves on the start U0 = 0 (J = 275)
    # its reported cost is the episode cost of its own trajectory, computed independently
    stage = cost.stage_values(res.X[:-1], res.U)
    terminal = cost.terminal_values(res.X[-1], 10)
    assert res.cost == pytest.approx(float(truncated_by_loop(
        stage[None], terminal[None], ended(res.X[None, 1:]), 1000.0)[0]))
    # and it beats the free plan scored as an episode
    free_stage = cost.stage_values(free.X[:-1], free.U)
    free_J = truncated_by_loop(free_stage[None], cost.terminal_values(free.X[-1], 10)[None],
                               ended(free.X[None, 1:]), 1000.0)[0]
    assert res.cost < free_J


def test_ilqr_reports_a_plan_no_step_improves_under_the_episode_cost_as_converged():
    """Warm-started with its own solution (or any plan that ends right at x = 3), every step
    the smooth cost suggests ends the episode: the plan is optimal under the episode's cost.
    The solve used to end 'failed' (no improving step up to lambda_max) with that plan; a
    plan whose steps all diverge still fails."""
    ended = lambda X: X[..., 0] > 3.0  # noqa: E731
    first, cost = integrator_to_five(ended)
    model = LinearDynamics(np.eye(1), np.eye(1))
    opts = ILQROptions(max_iter=50, termination_cost=1000.0)
    for U0 in (first.U, np.full((10, 1), 0.3)):
        res = ilqr(cost, model, np.zeros(1), U0, u_min=-1, u_max=1, options=opts,
                   terminated=ended)
        assert res.status == "converged", res.message
        assert "no step improves the episode's cost" in res.message
        np.testing.assert_array_equal(res.U, U0)  # the plan, unchanged
        assert not any(tr["accepted"] for tr in res.trace)
        assert res.X.max() <= 3.0 and np.isfinite(res.cost)

    # but a plan whose every step diverges (a model that is NaN off it) still fails
    cost = quadratic_cost(np.eye(1), 0.01 * np.eye(1), np.array([5.0]), Qf=np.eye(1))
    res = ilqr(cost, NaNOffNominal(np.eye(1), np.eye(1)), np.zeros(1), np.zeros((10, 1)),
               u_min=-1, u_max=1, terminated=lambda X: X[..., 0] > 3.0)
    assert res.status == "failed" and "lambda_max" in res.message


def test_terminated_must_return_one_bool_per_state():
    cost = quadratic_cost(np.eye(1), np.eye(1), np.zeros(1))
    with pytest.raises(ValueError, match="terminated"):
        ilqr(cost, LinearDynamics(np.eye(1), np.eye(1)), np.ones(1), np.zeros((3, 1)),
             terminated=lambda X: np.zeros(2, dtype=bool))
    with pytest.raises(TypeError, match="terminated"):
        ilqr(cost, LinearDynamics(np.eye(1), np.eye(1)), np.ones(1), np.zeros((3, 1)),
             terminated=3)


@pytest.mark.parametrize("stage, terminal, done, name", [
    (np.zeros((2, 3)), np.zeros(2), np.zeros((2, 1), bool), "done"),  # would broadcast silently
    (np.zeros((2, 3)), np.zeros(2), np.zeros(2, bool), "done"),
    (np.zeros((2, 3)), np.zeros(3), np.zeros((2, 3), bool), "terminal"),
    (np.zeros(3), np.zeros(()), np.zeros(3, bool), "stage"),
])
def test_truncated_total_refuses_mismatched_shapes(stage, terminal, done, name):
    with pytest.raises(ValueError, match=name):
        truncated_total(stage, terminal, done)


def test_cem_checks_what_terminated_returns():
    cost = quadratic_cost(np.eye(1), np.eye(1), np.zeros(1))
    model = LinearDynamics(np.eye(1), np.eye(1))
    kw = dict(u_min=-1, u_max=1, options={"iterations": 1, "samples": 8, "elites": 2})
    for wrong in (lambda X: np.zeros(X.shape[0], bool),          # one per sample, not per state
                  lambda X: np.zeros((X.shape[0], 1), bool)):    # would broadcast silently
        with pytest.raises(ValueError, match="terminated"):
            cem(cost, model, np.ones(1), np.zeros((3, 1)), **kw, terminated=wrong)
    with pytest.raises(TypeError, match="terminated"):
        cem(cost, model, np.ones(1), np.zeros((3, 1)), **kw, terminated=3)


def test_ilqr_checks_terminated_before_any_rollout():
    """A non-callable ``terminated`` is refused even when the initial rollout diverges."""
    cost = quadratic_cost(np.eye(1), np.eye(1), np.zeros(1))
    model = LinearDynamics(1e9 * np.eye(1), np.eye(1))
    with pytest.raises(TypeError, match="terminated"):
        ilqr(cost, model, np.ones(1), np.zeros((3, 1)), terminated=3)


def test_mpc_policy_refuses_a_termination_fn_that_is_not_callable():
    """Checked where it is given, not as a ``TypeError: 'int' object is not callable`` from
    inside iLQR's line search at the first predict."""
    import gymnasium as gym

    import envs  # noqa: F401  (registers mbtsr/TwoLinkArm-v0)
    from agents.config import PlannerConfig
    from agents.evaluation import oracle_policy

    env = gym.make("mbtsr/TwoLinkArm-v0")
    with pytest.raises(TypeError, match="termination_fn"):
        oracle_policy(env, PlannerConfig(kind="ilqr", horizon=5), termination_fn=3)
