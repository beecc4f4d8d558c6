"""The agent's parts on their own: planning (config -> MPC policy, ReplanState), collection,
JacProp labels, model training, the evaluator and the task checks. Real MuJoCo, CasADi, torch;
tiny sizes."""

from __future__ import annotations

import math

import casadi as ca
import gymnasium as gym
import numpy as np
import pytest
import torch

import envs  # noqa: F401  (registers mbtsr/TwoLinkArm-v0)
from agents.collection import Collector
from agents.config import AgentConfig, CollectionConfig, PlannerConfig
from agents.evaluation import Evaluator, evaluate_policy_costs
from agents.labels import JacobianLabeler, check_ltv_memory
from agents.model_training import ModelTrainer, model_errors
from agents.planning import ReplanEvery, ReplanState, make_policy, solver
from agents.task_setup import check_state_map, resolve_task
from agents.tasks import ObservationCost, StateMap, default_task_for_env, env_spec
from mbtsr.cem import CEMOptions, cem
from mbtsr.cem_ilqr import CEMILQROptions, cem_ilqr
from mbtsr.ensemble import DynamicsEnsemble
from mbtsr.ilqr import ILQROptions, ilqr
from mbtsr.training import RegularizationConfig, TrainConfig
from mbtsr.trajectory import Trajectory

ARM = "mbtsr/TwoLinkArm-v0"
torch.set_num_threads(1)


# ----------------------------------------------------------------- planning
def test_solver_is_built_from_the_configs_plain_fields():
    p = PlannerConfig(kind="ilqr", ilqr_iterations=3)
    assert solver(p, seed=5) == (ilqr, ILQROptions(), 3)  # iLQR's own defaults, one set
    with pytest.raises(ValueError, match="explore_weight needs a planner with CEM"):
        solver(p, explore_weight=1.0)
    p = PlannerConfig(kind="cem", cem=CEMOptions(samples=32, elites=4, iterations=2,
                                                 particles=4))
    opt, options, iterations = solver(p, seed=5, explore_weight=0.5, explore_on="cost",
                                      particles=1)
    assert opt is cem and iterations == 2
    assert options == CEMOptions(samples=32, elites=4, iterations=2, particles=1, seed=5,
                                 explore_weight=0.5, explore_on="cost")
    p = PlannerConfig(ilqr_iterations=4)
    opt, options, iterations = solver(p, seed=9)
    assert opt is cem_ilqr and iterations == 4
    assert options == CEMILQROptions(max_iter=4, cem=CEMOptions(samples=64, elites=8,
                                                                iterations=2, seed=9))


def _arm_task(episode_steps: int = 10):
    env = gym.make(ARM, episode_steps=episode_steps)
    cost_fn, state_map = default_task_for_env(env)
    spec = env_spec(env)
    return env, spec, ObservationCost(cost_fn, state_map, spec, 4)


@pytest.mark.parametrize("k,feedback", [(1, False), (3, False), (3, True)])
def test_make_policy_takes_horizon_and_replanning_from_the_config(k, feedback):
    env, spec, task_cost = _arm_task()
    planner = PlannerConfig(kind="ilqr", horizon=7, replan_every=k, replan_feedback=feedback,
                            ilqr_iterations=1, first_plan_iterations=3)
    policy = make_policy(planner, env.unwrapped.dynamics_model(), task_cost)
    assert isinstance(policy, ReplanEvery) and (policy.k, policy.feedback) == (k, feedback)
    assert policy.policy.horizon == policy.policy.mpc.horizon == 7
    obs, _ = env.reset(seed=0)
    action, state = policy.predict(obs, None, episode_start=True)
    assert action.shape == (2,) and np.all(np.abs(action) <= spec.u_max)
    if k == 1:
        assert isinstance(state, np.ndarray) and state.shape == (7, 2)
        return
    assert isinstance(state, ReplanState) and state.age == 1 and state.plan.shape == (7, 2)
    res = policy.policy.last_result
    if feedback:  # the plan's rows 1.. and their gains, as the solve returned them
        np.testing.assert_array_equal(state.states, np.asarray(res.X)[1:])
        np.testing.assert_array_equal(state.gains[:-1], np.asarray(res.K)[1:])
    else:
        assert state.states is None and state.gains is None
    # the next step replays the plan's next control (open loop: exactly)
    a2, s2 = policy.predict(obs, state)
    assert s2.age == 2
    if not feedback:
        np.testing.assert_array_equal(a2, np.clip(np.asarray(res.U)[1], spec.u_min, spec.u_max))


