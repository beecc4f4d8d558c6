"""The true-model oracle for any Gymnasium MuJoCo env (issue 12 item 4): MPC on
``MujocoDynamics`` lifted to ``[qpos, qvel, observation]``, no user glue.

Checks: the lifted model's observation part is the env's own observation; its Jacobians agree
with independent finite differences of its own ``step``; the oracle's plans start from the env's
true state after ``reset`` (same seeds as the agent's evaluation); on InvertedPendulum-v5 the
true-model MPC keeps the pole up where doing nothing lets it fall; the agent's oracle is wired
for Reacher-v5 and InvertedPendulum-v5; an env with no true model gives a clear error / None.
Tiny horizons and episodes throughout."""

from __future__ import annotations

import casadi as ca
import gymnasium as gym
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agents.config import AgentConfig, PlannerConfig
from agents.evaluation import evaluate_policy_costs, has_true_model, oracle_policy
from agents.tasks import StateMap, angle_pairs, inverted_pendulum, reacher
from envs.mujoco_model import MujocoDynamics, ObservedDynamics, state_of
from mbtsr.episode import as_policy, run_episode

reacher_cost, reacher_terminal = reacher().cost_fn, reacher().terminal_cost_fn
pendulum_cost = inverted_pendulum().cost_fn
TINY = {"planner": PlannerConfig(kind="ilqr", horizon=4, ilqr_iterations=1,
                                  first_plan_iterations=3)}


@pytest.mark.parametrize("env_id", ["Reacher-v5", "InvertedPendulum-v5"])
def test_lifted_state_is_the_envs_observation_and_true_state(env_id):
    env = gym.make(env_id)
    model = ObservedDynamics(MujocoDynamics(env), env)
    obs, _ = env.reset(seed=1000)
    z = model.lift(state_of(env))
    base = env.unwrapped
    np.testing.assert_array_equal(z[: model.n], np.concatenate((base.data.qpos, base.data.qvel)))
    np.testing.assert_allclose(z[model.n :], obs, rtol=0, atol=1e-12)
    # one step of the model vs one env step (cold vs warm solver start, one substep of
    # kinematics lag in body positions: see envs.mujoco_model)
    u = np.full(env.action_space.shape, 0.5)
    z1 = model.step(z, u)
    obs1, *_ = env.step(u)
    np.testing.assert_allclose(z1[: model.n], state_of(env), rtol=0, atol=1e-6)
    np.testing.assert_allclose(z1[model.n :], obs1, rtol=0, atol=1e-4)
    env.close()


@pytest.mark.parametrize("env_id", ["Reacher-v5", "InvertedPendulum-v5"])
def test_lifted_jacobians_match_finite_differences_of_step(env_id):
    env = gym.make(env_id)
    model = ObservedDynamics(MujocoDynamics(env), env)
    env.reset(seed=3)
    rng = np.random.default_rng(0)
    z = model.lift(state_of(env) + 0.05 * rng.standard_normal(model.n))
    u = rng.uniform(-0.5, 0.5, env.action_space.shape)
    A, B = model.jacobians(z[None], u[None])
    eps = 1e-5  # a different step than the model's (1e-6)
    num_a = np.empty((model.state_dim, model.n))
    for i in range(model.n):
        dz = np.zeros(model.state_dim)
        dz[i] = eps
        num_a[:, i] = (model.step(z + dz, u) - model.step(z - dz, u)) / (2 * eps)
    num_b = np.empty((model.state_dim, model.action_dim))
    for j in range(model.action_dim):
        du = np.zeros(model.action_dim)
        du[j] = eps
        num_b[:, j] = (model.step(z, u + du) - model.step(z, u - du)) / (2 * eps)
    np.testing.assert_allclose(A[0][:, : model.n], num_a, rtol=1e-3, atol=1e-4)
    np.testing.assert_allclose(A[0][:, model.n :], 0.0)  # step ignores the observation part
    np.testing.assert_allclose(B[0], num_b, rtol=1e-3, atol=1e-4)
    env.close()


def test_reacher_oracle_without_glue_starts_from_the_true_state():
    env = gym.make("Reacher-v5")
    assert has_true_model(env)
    policy = oracle_policy(env, cost_fn=reacher_cost, terminal_cost_fn=reacher_terminal, **TINY)
    obs, _ = env.reset(seed=1000)
    x0 = state_of(env)
    policy.predict(obs, episode_start=True)
    X = np.asarray(policy.policy.last_result.X)  # the MPC policy inside ReplanEvery
    np.testing.assert_array_equal(X[0, :8], x0)  # the plan starts at the env's qpos|qvel
    costs = evaluate_policy_costs(policy, env, None, 1000, n_episodes=2, max_steps=5)
    assert costs.shape == (2,) and np.isfinite(costs).all()
    env.close()


def test_true_model_mpc_keeps_the_inverted_pendulum_up():
    env = gym.make("InvertedPendulum-v5")
    policy = oracle_policy(env, PlannerConfig(kind="ilqr", horizon=10, ilqr_iterations=1,
                                              first_plan_iterations=5), cost_fn=pendulum_cost)
    steps = 40
    for seed in (1000, 1001):
        zero = run_episode(env, lambda obs, t: np.zeros(1), seed=seed, max_steps=steps)
        assert zero.terminated, "doing nothing must let the pole fall within the episode"
        rec = run_episode(env, as_policy(policy), seed=seed, max_steps=steps)
        assert not rec.terminated
        assert len(rec.rewards) == steps
        assert np.max(np.abs(rec.obs[:, 1])) < 0.2
    env.close()


@pytest.mark.parametrize("env_id,cost,terminal", [
    ("Reacher-v5", reacher_cost, reacher_terminal),
    ("InvertedPendulum-v5", pendulum_cost, None),
])
def test_agent_oracle_any_mujoco_env(env_id, cost, terminal):
    from agents.jacprop_agent import JacPropAgent

    env = gym.make(env_id, max_episode_steps=6)
    cfg = AgentConfig.default({"planner.horizon": 4, "planner.ilqr_iterations": 1,
                               "planner.first_plan_iterations": 3, "evaluation.episodes": 2,
                               "evaluation.every": 0},
                              progress=False, tensorboard=False, checkpoint=False)
    agent = JacPropAgent(env, cfg, cost_fn=cost, terminal_cost_fn=terminal)
    mean = agent.compute_oracle()
    assert mean is not None and np.isfinite(mean)
    assert agent.oracle_costs.shape == (2,)
    # the same episodes by hand: same seeds (eval_seed + i), the agent's planner
    env2 = gym.make(env_id, max_episode_steps=6)
    policy = oracle_policy(env2, cfg.planner, seed=cfg.seed, cost_fn=cost,
                           terminal_cost_fn=terminal)
    by_hand = evaluate_policy_costs(policy, env2, None, cfg.evaluation.seed, n_episodes=2,
                                    max_steps=6)
    np.testing.assert_allclose(agent.oracle_costs, by_hand, rtol=0, atol=1e-9)
    env.close()


def test_env_without_true_model():
    """Not MuJoCo and no dynamics_model(): oracle_policy raises a clear ValueError; the agent
    reports no oracle (``compute_oracle() is None``) and goes on."""
    import casadi as ca

    from agents.jacprop_agent import JacPropAgent

    env = gym.make("Pendulum-v1")
    assert not has_true_model(env)

    def cost(obs, a):
        return ca.sumsqr(obs) + ca.sumsqr(a)

    with pytest.raises(ValueError, match="no true model"):
        oracle_policy(env, cost_fn=cost)
    cfg = AgentConfig.default({"evaluation.every": 0}, progress=False, tensorboard=False,
                              checkpoint=False)
    agent = JacPropAgent(env, cfg, cost_fn=cost)
    assert agent.compute_oracle() is None
    env.close()


@pytest.mark.parametrize("planner", [None, "ilqr"])
def test_bench_suite_baselines_smoke(planner):
    from agents.experiments.bench_suite import EVAL_EPISODES, task_baselines

    kind = {} if planner is None else {"planner.kind": planner}
    rec = task_baselines("reacher", smoke=True,
                         overrides={**kind, "planner.terminal_weight": 3.0, "planner.horizon": 4})
    # the overrides reach the oracle's planner, over the smoke budgets (horizon 5)
    assert rec["planner"]["terminal_weight"] == 3.0 and rec["planner"]["horizon"] == 4
    assert len(rec["oracle_returns"]) == len(rec["zero_returns"]) == EVAL_EPISODES
    # even a 5-step horizon on the true model beats doing nothing
    assert np.isfinite(rec["oracle_return"]) and rec["oracle_return"] > rec["zero_return"]
    assert rec["planner"]["kind"] == (planner or "cem-ilqr")
    assert 0 < rec["oracle_cpu_seconds"]