def test_replan_state_shifts_every_array_by_one_row():
    plan, X, K = np.arange(6.0).reshape(3, 2), np.arange(9.0).reshape(3, 3), np.ones((3, 2, 3))
    K[1] *= 2
    s = ReplanState(plan, 1, X, K).shifted()
    np.testing.assert_array_equal(s.plan, [[2, 3], [4, 5], [4, 5]])
    np.testing.assert_array_equal(s.states, [[3, 4, 5], [6, 7, 8], [6, 7, 8]])
    np.testing.assert_array_equal(s.gains[0], 2 * np.ones((2, 3)))
    assert s.age == 2 and ReplanState(plan, 1).shifted().gains is None


# ----------------------------------------------------------------- collection
def test_collector_plays_the_excitation_and_records_model_states():
    env, spec, _ = _arm_task(episode_steps=12)
    state_map = StateMap(prefix=4)
    col = Collector(env, spec, CollectionConfig(excitation_scale=0.5), state_map)
    U = col.excitation(12, seed=3)
    np.testing.assert_array_equal(U, col.excitation(12, seed=3))
    assert np.all(U >= spec.u_min) and np.all(U <= spec.u_max)
    rec, traj = col.rollout(None, episode=4, reset_seed=1, signal_seed=3)
    np.testing.assert_array_equal(rec.actions, U.astype(np.float32))  # the env's dtype
    np.testing.assert_array_equal(traj.x, np.asarray(rec.obs)[:, :4])
    assert traj.T == 12 and traj.meta == {"episode": 4, "seed": 1}
    _, short = col.rollout(None, episode=5, reset_seed=1, signal_seed=3, max_steps=5)
    assert short.T == 5


def test_collector_continues_a_running_episode_and_forgets_it():
    env, spec, _ = _arm_task(episode_steps=12)
    col = Collector(env, spec, CollectionConfig(rollout_steps=5, continue_rollouts=True),
                    StateMap(prefix=4))
    rec1, t1 = col.rollout(None, episode=0, reset_seed=1, signal_seed=3)
    _, t2 = col.rollout(None, episode=1, reset_seed=2, signal_seed=4)
    np.testing.assert_array_equal(t2.x[0], t1.x[-1])  # continued, not reset
    assert t2.meta["seed"] is None
    _, t3 = col.rollout(None, episode=2, reset_seed=2, signal_seed=4)
    assert t3.T == 2  # the rest of the 12-step episode
    col.forget()
    _, t4 = col.rollout(None, episode=3, reset_seed=2, signal_seed=4)
    assert t4.meta["seed"] == 2 and t4.T == 5


# ----------------------------------------------------------------- labels
def _linear_trajectory(T: int, seed: int = 0) -> tuple[Trajectory, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    A = np.array([[1.0, 0.1], [-0.2, 0.95]])
    B = np.array([[0.0], [0.1]])
    u = rng.normal(size=(T, 1))
    x = np.zeros((T + 1, 2))
    x[0] = rng.normal(size=2)
    for t in range(T):
        x[t + 1] = A @ x[t] + B @ u[t]
    return Trajectory(x, u, 0.1), A, B


def _model(n: int = 2, m: int = 1) -> DynamicsEnsemble:
    cfg = AgentConfig.default({"model.ensemble_size": 2, "model.hidden_width": 8})
    return DynamicsEnsemble(cfg.model.ensemble_config(n, m, 0))


def test_labels_recover_a_linear_system_and_fall_back_on_one_transition():
    traj, A, B = _linear_trajectory(40)
    labeler = JacobianLabeler(2, 1, RegularizationConfig.named("sampled", ltv_lambda=10.0))
    model = _model()
    lam, note = labeler.add(traj, model, [], episode=0)
    assert lam == 10.0 and note == ""
    ltv = labeler.models[0]
    np.testing.assert_allclose(ltv.A, np.broadcast_to(A, (40, 2, 2)), atol=1e-6)
    np.testing.assert_allclose(ltv.B, np.broadcast_to(B, (40, 2, 1)), atol=1e-6)
    one = Trajectory(traj.x[5:7], traj.u[5:6], 0.1)
    with pytest.warns(RuntimeWarning, match="pooled over all episodes"):
        lam, note = labeler.add(one, model, [traj], episode=1)
    assert math.isnan(lam) and "least-squares" in note
    np.testing.assert_allclose(labeler.models[1].A[0], A, atol=1e-5)  # noise-free: exact
    restored = JacobianLabeler(2, 1, RegularizationConfig.named("sampled", ltv_lambda=10.0))
    restored.load_state_dict(labeler.state_dict())
    for a, b in zip(restored.models, labeler.models):
        np.testing.assert_array_equal(a.A, b.A)
        np.testing.assert_array_equal(a.B, b.B)
    assert restored.lambdas[0] == 10.0 and math.isnan(restored.lambdas[1])


def test_labels_without_ltv_regularization_only_log_nan():
    traj, _, _ = _linear_trajectory(10)
    labeler = JacobianLabeler(2, 1, RegularizationConfig.named("none"))
    assert math.isnan(labeler.add(traj, _model(), [], 0)[0]) and labeler.models == []
    # automatic selection: a weight > 0, the median of earlier ones when it cannot select
    auto = JacobianLabeler(2, 1, RegularizationConfig.named("sampled", ltv_lambda=None))
    auto.lambdas = [2.0, 4.0, math.nan]
    short = Trajectory(traj.x[:3], traj.u[:2], 0.1)
    notes: list[str] = []
    assert auto.select_lambda(short, notes) == 3.0 and "median" in notes[0]
    assert auto.select_lambda(_linear_trajectory(60)[0]) > 0


def test_ltv_memory_check_refuses_huge_states():
    check_ltv_memory(RegularizationConfig.named("sampled"), 10, 2)
    with pytest.raises(ValueError, match="smaller model state"):
        check_ltv_memory(RegularizationConfig.named("sampled"), 400, 10)
    check_ltv_memory(RegularizationConfig.named("none"), 400, 10)


# ----------------------------------------------------------------- model training
def test_trainer_warm_starts_and_seeds_each_update():
    traj, _, _ = _linear_trajectory(30)
    model = _model()
    trainer = ModelTrainer(model, TrainConfig(steps=20, batch=16), RegularizationConfig.named(
        "none"))
    assert trainer.configs(7)[0].seed == 7 and trainer.configs(7)[0].steps == 20
    assert all(math.isnan(v) for v in model_errors(model, traj))  # untrained: no error yet
    history = trainer.train([traj], [], seed=1)
    assert history.steps == 20 and trainer.optimizer_state is not None
    one_step, jac = model_errors(model, traj)
    assert np.isfinite(one_step) and math.isnan(jac)  # no true linearization given


# ----------------------------------------------------------------- evaluation
def test_evaluator_schedule_and_scores_like_evaluate_policy_costs():
    env = gym.make(ARM, episode_steps=6)
    cfg = AgentConfig.default({"evaluation.every": 3, "evaluation.episodes": 2,
                               "evaluation.oracle_cache_dir": None,
                               "collection.n_excitation_episodes": 2,
                               "planner.kind": "ilqr", "planner.horizon": 4,
                               "planner.ilqr_iterations": 1, "planner.first_plan_iterations": 2})
    cost_fn, state_map = default_task_for_env(env)
    ev = Evaluator(env, cfg, 6, cost_fn=cost_fn, state_map=state_map, terminal_cost_fn=None,
                   termination_fn=None)
    assert [e for e in range(10) if ev.due(e, 0)] == [1, 4, 7]
    assert ev.due(0, 0, last=True) is False and ev.due(2, 0, last=True) is True
    targets = ev.targets()
    assert len(targets) == 2 and ev.problem(1)[1] == cfg.evaluation.seed + 1

    def zero(obs):
        return np.zeros(2)

    out = ev.evaluate(zero)
    by_hand = evaluate_policy_costs(zero, gym.make(ARM, episode_steps=6), targets,
                                    cfg.evaluation.seed, max_steps=6)
    assert out["eval_returns"] == [float(-c) for c in by_hand]
    oracle = ev.oracle_costs
    assert oracle.shape == (2,) and out["cost_ratio"] == pytest.approx(
        by_hand.sum() / oracle.sum(), rel=1e-12)
    assert ev.take_oracle_seconds() > 0 and ev.take_oracle_seconds() == 0.0
    ev.evaluate(zero)
    assert ev.oracle_costs is oracle  # computed once


# ----------------------------------------------------------------- task checks
def test_task_setup_refuses_a_map_that_indexes_the_batch_and_learns_a_missing_cost():
    env = gym.make("Pendulum-v1")
    spec = env_spec(env)
    with pytest.raises(ValueError, match=r"obs\[\.\.\., i\]"):
        check_state_map(StateMap(lambda o: np.stack([o[0], o[1]]), lambda s, r: ca.vertcat(
            s, r[2])), env, spec)
    assert check_state_map(StateMap(), env, spec).shape == (3,)
    learned = resolve_task(env, None, None, None)  # no cost anywhere: a learned reward
    assert learned.cost_fn is None and learned.source == "learned"


def test_cost_fn_learned_learns_the_reward_of_a_known_env_and_survives_save_and_load(tmp_path):
    """``cost_fn="learned"`` on an env of agents.tasks: a reward model, not the registry's
    cost; the termination given is kept, a terminal cost is refused, and a saved agent loads as
    a learned-reward agent (not as the registry task of its env id)."""
    from agents import JacPropAgent
    from agents.tasks import inverted_pendulum

    env = gym.make("InvertedPendulum-v5", max_episode_steps=20)
    assert resolve_task(env, None, None, None).source == "registry"
    done = inverted_pendulum().termination_fn
    task = resolve_task(env, "learned", None, None)  # the registry's termination, kept
    assert (task.source, task.cost_fn, task.termination_fn) == ("learned", None, done)
    own = resolve_task(env, "learned", None, None, termination_fn=np.isnan)
    assert own.termination_fn is np.isnan
    with pytest.raises(ValueError, match="terminal_cost_fn needs a written cost_fn"):
        resolve_task(env, "learned", None, None, terminal_cost_fn=lambda o: ca.sumsqr(o))
    with pytest.raises(ValueError, match="'learn'"):
        resolve_task(env, "learn", None, None)
    cfg = AgentConfig.default({"model.ensemble_size": 1, "model.hidden_width": 8,
                               "training.steps": 5, "planner.horizon": 3,
                               "evaluation.episodes": 1, "reward.steps": 20})
    agent = JacPropAgent(env, cfg, cost_fn="learned")
    agent.learn(total_timesteps=40)
    assert agent.task.source == "learned" and agent.cost_fn is None
    agent.save(tmp_path / "a.pt")
    loaded = JacPropAgent.load(tmp_path / "a.pt", env)  # no function to pass again
    assert loaded.task.source == "learned"
    with pytest.raises(ValueError, match="holds a learned reward: load it with cost_fn='learned'"):
        JacPropAgent.load(tmp_path / "a.pt", env, **inverted_pendulum().agent_kwargs())
    written = JacPropAgent(env, cfg, **inverted_pendulum().agent_kwargs())
    written.save(tmp_path / "w.pt")
    with pytest.raises(ValueError, match="holds a written cost: load it with its cost_fn"):
        JacPropAgent.load(tmp_path / "w.pt", env, cost_fn="learned")
    obs = env.reset(seed=3)[0]
    np.testing.assert_array_equal(loaded.predict(obs)[0], agent.predict(obs)[0])


def test_jacobian_error_only_where_the_model_state_is_the_envs_own():
    """The arm with a learned reward learns its 6-number observation, which the env cannot
    linearize (it crashed at the first update before): the Jacobian error is NaN there, and
    finite for the registry task, whose model state is the arm's own [q, qd]."""
    from agents import JacPropAgent

    cfg = AgentConfig.default({"model.ensemble_size": 1, "model.hidden_width": 8,
                               "training.steps": 5, "planner.horizon": 3,
                               "evaluation.episodes": 1, "reward.steps": 20})
    errors = {}
    for cost in ("learned", None):
        env = gym.make("mbtsr/TwoLinkArm-v0", episode_steps=15)
        agent = JacPropAgent(env, cfg, cost_fn=cost)
        agent.learn(total_timesteps=45)
        errors[cost] = [r["jacobian_error"] for r in agent.logger_rows
                        if not math.isnan(r.get("one_step_rms", math.nan))]
    assert errors["learned"] and all(math.isnan(e) for e in errors["learned"])
    assert errors[None] and all(math.isfinite(e) and e > 0 for e in errors[None])


@pytest.mark.parametrize("kind", ["ilqr", "cem", "cem-ilqr"])
def test_oracle_plans_with_the_planners_kind_and_one_particle(kind):
    """The oracle is the agent's planner on the true model: the same optimizer and iteration
    counts from the same PlannerConfig; CEM's particles are 1 (one true model)."""
    from agents.evaluation import oracle_policy

    env = gym.make(ARM, episode_steps=5)
    planner = PlannerConfig(kind=kind, horizon=6, replan_every=2, first_plan_iterations=3,
                            cem=CEMOptions(samples=16, elites=4, iterations=2, particles=3))
    oracle = oracle_policy(env, planner, seed=4)
    mpc = oracle.policy.mpc
    expected = {"ilqr": ilqr, "cem": cem, "cem-ilqr": cem_ilqr}[kind]
    assert mpc.optimizer is expected and mpc.horizon == oracle.policy.horizon == 6
    assert oracle.k == 2 and mpc.options.first_step_iterations == 3
    if kind == "cem":
        assert mpc.options.optimizer_options.particles == 1
        assert mpc.options.optimizer_options.seed == 4
    obs, _ = env.reset(seed=0)
    action, state = oracle.predict(obs, None, episode_start=True)
    assert isinstance(state, ReplanState) and np.all(np.isfinite(action))