def test_true_model_mpc_keeps_the_double_pendulum_up():
    """Issue 20's cause: InvertedDoublePendulum-v5's cost (its reward terms, the tip height
    written from the sin/cos observations) is not convex in the planner's state, and a cold
    30-step plan from zeros falls within 10 steps. Before the fix the true-model MPC's poles
    fell within about 10 steps (returns 82-91 per 1000-step episode); now the tip stays near
    its top height (1.2 m) and the episode does not end."""
    from agents.tasks import inverted_double_pendulum

    task = inverted_double_pendulum(max_episode_steps=40)
    env = task.make_env()
    planner = PlannerConfig(kind="ilqr", horizon=30, ilqr_iterations=2, first_plan_iterations=20)
    policy = oracle_policy(env, planner, **task.agent_kwargs())
    rec = run_episode(env, as_policy(policy), seed=1000)
    assert len(rec.actions) == 40 and not rec.terminated
    tip_height = 0.6 * rec.obs[:, 3] + 0.6 * (rec.obs[:, 3] * rec.obs[:, 4]
                                              - rec.obs[:, 1] * rec.obs[:, 2])
    assert tip_height.min() > 1.15
    assert -rec.cost > 40 * 9.0  # alive bonus 10 minus the distance penalty (0.64 at the top)


def test_the_double_pendulum_angles_are_found_and_map_back_to_the_observation():
    """On observations InvertedDoublePendulum-v5 visits, :func:`angle_pairs` finds its two
    (sin, cos) pairs; the angle state holds the env's own ``[qpos, qvel]`` (and the constraint
    force), and ``observation(state(obs), obs)`` rebuilds the observation."""
    env = gym.make("InvertedDoublePendulum-v5")
    obs, _ = env.reset(seed=3)
    rng, seen, joint = np.random.default_rng(0), [], []
    for _ in range(30):
        seen.append(obs)
        joint.append(np.r_[env.unwrapped.data.qpos, env.unwrapped.data.qvel])
        obs, _, terminated, _, _ = env.step(rng.uniform(-1, 1, 1))
        if terminated:
            obs, _ = env.reset(seed=4)
    pairs = angle_pairs(np.array(seen))
    assert pairs == ((1, 3), (2, 4))
    state_map = StateMap(angles=pairs)
    states = state_map.state(np.array(seen))
    np.testing.assert_allclose(states[:, :6], np.array(joint), rtol=0, atol=1e-12)
    for o, s in zip(seen, states):
        back = np.asarray(ca.DM(state_map.observation(ca.DM(s), ca.DM(o)))).ravel()
        np.testing.assert_allclose(back, o, rtol=0, atol=1e-12)
    assert StateMap.from_dict(state_map.to_dict()).angles == pairs


def test_angle_pairs_leaves_out_what_is_not_one_angle_away_from_its_jump():
    """Reacher's joints turn through +-pi (their angles would jump), a pair that never moves
    is not told apart from constants, and the sum of squares must hold on every row."""
    rng = np.random.default_rng(0)
    q = rng.uniform(-0.5, 0.5, 40)
    other = rng.normal(size=40)
    assert angle_pairs(np.column_stack([other, np.cos(q), np.sin(q)])) == ((2, 1),)
    assert angle_pairs(np.column_stack([np.cos(6 * q), np.sin(6 * q)])) == ()
    assert angle_pairs(np.column_stack([np.zeros(40), np.ones(40), other])) == ()
    off = np.column_stack([np.sin(q), np.cos(q) * (1 + 1e-3 * (np.arange(40) == 7))])
    assert angle_pairs(off) == ()
    assert angle_pairs(np.column_stack([np.cos(q), np.sin(q), np.cos(q), np.sin(q)])) == (
        (1, 0), (3, 2))  # each column in one pair


def test_affine_observations_are_detected_and_give_the_same_lifted_model():
    """HalfCheetah's observation [qpos[1:], qvel] is affine in the state: the lifted model
    computes it as one matrix product, equal to the env's own _get_obs; Hopper's clipped
    velocities and Reacher's sin/cos are not affine and keep the env's _get_obs."""
    env = gym.make("HalfCheetah-v5")
    env.reset(seed=0)
    dyn = MujocoDynamics(env)
    model = ObservedDynamics(dyn, env)
    assert model.affine is not None
    rng = np.random.default_rng(1)
    xs = state_of(env) + 0.3 * rng.standard_normal((5, model.n))
    np.testing.assert_allclose(model._observe(xs), dyn.observation(env, xs), rtol=0, atol=1e-12)
    z = model.lift(xs[0])
    us = rng.uniform(-1, 1, (4, model.action_dim))
    A, B = model.jacobians(np.repeat(z[None], 4, axis=0), us)
    eps = 1e-6  # the lifted Jacobian's control columns against central differences of step
    for j in range(model.action_dim):
        du = np.zeros(model.action_dim)
        du[j] = eps
        fd = (model.step(z, us[0] + du) - model.step(z, us[0] - du)) / (2 * eps)
        np.testing.assert_allclose(B[0, :, j], fd, rtol=1e-4, atol=1e-4)
    for env_id in ("Hopper-v5", "Reacher-v5"):
        other = gym.make(env_id)
        other.reset(seed=0)
        assert ObservedDynamics(MujocoDynamics(other), other).affine is None


def test_true_model_variants_parse_and_refuse():
    """bench_ilqr's true-model section measures planner kinds and named planner settings alike, and
    refuses variants that are not planner settings with a message naming them."""
    from agents.experiments.bench_ilqr import Args, _true_model_variants

    a = Args(true_model_planners=("ilqr",),
             true_model_variants='{"h15": {"planner.horizon": 15}}')
    assert _true_model_variants(a) == {"ilqr": {"planner.kind": "ilqr"},
                                       "h15": {"planner.horizon": 15}}
    with pytest.raises(ValueError, match=r"only planner.*training.steps"):
        _true_model_variants(Args(true_model_variants='{"x": {"training.steps": 3}}'))
    with pytest.raises(ValueError, match="JSON object"):
        _true_model_variants(Args(true_model_variants="[1]"))
    with pytest.raises(ValueError, match=r"labels \['ilqr'\] are planner kinds"):
        _true_model_variants(Args(true_model_variants='{"ilqr": {"planner.horizon": 9}}'))
    with pytest.raises(ValueError, match=r"names \['h9'\]"):
        _true_model_variants(Args(true_model_returns=("h9",)))
    # a bad value is refused before any measurement, naming the variant and the task
    from agents.experiments.bench_ilqr import check_true_model_variants

    check_true_model_variants(a)
    with pytest.raises(ValueError, match=r"variant 'h0' on task 'reacher'.*horizon"):
        check_true_model_variants(Args(true_model_tasks=("reacher",),
                                       true_model_variants='{"h0": {"planner.horizon": 0}}'))


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 3), st.integers(1, 3), st.integers(0, 10_000))
def test_planted_angles_are_found_and_round_trip(n_other, n_angles, seed):
    """Property: angles within +-1.4 rad planted as (sin, cos) columns at random places among
    other columns are found (one orientation or the other: both stay away from +-pi) and the
    angle map's observation of its state is the observation again."""
    rng = np.random.default_rng(seed)
    q = rng.uniform(-1.4, 1.4, (30, n_angles))
    obs = np.column_stack([np.sin(q), np.cos(q), rng.normal(size=(30, n_other))])
    order = rng.permutation(obs.shape[1])
    obs = obs[:, order]
    where = {int(c): k for k, c in enumerate(order)}  # planted column -> its place
    pairs = angle_pairs(obs)
    assert sorted(tuple(sorted(p)) for p in pairs) == sorted(
        tuple(sorted((where[k], where[n_angles + k]))) for k in range(n_angles))
    state_map = StateMap(angles=pairs)
    states = state_map.state(obs)
    assert states.shape == (30, obs.shape[1] - n_angles)
    back = np.asarray(ca.DM(state_map.observation(ca.DM(states[5]), ca.DM(obs[5])))).ravel()
    np.testing.assert_allclose(back, obs[5], rtol=0, atol=1e-12)


@pytest.mark.parametrize("angles", [[(1, 1)], [(1, 2, 3)], [(-1, 2)], [(1, 2), (2, 3)],
                                    [(1.5, 2)]])
def test_bad_angle_pairs_are_named(angles):
    with pytest.raises(ValueError, match="angles must be .sine column, cosine column. pairs"):
        StateMap(angles=angles)
    with pytest.raises(ValueError, match="give one of prefix, angles or state_fn/obs_fn"):
        StateMap(lambda o: o, lambda s, o: s, angles=((0, 1),))
