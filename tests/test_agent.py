"""Tests of the Algorithm-1 agent (agents/): config, task/cost compilation, checkpoints, the
per-episode log, the evaluation protocol, tiny real learning runs on the two-link arm and on
Gymnasium's Pendulum-v1, save/load, and (slow) actually solving the arm.

Everything runs for real: MuJoCo, CasADi, torch training, iLQR. Budgets are tiny so that the
default (non-slow) tests of this file take well under a minute on 2 cores.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import os

import casadi as ca
import gymnasium as gym
import numpy as np
import pytest
import torch
from helpers_envs import TerminateAfter
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import envs  # noqa: F401  (registers mbtsr/TwoLinkArm-v0)
from agents.checkpoint import (
    load_checkpoint,
    numpy_rng_state,
    save_checkpoint,
    set_numpy_rng_state,
)
from agents.config import AgentConfig, PlannerConfig
from agents.episode_log import LOG_COLUMNS, EpisodeLog
from agents.evaluation import (
    evaluate_policy_costs,
    evaluation_targets,
    oracle_policy,
    run_episode,
    solved_threshold,
)
from agents.jacprop_agent import JacPropAgent
from agents.planning import ReplanState, planner_cost
from agents.tasks import ObservationCost, default_task_for_env, env_spec
from mbtsr.ensemble import load_model
from mbtsr.io import atomic_write_bytes
from mbtsr.metrics import prediction_rms
from mbtsr.trajectory import Trajectory, load_trajectories

ARM = "mbtsr/TwoLinkArm-v0"

torch.set_num_threads(1)


def tiny_config(changes: dict | None = None, /, **top) -> AgentConfig:
    """A configuration that runs an episode in about a second (``changes``: dotted fields)."""
    base = {
        "collection.n_excitation_episodes": 1,
        "collection.episode_steps": 30,
        "model.ensemble_size": 2,
        "model.hidden_width": 16,
        "training.steps": 100,
        "training.batch": 64,
        "planner.horizon": 8,
        "planner.ilqr_iterations": 1,
        "planner.first_plan_iterations": 5,
        "evaluation.every": 0,
        "regularization.ltv_lambda": 2.0,
    }
    kind = (changes or {}).get("planner.kind") or top.get("planner") or "cem-ilqr"
    if kind == "cem":  # each planner's budget only where it acts (the config refuses the rest)
        del base["planner.ilqr_iterations"]
    elif kind == "cem-ilqr":
        base.update({"planner.proposal.samples": 16, "planner.proposal.elites": 4,
                     "planner.proposal.iterations": 1})
    # the paper's sampled JacProp (the default is none), unless the test names a regularizer
    top = {"progress": False, "tensorboard": False, "torch_threads": 1,
           "regularization": "sampled", **top}
    return AgentConfig.default({**base, **(changes or {})}, **top)


def pendulum_cost(obs, action):
    """Pendulum-v1 swing-up cost on the observation [cos th, sin th, th_dot]."""
    return 2.0 * (1.0 - obs[0]) + 0.1 * obs[2] ** 2 + 0.001 * ca.sumsqr(action)


def heldout_trajectories(env_id: str, state_fn, seeds, T: int, scale: float) -> list[Trajectory]:
    """Excitation trajectories from resets the agent never sees (for model-error checks)."""
    env = gym.make(env_id)
    out = []
    for s in seeds:
        rng = np.random.default_rng(s)
        low, high = env.action_space.low, env.action_space.high
        U = np.clip(scale * (high - low) / 2 * rng.standard_normal((T, low.size)), low, high)
        rec = run_episode(env, lambda o, t, U=U: U[t], seed=s, max_steps=T)
        out.append(Trajectory(state_fn(rec.obs), rec.actions))
    env.close()
    return out


# ---------------------------------------------------------------------------------- config
INT_FIELDS = {
    "collection.n_excitation_episodes": 1, "model.ensemble_size": 1, "model.hidden_width": 1,
    "training.epochs": 1, "planner.horizon": 2, "planner.ilqr_iterations": 1,
    "planner.first_plan_iterations": 1, "evaluation.episodes": 1, "regularization.n_copies": 1,
    "collection.excitation_window": 1, "collection.exploration_window": 1, "video_every": 1,
    "training.batch": 1,
    "evaluation.every": 0, "seed": 0, "evaluation.seed": 0, "torch_threads": 0,
}


@settings(max_examples=40, deadline=None)
@given(field=st.sampled_from(sorted(INT_FIELDS)), delta=st.integers(1, 10**6))
def test_config_rejects_integers_below_their_minimum(field, delta):
    with pytest.raises(ValueError, match=field):
        AgentConfig.default({field: INT_FIELDS[field] - delta})


@settings(max_examples=30, deadline=None)
@given(
    field=st.sampled_from(["training.lr", "regularization.sigma", "collection.excitation_scale",
                           "evaluation.solved_ratio", "collection.exploration_std",
                           "training.weight_decay", "planner.terminal_weight"]),
    value=st.one_of(st.just(math.nan), st.just(math.inf), st.floats(-1e6, -1e-9)),
)
def test_config_rejects_bad_floats(field, value):
    with pytest.raises(ValueError, match=field):
        AgentConfig.default({field: value})


@pytest.mark.parametrize(
    "field, value",
    [("regularization", "jacprop"), ("model.formulation", "h"), ("collection.excitation", "chirp"),
     ("regularization.ltv_lambda", "best"), ("regularization.ltv_lambda", 0.0),
     ("model.hidden_layers", 0), ("model.activations", ("tanh", "nope")),
     ("model.activations", ()), ("collection.excitation_scale", 1.5),
     ("evaluation.solved_ratio", 0.9)],
)
def test_config_rejects_bad_choices(field, value):
    with pytest.raises(ValueError, match=field):
        AgentConfig.default({field: value})


def test_config_round_trips_through_json_and_rejects_unknown_keys():
    cfg = AgentConfig.default({"model.activations": ("tanh",), "regularization.ltv_lambda": 3.0},
                              regularization="exact", seed=7)
    again = AgentConfig.from_dict(json.loads(cfg.to_json()))
    assert again == cfg
    with pytest.raises(ValueError, match="unknown AgentConfig field"):
        AgentConfig.from_dict({**cfg.to_dict(), "nonsense": 1})


# ---------------------------------------------------------------------- construction errors
class _UnboundedActionEnv(gym.Env):
    observation_space = gym.spaces.Box(-1.0, 1.0, (2,))
    action_space = gym.spaces.Box(-np.inf, np.inf, (1,))

    def reset(self, *, seed=None, options=None):
        return np.zeros(2, dtype=np.float32), {}

    def step(self, action):
        return np.zeros(2, dtype=np.float32), 0.0, False, False, {}


def test_construction_rejects_non_box_spaces_and_unbounded_actions():
    with pytest.raises(ValueError, match="action_space must be a gymnasium.spaces.Box"):
        JacPropAgent(gym.make("CartPole-v1"), tiny_config(),
                     cost_fn=lambda o, a: ca.sumsqr(o))
    with pytest.raises(ValueError, match="observation_space must be a gymnasium.spaces.Box"):
        JacPropAgent(gym.make("FrozenLake-v1"), tiny_config(), cost_fn=lambda o, a: o)
    with pytest.raises(ValueError, match="bounded"):
        JacPropAgent(_UnboundedActionEnv(), tiny_config({"collection.episode_steps": 10}),
                     cost_fn=lambda o, a: ca.sumsqr(o))
    from stable_baselines3.common.env_util import make_vec_env

    with pytest.raises(TypeError, match="not a VecEnv"):
        JacPropAgent(make_vec_env("Pendulum-v1"), tiny_config(), cost_fn=pendulum_cost)
    with pytest.raises(TypeError, match="AgentConfig"):
        JacPropAgent(gym.make("Pendulum-v1"), {"horizon": 5}, cost_fn=pendulum_cost)


@pytest.mark.parametrize(
    "cost_fn, message",
    [
        (lambda o, a: o[5] ** 2 + ca.sumsqr(a), "cost_fn.*dimension 3"),  # obs has 3 entries
        (lambda o, a: ca.mtimes(ca.DM.eye(4), o), "cost_fn.*dimension 3"),  # 4x4 weight
        (lambda o, a: ca.sumsqr(o) + a[1], "cost_fn.*action of dimension 1"),
        (lambda o, a: o * 2.0, "scalar"),
        (lambda o, a: 3.0, "does not depend"),
        ("not callable", "callable"),
    ],
)
def test_construction_rejects_costs_that_do_not_fit_the_env(cost_fn, message):
    with pytest.raises((ValueError, TypeError), match=message):
        JacPropAgent(gym.make("Pendulum-v1"), tiny_config(), cost_fn=cost_fn)


def test_an_env_id_builds_the_agent_gym_make_does(tmp_path):
    """As SB3: ``JacPropAgent("Pendulum-v1")`` is ``JacPropAgent(gym.make("Pendulum-v1"))``."""
    by_id = JacPropAgent("Pendulum-v1", tiny_config(), cost_fn=pendulum_cost)
    made = JacPropAgent(gym.make("Pendulum-v1"), tiny_config(), cost_fn=pendulum_cost)
    assert by_id.get_env().spec.id == "Pendulum-v1"
    obs = np.array([0.3, -0.95, 0.4])
    np.testing.assert_array_equal(by_id.predict(obs)[0], made.predict(obs)[0])
    with pytest.raises(gym.error.NameNotFound):
        JacPropAgent("Pendulm-v1", tiny_config())
    video = JacPropAgent(ARM, tiny_config(video=True, run_dir=str(tmp_path)))  # renders frames
    assert video.get_env().render_mode == "rgb_array"


def test_construction_rejects_bad_maps_and_video_without_rgb():
    env = gym.make("Pendulum-v1")
    assert JacPropAgent(env, tiny_config()).task.source == "learned"  # no cost: a learned reward
    with pytest.raises(ValueError, match="without obs_fn"):
        JacPropAgent(env, tiny_config(), cost_fn=pendulum_cost,
                     state_fn=lambda o: np.arctan2(o[..., 1], o[..., 0])[..., None])
    with pytest.raises(ValueError, match="obs_fn"):
        JacPropAgent(env, tiny_config(), cost_fn=pendulum_cost,
                     state_fn=lambda o: o[..., :2], obs_fn=lambda s, ref: s)  # 2 != 3 entries
    with pytest.raises(ValueError, match="rgb_array"):
        JacPropAgent(gym.make(ARM), tiny_config(video=True, run_dir="/tmp/unused"))


# ------------------------------------------------------------------------- task and costs
def test_arm_default_cost_equals_minus_the_env_reward():
    """The built-in cost c(obs_{t+1}, a_t) reproduces the env's own reward exactly."""
    env = gym.make(ARM)
    cost_fn, state_map = default_task_for_env(env)
    spec = env_spec(env)
    task = ObservationCost(cost_fn, state_map, spec, state_dim=4)
    rng = np.random.default_rng(0)
    U = rng.uniform(-1.0, 1.0, (50, 2))
    rec = run_episode(env, lambda o, t: U[t], seed=3, max_steps=50)
    np.testing.assert_allclose(task.on_observations(rec.obs[1:], rec.actions), -rec.rewards,
                               rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(state_map.state(rec.obs), rec.states)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_planner_cost_matches_numpy_formula_and_depends_only_on_the_target(data):
    env = gym.make(ARM)
    cost_fn, state_map = default_task_for_env(env)
    task = ObservationCost(cost_fn, state_map, env_spec(env), state_dim=4)
    cost = planner_cost(task, terminal_weight=2.0)  # one compiled cost, the reference a param
    f = st.floats(-3.0, 3.0)
    x = np.array(data.draw(st.lists(f, min_size=4, max_size=4)))
    u = np.array(data.draw(st.lists(st.floats(-1, 1), min_size=2, max_size=2)))
    ref = np.array(data.draw(st.lists(f, min_size=6, max_size=6)))
    Q, R = env.unwrapped.cost_Q, env.unwrapped.cost_R
    e = x - np.r_[ref[4:], 0.0, 0.0]
    stage = cost.stage_values(x[None], u[None], 0, ref)[0]
    assert stage == pytest.approx(e @ Q @ e + u @ R @ u, rel=1e-12)
    assert cost.terminal_values(x, 0, ref) == pytest.approx(2.0 * e @ Q @ e, rel=1e-12)
    ref2 = ref.copy()
    ref2[:4] += 1.0  # the state part of the reference does not matter
    assert cost.stage_values(x[None], u[None], 0, ref2)[0] == stage


# ------------------------------------------------------------------------------ checkpoints
def test_checkpoint_round_trip_restores_rng_streams_and_arrays(tmp_path):
    rng = np.random.default_rng(123)
    rng.standard_normal(5)
    torch_state = torch.get_rng_state()
    payload = {"rng": numpy_rng_state(rng), "torch_rng": torch_state,
               "x": np.arange(6.0).reshape(2, 3), "nested": {"l": [1, 2.5, "s"], "n": None}}
    save_checkpoint(tmp_path / "c.pt", payload)
    expected = rng.standard_normal(4)
    loaded = load_checkpoint(tmp_path / "c.pt")
    other = set_numpy_rng_state(np.random.default_rng(0), loaded["rng"])
    np.testing.assert_array_equal(other.standard_normal(4), expected)
    np.testing.assert_array_equal(loaded["x"].numpy(), payload["x"])
    assert torch.equal(loaded["torch_rng"], torch_state)
    assert loaded["nested"] == payload["nested"]


def test_atomic_write_keeps_the_old_file_when_the_rename_fails(tmp_path, monkeypatch):
    path = tmp_path / "f.bin"
    atomic_write_bytes(path, b"old")

    def boom(src, dst):
        raise OSError("simulated crash before the rename")

    monkeypatch.setattr(os, "replace", boom)
    with pytest.raises(OSError):
        atomic_write_bytes(path, b"new")
    assert path.read_bytes() == b"old"


def test_load_checkpoint_rejects_other_files(tmp_path):
    torch.save({"weights": torch.zeros(2)}, tmp_path / "other.pt")
    with pytest.raises(ValueError, match="not an agent checkpoint"):
        load_checkpoint(tmp_path / "other.pt")
    with pytest.raises(FileNotFoundError):
        load_checkpoint(tmp_path / "missing.pt")


def test_episode_log_writes_exact_csv_and_rewrites_it_on_resume(tmp_path):
    rows = [{"episode": i, "phase": "mpc", "episode_cost": 1.0 / 3.0 + i, "solved": i == 1}
            for i in range(3)]
    log = EpisodeLog(tmp_path, rows=[])
    for r in rows:
        log.append(r)
    with open(tmp_path / "episodes.csv") as fh:
        read = list(csv.DictReader(fh))
    assert list(read[0]) == list(LOG_COLUMNS)
    assert [float(r["episode_cost"]) for r in read] == [r["episode_cost"] for r in rows]
    assert [r["solved"] for r in read] == ["0", "1", "0"]
    EpisodeLog(tmp_path, rows=rows[:2])  # a resumed run restored two rows
    with open(tmp_path / "episodes.csv") as fh:
        assert len(list(csv.DictReader(fh))) == 2
    with pytest.raises(ValueError, match="unknown log column"):
        log.append({"episode": 3, "bogus": 1.0})


# ------------------------------------------------------------------------------- evaluation
def test_evaluation_targets_are_the_envs_own_draws_and_validated():
    targets = evaluation_targets(3, seed=5)
    env = gym.make(ARM)
    for i, t in enumerate(targets):
        _, info = env.reset(seed=5 + i)
        np.testing.assert_array_equal(t, info["target"])
    np.testing.assert_array_equal(np.asarray(evaluation_targets(3, seed=5)), np.asarray(targets))
    for bad in (0, -1, 2.5, True):
        with pytest.raises(ValueError, match="n must be"):
            evaluation_targets(bad, seed=0)
    with pytest.raises(ValueError, match="seed"):
        evaluation_targets(2, seed=-1)


def test_evaluate_policy_costs_matches_a_hand_loop_and_stops_early():
    env = gym.make(ARM, episode_steps=20)
    targets = [np.array([0.3, -0.2]), np.array([-0.5, 0.4]), np.array([0.1, 0.1])]
    policy = lambda obs: np.array([0.2, -0.1])  # noqa: E731
    costs = evaluate_policy_costs(policy, env, targets, seed=11)
    for i, tgt in enumerate(targets):
        env.reset(seed=11 + i, options={"target": tgt})
        total, done = 0.0, False
        while not done:
            _, r, term, trunc, _ = env.step(np.array([0.2, -0.1], dtype=np.float32))
            total -= r
            done = term or trunc
        assert costs[i] == pytest.approx(total, rel=1e-12)
    part = evaluate_policy_costs(policy, env, targets, seed=11, stop_above=costs[0] * 0.5)
    assert len(part) == 1 and part[0] == costs[0]
    with pytest.raises(ValueError, match="oracle"):
        solved_threshold(-1.0)
    assert solved_threshold(10.0) == pytest.approx(12.0)


def test_oracle_mpc_with_the_true_model_reaches_the_target():
    env = gym.make(ARM, episode_steps=40)
    target = np.array([0.6, -0.4])
    policy = oracle_policy(env, PlannerConfig(kind="ilqr", horizon=15, ilqr_iterations=2,
                                              first_plan_iterations=15))
    oracle = evaluate_policy_costs(policy, env, [target], seed=0)[0]
    idle = evaluate_policy_costs(lambda o: np.zeros(2), env, [target], seed=0)[0]
    rec_state = {"U": None}

    def act(obs, t):
        a, rec_state["U"] = policy.predict(obs, rec_state["U"], episode_start=t == 0)
        return a

    rec = run_episode(env, act, seed=0, options={"target": target})
    assert np.abs(rec.states[-1, :2] - target).max() < 0.05
    assert oracle < 0.25 * idle


def test_oracle_takes_the_agents_state_maps_and_refuses_conflicting_ones():
    """On the arm (whose true model lives in the agent's model state) ``state_fn``/``obs_fn``
    equal to the arm's own map plan exactly as the default map; conflicting maps are refused."""
    import casadi as ca

    from agents.tasks import StateMap

    env = gym.make(ARM, episode_steps=10)
    obs, _ = env.reset(seed=0, options={"target": np.array([0.6, -0.4])})

    def state_fn(o):
        return np.asarray(o)[..., :4]

    def obs_fn(s, ref):
        return ca.vertcat(s, ref[4:6])

    kw = {"planner": PlannerConfig(kind="ilqr", horizon=8, ilqr_iterations=2,
                                   first_plan_iterations=5)}
    a_default, _ = oracle_policy(env, **kw).predict(obs, None, episode_start=True)
    a_maps, _ = oracle_policy(env, state_fn=state_fn, obs_fn=obs_fn, **kw).predict(
        obs, None, episode_start=True)
    np.testing.assert_allclose(a_maps, a_default, rtol=0, atol=1e-9)
    with pytest.raises(ValueError, match="not both"):
        oracle_policy(env, state_map=StateMap(prefix=4), state_fn=state_fn, obs_fn=obs_fn, **kw)
    with pytest.raises(ValueError, match="obs_fn was given without state_fn"):
        oracle_policy(env, obs_fn=obs_fn, **kw)


@pytest.mark.parametrize("window", [1, 8])
def test_exploration_noise_has_the_stated_std_and_memory(window):
    """Training-rollout noise: std ``exploration_std`` x the half-range; white noise has no
    lag-1 correlation, a moving average of ``W`` white samples has ``(W - 1) / W``."""
    env = gym.make(ARM, episode_steps=30)
    agent = JacPropAgent(env, tiny_config({"collection.exploration_std": 0.2,
                                           "collection.exploration_window": window}))
    noise = agent.collector.exploration_noise(20000, seed=7)[window:]  # after the filter's ramp-up
    half = 0.5 * (agent.spec.u_max - agent.spec.u_min)
    np.testing.assert_allclose(noise.std(0), 0.2 * half, rtol=0.1)
    lag1 = [np.corrcoef(noise[1:, j], noise[:-1, j])[0, 1] for j in range(noise.shape[1])]
    np.testing.assert_allclose(lag1, (window - 1) / window, atol=0.03)
    again = agent.collector.exploration_noise(20000, seed=7)[window:]
    np.testing.assert_array_equal(noise, again)  # same seed, same noise


# ----------------------------------------------------------------- learning: the arm (tiny)
@pytest.fixture(scope="module")
def arm_run(tmp_path_factory):
    """Three tiny episodes on the arm with TensorBoard, checkpoints and a 2-episode evaluation;
    the model error on held-out data is recorded after the first and the last episode."""
    run_dir = tmp_path_factory.mktemp("arm_run")
    env = gym.make(ARM, episode_steps=30)
    cfg = tiny_config({"evaluation.every": 1, "evaluation.episodes": 2},
                      run_dir=str(run_dir), tensorboard=True, seed=3)
    agent = JacPropAgent(env, cfg)
    heldout = heldout_trajectories(ARM, lambda o: o[:, :4], [901, 902], 30, 0.3)
    agent.learn(episodes=1, progress_bar=False)
    err_first = prediction_rms(agent.model, heldout)
    agent.learn(episodes=2, progress_bar=False)
    err_last = prediction_rms(agent.model, heldout)
    return agent, run_dir, err_first, err_last


def test_tiny_arm_run_writes_the_logs_and_files(arm_run):
    agent, run_dir, _, _ = arm_run
    with open(run_dir / "episodes.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert [int(r["episode"]) for r in rows] == [0, 1, 2]
    assert [r["phase"] for r in rows] == ["excitation", "mpc", "mpc"]
    assert [int(r["env_steps"]) for r in rows] == [30, 60, 90]
    for r in rows[1:]:  # the model has seen data: errors on the NEW trajectory are logged
        assert 0 < float(r["one_step_rms"]) < math.inf
        assert 0 < float(r["jacobian_error"]) < math.inf
        assert int(r["eval_episodes_run"]) >= 1 and float(r["cost_ratio"]) > 0
    for c in ("time_rollout", "time_planning", "time_ltv", "time_training", "time_total"):
        assert all(float(r[c]) >= 0 for r in rows)
    assert float(rows[1]["time_planning"]) > 0  # the MPC phase plans
    assert any(f.name.startswith("events.out.tfevents") for f in (run_dir / "tb").iterdir())
    data = load_trajectories(run_dir / "data.npz")
    assert len(data) == 3 and all(d.x.shape == (31, 4) for d in data)
    model = load_model(run_dir / "model.pt")
    x, u = data[0].inputs
    np.testing.assert_array_equal(model.step(x, u), agent.model.step(x, u))
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["episodes_done"] == 3 and summary["oracle_cost"] > 0
    assert set(summary["wall_seconds_per_phase"]) >= {"rollout", "ltv", "training", "planning"}


def test_a_fresh_agent_refuses_a_run_dir_that_holds_another_run(arm_run):
    """Nothing is lost: a new agent pointed at a finished run's folder fails before writing."""
    agent, run_dir, _, _ = arm_run
    before = {p.name: p.read_bytes() for p in run_dir.iterdir() if p.is_file()}
    fresh = JacPropAgent(gym.make(ARM, episode_steps=30), agent.config)
    with pytest.raises(ValueError, match="holds another run's checkpoint.*JacPropAgent.load"):
        fresh.learn(episodes=1, progress_bar=False)
    assert {p.name: p.read_bytes() for p in run_dir.iterdir() if p.is_file()} == before
    assert fresh.env_steps == 0


def test_tiny_arm_run_improves_the_model_on_heldout_data(arm_run):
    _, _, err_first, err_last = arm_run
    assert err_last < 0.8 * err_first


def test_save_load_round_trip_gives_identical_predictions(arm_run, tmp_path):
    agent, _, _, _ = arm_run
    path = agent.save(tmp_path / "agent.pt")
    loaded = JacPropAgent.load(path)  # no env: act only
    obs = np.array([0.1, -0.2, 0.3, 0.0, 0.5, -0.4])
    a1, s1 = agent.predict(obs, episode_start=True)
    a2, s2 = loaded.predict(obs, episode_start=True)
    np.testing.assert_array_equal(a1, a2)
    np.testing.assert_array_equal(s1, s2)
    b1, _ = agent.predict(obs + 0.01, s1)
    b2, _ = loaded.predict(obs + 0.01, s2)
    np.testing.assert_array_equal(b1, b2)
    assert loaded.episodes_done == 3 and len(loaded.trajectories) == 3
    assert json.dumps(loaded.logger_rows) == json.dumps(agent.logger_rows)  # NaN-safe
    with pytest.raises(ValueError, match="loaded without an env"):
        loaded.learn(episodes=1)
    with pytest.raises(ValueError, match="does not match"):
        JacPropAgent.load(path, env=gym.make("Pendulum-v1"))


@settings(max_examples=20, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(shape=st.sampled_from([(5,), (7,), (2, 5), (2, 2, 6), ()]))  # [B, 6]: a batch
def test_predict_rejects_observations_of_the_wrong_shape(arm_run, shape):
    agent = arm_run[0]
    with pytest.raises(ValueError, match="observation"):
        agent.predict(np.zeros(shape))


def test_predict_rejects_a_foreign_warm_start(arm_run):
    agent = arm_run[0]
    with pytest.raises(ValueError, match="state"):
        agent.predict(np.zeros(6), state=np.zeros((3, 2)))


def test_video_of_an_episode_is_written(tmp_path):
    env = gym.make(ARM, episode_steps=8, render_mode="rgb_array", width=64, height=48)
    agent = JacPropAgent(env, tiny_config({"collection.episode_steps": 8, "training.steps": 2},
                                          run_dir=str(tmp_path), video=True, video_every=1))
    agent.learn(episodes=1, progress_bar=False)
    videos = list((tmp_path / "videos").iterdir())
    assert len(videos) == 1 and videos[0].stem == "episode_0000"
    assert videos[0].stat().st_size > 0


# --------------------------------------------------------- learning: Pendulum-v1 (own env)
def test_tiny_pendulum_run_with_a_user_cost(tmp_path):
    """The README's "use your own environment" example on gymnasium's Pendulum-v1."""
    env = gym.make("Pendulum-v1")
    cfg = tiny_config({"collection.episode_steps": 40, "training.steps": 80},
                      run_dir=str(tmp_path), seed=1)
    agent = JacPropAgent(env, cfg, cost_fn=pendulum_cost)
    assert agent.state_dim == 3 and agent.spec.u_max[0] == 2.0
    heldout = heldout_trajectories("Pendulum-v1", lambda o: o, [501, 502], 40, 0.5)
    agent.learn(episodes=1, progress_bar=False)
    err_first = prediction_rms(agent.model, heldout)
    agent.learn(episodes=2, progress_bar=False)
    err_last = prediction_rms(agent.model, heldout)
    assert err_last < 0.8 * err_first
    rows = agent.logger_rows
    assert [r["phase"] for r in rows] == ["excitation", "mpc", "mpc"]
    assert math.isnan(rows[1]["jacobian_error"])  # Pendulum offers no linearize
    assert all(math.isfinite(r["episode_cost"]) and r["env_steps"] == 40 * (i + 1)
               for i, r in enumerate(rows))
    action, _ = agent.predict(env.reset(seed=0)[0])
    assert action.shape == (1,) and -2.0 <= action[0] <= 2.0
    with pytest.raises(ValueError, match=r"its own cost_fn, .*pass cost_fn= to load"):
        JacPropAgent.load(tmp_path / "checkpoint.pt", env=env)
    again = JacPropAgent.load(tmp_path / "checkpoint.pt", env=env, cost_fn=pendulum_cost)
    np.testing.assert_array_equal(again.predict(np.array([1.0, 0.0, 0.0]))[0],
                                  agent.predict(np.array([1.0, 0.0, 0.0]))[0])


# --------------------------------------------------------------------------- slow: solving
@pytest.mark.slow
def test_default_agent_solves_the_arm_within_30_episodes(tmp_path):
    env = gym.make(ARM)
    cfg = AgentConfig.default({"evaluation.stop_when_solved": True}, run_dir=str(tmp_path),
                              progress=False, torch_threads=1)
    agent = JacPropAgent(env, cfg)
    agent.learn(episodes=30, progress_bar=False)
    summary = agent.summary()
    assert summary["episodes_to_solve"] is not None, summary
    assert summary["final_cost_ratio"] <= 1.2


# --------------------------------------------------------------------------- user maps
def _pendulum_angle_state(obs):
    """obs [..., 3] -> [..., 2] = (angle, velocity), written for batches."""
    obs = np.asarray(obs)
    return np.stack([np.arctan2(obs[..., 1], obs[..., 0]), obs[..., 2]], axis=-1)


def _pendulum_obs_of_state(s, ref):
    return ca.vertcat(ca.cos(s[0]), ca.sin(s[0]), s[1])


def test_state_fn_is_checked_on_a_batch_at_construction():
    env = gym.make("Pendulum-v1")

    def per_observation(obs):  # obs[0] of a batch is a row, not the cosine
        return np.array([np.arctan2(obs[1], obs[0]), obs[2]])

    with pytest.raises(ValueError, match=r"state_fn must .*batch of observations \[B, obs_dim\]"):
        JacPropAgent(env, tiny_config(), cost_fn=pendulum_cost, state_fn=per_observation,
                     obs_fn=_pendulum_obs_of_state)
    agent = JacPropAgent(env, tiny_config(), cost_fn=pendulum_cost,
                         state_fn=_pendulum_angle_state, obs_fn=_pendulum_obs_of_state)
    assert agent.state_dim == 2


def test_load_explains_a_missing_state_fn(tmp_path):
    env = gym.make("Pendulum-v1")
    agent = JacPropAgent(env, tiny_config({"collection.episode_steps": 10}), cost_fn=pendulum_cost,
                         state_fn=_pendulum_angle_state, obs_fn=_pendulum_obs_of_state)
    agent.learn(episodes=1, progress_bar=False)
    path = agent.save(tmp_path / "a.pt")
    with pytest.raises(ValueError, match=r"its own state_fn, obs_fn,.*pass state_fn=, obs_fn="):
        JacPropAgent.load(path, env=env, cost_fn=pendulum_cost)
    with pytest.raises(ValueError, match=r"its own cost_fn, state_fn, obs_fn,"):
        JacPropAgent.load(path)  # an unregistered task: every missing function is named
    with pytest.raises(ValueError, match="dimension 3.*trained on dimension 2"):
        JacPropAgent.load(path, env=env, cost_fn=pendulum_cost, state_fn=lambda o: np.asarray(o),
                          obs_fn=lambda s, r: s)
    again = JacPropAgent.load(path, env=env, cost_fn=pendulum_cost,
                              state_fn=_pendulum_angle_state, obs_fn=_pendulum_obs_of_state)
    obs = np.array([0.0, 1.0, 0.5])
    np.testing.assert_array_equal(again.predict(obs)[0], agent.predict(obs)[0])


# --------------------------------------------------------------------------- the user's task
def test_learn_with_an_env_step_budget_cuts_the_last_episode():
    env = gym.make("Pendulum-v1")
    agent = JacPropAgent(env, tiny_config({"collection.episode_steps": 20}), cost_fn=pendulum_cost)
    agent.learn(total_timesteps=45, progress_bar=False)
    assert [t.T for t in agent.trajectories] == [20, 20, 5]
    assert agent.env_steps == 45 == agent.logger_rows[-1]["env_steps"]
    agent.learn(100, episodes=1, progress_bar=False)  # the episode count stops first
    assert agent.env_steps == 65
    agent.learn(7, progress_bar=False)  # SB3's positional total_timesteps: exactly 7 steps
    assert agent.env_steps == 72 and agent.trajectories[-1].T == 7
    with pytest.raises(ValueError, match="total_timesteps"):
        agent.learn(total_timesteps=-1)
    with pytest.raises(ValueError, match="give total_timesteps"):
        agent.learn()


def test_solved_return_decides_from_the_envs_own_rewards():
    """Returns per evaluation episode equal an independent replay of the deterministic policy;
    the success criterion is the mean return against ``solved_return``."""
    env = gym.make("Pendulum-v1")
    cfg = tiny_config({"collection.episode_steps": 15, "evaluation.every": 1,
                       "evaluation.episodes": 2, "evaluation.seed": 7})
    easy = JacPropAgent(env, cfg.replace({"evaluation.solved_return": -1e9}), cost_fn=pendulum_cost)
    easy.learn(episodes=2, progress_bar=False)
    row = easy.logger_rows[0]
    assert row["solved"] and len(row["eval_returns"]) == 2
    assert row["eval_return"] == pytest.approx(np.mean(row["eval_returns"]))
    summary = easy.summary()
    assert summary["episodes_to_solve"] == 1 and summary["env_steps_to_solve"] == 15
    assert summary["solved_criterion"] == "mean_return"
    # independent replay of the final policy on the evaluation episodes
    eval_env = gym.make("Pendulum-v1")
    replay = [float(np.sum(easy.rollout_policy(eval_env, seed=7 + i).rewards)) for i in range(2)]
    np.testing.assert_allclose(easy.logger_rows[-1]["eval_returns"], replay, rtol=1e-12)
    hard = JacPropAgent(env, cfg.replace({"evaluation.solved_return": 0.0}), cost_fn=pendulum_cost)
    hard.learn(episodes=2, progress_bar=False)  # Pendulum's rewards are <= 0 and not all 0
    assert not any(r["solved"] for r in hard.logger_rows)
    assert hard.summary()["episodes_to_solve"] is None


def test_rollout_steps_shortens_training_rollouts_not_evaluation():
    """``collection.rollout_steps``: every training rollout (excitation and MPC) is that long and
    starts from a reset, the budget counts its steps, and the evaluation episodes keep the
    episode's length (their returns equal a replay of that length)."""
    env = gym.make("Pendulum-v1")
    cfg = tiny_config({"collection.episode_steps": 15, "collection.rollout_steps": 6,
                       "evaluation.every": 2, "evaluation.episodes": 1})
    agent = JacPropAgent(env, cfg, cost_fn=pendulum_cost)
    agent.learn(total_timesteps=20, progress_bar=False)
    assert [t.T for t in agent.trajectories] == [6, 6, 6, 2]  # the last one cut by the budget
    assert agent.env_steps == 20 and [r["phase"] for r in agent.logger_rows] == [
        "excitation", "mpc", "mpc", "mpc"]
    assert len({t.meta["seed"] for t in agent.trajectories}) == 4  # a reset per rollout
    replay = agent.rollout_policy(gym.make("Pendulum-v1"), seed=cfg.evaluation.seed)
    assert len(replay.rewards) == 15
    assert agent.logger_rows[-1]["eval_returns"] == [pytest.approx(float(np.sum(replay.rewards)),
                                                                   rel=1e-12)]
    with pytest.raises(ValueError, match="collection.rollout_steps"):
        tiny_config({"collection.rollout_steps": 1})
    with pytest.raises(ValueError, match="rollout_steps=15 has no effect"):
        tiny_config({"collection.episode_steps": 15, "collection.rollout_steps": 15})
    with pytest.warns(UserWarning, match="rollout_steps=300 has no effect"):
        JacPropAgent(gym.make("Pendulum-v1"), tiny_config({"collection.episode_steps": None,
                                                           "collection.rollout_steps": 300}),
                     cost_fn=pendulum_cost)  # Pendulum-v1's TimeLimit: 200 steps


def test_continue_rollouts_hands_the_episode_on_across_updates():
    """``collection.continue_rollouts``: rollouts of 6 steps continue one env episode of 15
    (6 + 6 + 3, then a reset), with a model update between them. Replaying the first episode's
    recorded actions from its reset in a fresh env reproduces every segment's states, so nothing
    reset or skipped a step between the segments."""
    cfg = tiny_config({"collection.episode_steps": 15, "collection.rollout_steps": 6,
                       "collection.continue_rollouts": True, "evaluation.every": 0})
    agent = JacPropAgent(gym.make("Pendulum-v1"), cfg, cost_fn=pendulum_cost)
    agent.learn(total_timesteps=20, progress_bar=False)
    trajs = agent.trajectories
    assert [t.T for t in trajs] == [6, 6, 3, 5]
    assert [t.meta["seed"] is None for t in trajs] == [False, True, True, False]
    assert len(agent.logger_rows) == 4 and all(r["train_steps"] > 0 for r in agent.logger_rows)
    U = np.concatenate([t.u for t in trajs[:3]])
    rec = run_episode(gym.make("Pendulum-v1"), lambda obs, t: U[t], seed=trajs[0].meta["seed"],
                      max_steps=15)
    X = agent.state_map.state(rec.obs)
    np.testing.assert_allclose(np.concatenate([trajs[0].x, trajs[1].x[1:], trajs[2].x[1:]]), X,
                               rtol=1e-6, atol=1e-6)
    agent.learn(total_timesteps=2, progress_bar=False)  # a new call: from a reset
    assert agent.trajectories[-1].meta["seed"] is not None
    with pytest.raises(ValueError, match="continue_rollouts=True needs collection.rollout_steps"):
        tiny_config({"collection.continue_rollouts": True})


def test_continue_rollouts_resets_after_termination_or_a_foreign_reset():
    """An episode that terminates is not continued, and neither is one whose env was reset by
    someone else between two rollouts (a warning; the TimeLimit's step count tells)."""
    cfg = tiny_config({"collection.episode_steps": 15, "collection.rollout_steps": 6,
                       "collection.continue_rollouts": True, "evaluation.every": 0})
    ends = JacPropAgent(TerminateAfter(gym.make("Pendulum-v1"), 4), cfg, cost_fn=pendulum_cost)
    ends.learn(total_timesteps=12, progress_bar=False)
    assert [t.T for t in ends.trajectories] == [4, 4, 4]
    assert all(t.meta["seed"] is not None for t in ends.trajectories)

    agent = JacPropAgent(gym.make("Pendulum-v1"), cfg, cost_fn=pendulum_cost)

    def reset_once(info):
        if info["row"]["episode"] == 0:
            agent.env.reset(seed=5)

    with pytest.warns(UserWarning, match="stepped or reset since the last training rollout"):
        agent.learn(total_timesteps=12, callback=reset_once, progress_bar=False)
    assert [t.meta["seed"] is None for t in agent.trajectories] == [False, False]


def test_terminal_cost_is_the_users_function_of_the_predicted_observation():
    env = gym.make("Pendulum-v1")

    def terminal(obs):
        return 5.0 * (1.0 - obs[0]) + obs[2] ** 2

    agent = JacPropAgent(env, tiny_config({"planner.terminal_weight": 2.0}), cost_fn=pendulum_cost,
                         state_fn=_pendulum_angle_state, obs_fn=_pendulum_obs_of_state,
                         terminal_cost_fn=terminal)
    rng = np.random.default_rng(0)
    for _ in range(5):
        s = rng.normal(size=2)
        ref = rng.normal(size=3)
        expected = 5.0 * (1.0 - np.cos(s[0])) + s[1] ** 2
        assert float(agent.task_cost.terminal(s, ref)) == pytest.approx(expected, rel=1e-12)
    with pytest.raises(ValueError, match="terminal_cost_fn must return a scalar"):
        JacPropAgent(env, tiny_config(), cost_fn=pendulum_cost, terminal_cost_fn=lambda o: o)


def test_termination_fn_is_checked_on_a_batch():
    env = gym.make("Pendulum-v1")
    with pytest.raises(ValueError, match="termination_fn must accept a batch"):
        JacPropAgent(env, tiny_config(), cost_fn=pendulum_cost,
                     termination_fn=lambda obs: bool(obs[0] > 0))
    with pytest.raises(ValueError, match="termination_fn.*one bool per observation"):
        JacPropAgent(env, tiny_config(), cost_fn=pendulum_cost,
                     termination_fn=lambda obs: obs[..., 0, 0] > 0)
    agent = JacPropAgent(env, tiny_config(), cost_fn=pendulum_cost,
                         termination_fn=lambda obs: np.abs(obs[..., 2]) > 7.9)
    assert agent.termination_fn is not None


def test_cem_planner_runs_the_same_mpc_and_respects_the_termination_fn():
    """planner='cem' plans with forward predictions only; a termination predicted at every
    state leaves only the first stage cost in every plan's cost."""
    env = gym.make("Pendulum-v1")
    cfg = tiny_config({"planner.cem.samples": 16, "planner.cem.elites": 4,
                       "planner.cem.iterations": 1, "collection.episode_steps": 12}, planner="cem")
    agent = JacPropAgent(env, cfg, cost_fn=pendulum_cost)
    agent.learn(episodes=2, progress_bar=False)
    assert agent.logger_rows[-1]["phase"] == "mpc"
    obs = env.reset(seed=0)[0]
    a1, plan = agent.predict(obs)
    a2, _ = agent.predict(obs)
    np.testing.assert_array_equal(a1, a2)  # seeded: predict is a pure function
    assert plan.shape == (cfg.planner.horizon, 1) and -2.0 <= a1[0] <= 2.0
    assert agent.policy.last_result.status in ("converged", "max_iter")
    ended = JacPropAgent(env, cfg, cost_fn=pendulum_cost,
                         termination_fn=lambda o: np.ones(o.shape[:-1], dtype=bool))
    ended.model.load_state_dict(agent.model.state_dict())
    ended.freeze()  # train -> freeze -> plan, as learn() does after its training round
    ended.predict(obs)
    res = ended.policy.last_result
    first_stage = float(agent.task_cost.stage(agent.state_map.state(obs), res.U[0], obs))
    assert res.cost == pytest.approx(first_stage, rel=1e-9)


@pytest.mark.parametrize("probabilistic", [False, True])
def test_cem_with_trajectory_sampling_scores_plans_under_every_member(probabilistic):
    """planner.propagation='ts': CEM plans on the trajectory-sampling view of the frozen
    ensemble, each sequence rolled out once per member (2 members, 2 particles); for
    deterministic members the returned cost is the mean of the members' costs of the returned
    plan. Probabilistic members sample their noise (seeded: predict stays a pure function)."""
    env = gym.make("Pendulum-v1")
    cfg = tiny_config({"planner.cem.samples": 16, "planner.cem.elites": 4,
                       "planner.cem.iterations": 1, "planner.cem.particles": 2,
                       "planner.propagation": "ts", "model.probabilistic": probabilistic,
                       "collection.episode_steps": 12}, planner="cem")
    agent = JacPropAgent(env, cfg, cost_fn=pendulum_cost)
    agent.learn(episodes=2, progress_bar=False)
    ts = agent.policy.model
    assert type(ts).__name__ == "TrajectorySampling" and ts.noise == probabilistic
    obs = env.reset(seed=0)[0]
    a1, _ = agent.predict(obs)
    np.testing.assert_array_equal(a1, agent.predict(obs)[0])  # seeded
    if not probabilistic:
        res = agent.policy.last_result
        X = np.repeat(obs[None], 2, 0)[:, None]  # row r follows member r mod 2
        for t, u in enumerate(res.U):
            X = np.concatenate([X, ts.step(X[:, -1], np.repeat(u[None], 2, 0), t)[:, None]], 1)
        members = agent.planning_model.member_predictions(obs, res.U[0])
        np.testing.assert_allclose(X[:, 1], members, rtol=1e-12)
        costs = [float(agent.planner_cost.total(X[i], res.U, 0, obs)) for i in range(2)]
        assert res.cost == pytest.approx(np.mean(costs), rel=1e-9)
    with pytest.raises(ValueError, match="planner.propagation='ts' .* needs planner.kind='cem'"):
        cfg.replace({"planner.kind": "ilqr"})


@pytest.mark.parametrize("explore_on", ["state", "cost"])
def test_explore_weight_steers_training_rollouts_and_not_evaluation(explore_on):
    """collection.explore_weight: training rollouts plan with the CEM proposal ranked by cost
    minus the members' disagreement (its own MPC), evaluation (predict) plans without it. Two
    agents with the same seed share the excitation episode, hence the model: their evaluation
    plans are identical, their training rollouts' plans are not; with weight 0 the training
    actor is the evaluation actor."""
    env = gym.make("Pendulum-v1")
    base = {"collection.exploration_std": 0.0, "planner.proposal.samples": 32,
            "planner.proposal.elites": 4}
    plain = JacPropAgent(env, tiny_config(base), cost_fn=pendulum_cost)
    agent = JacPropAgent(env, tiny_config({**base, "collection.explore_weight": 2.0,
                                           "collection.explore_on": explore_on}),
                         cost_fn=pendulum_cost)
    assert plain.explorer is plain.actor and agent.explorer is not agent.actor
    assert agent.explorer.policy.mpc.options.optimizer_options.cem.explore_weight == 2.0
    assert agent.explorer.policy.mpc.options.optimizer_options.cem.explore_on == explore_on
    assert agent.actor.policy.mpc.options.optimizer_options.cem.explore_weight == 0.0
    for a in (plain, agent):
        a.learn(episodes=1, progress_bar=False)  # the excitation episode and the update
    obs = env.reset(seed=3)[0]
    np.testing.assert_array_equal(agent.predict(obs)[0], plain.predict(obs)[0])
    explored = agent.explorer.predict(obs, None, episode_start=True)[1]
    assert not np.allclose(explored, plain.predict(obs)[1])
    for a in (plain, agent):
        a.learn(episodes=1, progress_bar=False)  # one training rollout with the planner
    assert agent.logger_rows[-1]["phase"] == "mpc"
    np.testing.assert_array_equal(agent.trajectories[0].u, plain.trajectories[0].u)
    assert not np.allclose(agent.trajectories[1].u, plain.trajectories[1].u)
    with pytest.raises(ValueError, match="collection.explore_weight"):
        tiny_config({**base, "collection.explore_weight": 1.0, "model.ensemble_size": 1})
    ts = JacPropAgent(env, tiny_config(  # trajectory sampling: the explorer plans on the view
        {"planner.cem.samples": 16, "planner.cem.elites": 4, "planner.cem.iterations": 1,
         "planner.cem.particles": 2, "planner.propagation": "ts",
         "collection.explore_weight": 1.0, "collection.explore_on": explore_on},
        planner="cem"), cost_fn=pendulum_cost)
    ts.learn(episodes=2, progress_bar=False)
    assert ts.logger_rows[-1]["phase"] == "mpc"
    assert type(ts.explorer.policy.mpc.model).__name__ == "TrajectorySampling"
    ts.explorer.predict(env.reset(seed=0)[0], None, episode_start=True)
    assert ts.explorer.policy.last_result.status in ("converged", "max_iter")


def test_refit_normalization_keeps_the_function_and_follows_the_data():
    """The ensemble's statistics move to the new data while predictions and Jacobians stay
    those of the old parameterization (float32 rounding)."""
    env = gym.make("Pendulum-v1")
    agent = JacPropAgent(env, tiny_config({"collection.episode_steps": 20}, renormalize=False),
                         cost_fn=pendulum_cost)
    agent.learn(episodes=1, progress_bar=False)
    model = agent.model
    more = heldout_trajectories("Pendulum-v1", lambda o: o, [7, 8], 30, 1.0)
    x = np.concatenate([t.x[:-1] for t in more])
    u = np.concatenate([t.u for t in more])
    before = model.step(x, u)
    A0, B0 = model.jacobians(x, u)
    old_std = model.in_std.clone()
    model.refit_normalization(agent.trajectories + more)
    xu = np.concatenate([np.concatenate([t.x[:-1], t.u], 1) for t in agent.trajectories + more])
    np.testing.assert_allclose(model.in_std.numpy(), xu.std(0), rtol=1e-5)
    assert not torch.allclose(old_std, model.in_std)
    scale = np.abs(before).max()
    np.testing.assert_allclose(model.step(x, u), before, atol=2e-5 * scale)
    A1, B1 = model.jacobians(x, u)
    np.testing.assert_allclose(A1, A0, atol=1e-4 * np.abs(A0).max())
    np.testing.assert_allclose(B1, B0, atol=1e-4 * np.abs(B0).max())


def test_replan_every_executes_each_plan_open_loop():
    """With replan_every=k the actions between solves are exactly the plan's next actions."""
    env = gym.make("Pendulum-v1")
    agent = JacPropAgent(env, tiny_config({"collection.episode_steps": 12,
                                           "planner.replan_every": 3}),
                         cost_fn=pendulum_cost)
    agent.learn(episodes=1, progress_bar=False)
    solves = []
    original = agent.policy.mpc.solve

    def counting_solve(*args, **kwargs):
        res = original(*args, **kwargs)
        solves.append(np.asarray(res.U, dtype=float).copy())
        return res

    agent.policy.mpc.solve = counting_solve
    rec = agent.rollout_policy(env, seed=4)
    assert len(solves) == 4  # steps 0, 3, 6, 9 of 12
    for j, U in enumerate(solves):
        np.testing.assert_allclose(rec.actions[3 * j: 3 * j + 3],
                                   np.clip(U[:3], -2, 2).astype(np.float32), rtol=1e-6)


def _feedback_agent(kind: str) -> tuple[gym.Env, JacPropAgent]:
    """A Pendulum agent after one episode, re-planning every 3 steps with feedback."""
    env = gym.make("Pendulum-v1")
    agent = JacPropAgent(env, tiny_config({"collection.episode_steps": 12, "planner.kind": kind,
                                           "planner.replan_every": 3,
                                           "planner.replan_feedback": True}),
                         cost_fn=pendulum_cost)
    agent.learn(episodes=1, progress_bar=False)
    return env, agent


@pytest.mark.parametrize("kind", ["ilqr", "cem-ilqr"])
def test_replan_feedback_follows_ilqrs_local_policy_between_solves(kind):
    """With planner.replan_feedback the actions between solves are the last solve's local
    policy ``clip(U_i + K_i (x - X_i))`` at the observed model state ``x``, recomputed here from
    each solve's result; a solve's own step plays its first control."""
    env, agent = _feedback_agent(kind)
    solves = []
    original = agent.policy.mpc.solve

    def recording_solve(*args, **kwargs):
        solves.append(original(*args, **kwargs))
        return solves[-1]

    agent.policy.mpc.solve = recording_solve
    rec = agent.rollout_policy(env, seed=4)
    assert len(solves) == 4  # steps 0, 3, 6, 9 of 12
    corrected = 0
    for j, res in enumerate(solves):
        for i in range(3):
            x = agent.state_map.state(np.asarray(rec.obs[3 * j + i], dtype=float))
            u = res.U[i] + (res.K[i] @ (x - res.X[i]) if i else 0.0)
            np.testing.assert_allclose(rec.actions[3 * j + i],
                                       np.clip(u, -2, 2).astype(np.float32), rtol=1e-5,
                                       atol=1e-6)
            corrected += bool(i) and not np.allclose(np.clip(u, -2, 2), np.clip(res.U[i], -2, 2))
    assert corrected > 0  # the learned model is not the pendulum: the gains act


def test_oracle_replan_feedback_plans_from_the_true_state():
    """The oracle (true MuJoCo state, TrueStatePolicy) with replan_feedback: the replayed
    actions are ``clip(U_i + K_i (x - X_i))`` at the env's true lifted state ``x``; the model
    is the env, so the state stays on the plan and the correction is at rounding level."""
    from agents import tasks

    task = tasks.inverted_pendulum(max_episode_steps=9)
    env = task.make_env()
    agent = JacPropAgent(env, tiny_config({"planner.kind": "ilqr", "planner.replan_every": 3,
                                           "planner.replan_feedback": True}),
                         **task.agent_kwargs())
    oracle = agent.evaluator.oracle_policy(env)
    solves, original = [], oracle.policy.mpc.solve

    def recording_solve(*args, **kwargs):
        solves.append(original(*args, **kwargs))
        return solves[-1]

    oracle.policy.mpc.solve = recording_solve
    obs, _ = env.reset(seed=3)
    state, lo, hi = None, env.action_space.low, env.action_space.high
    for t in range(9):
        x = oracle.policy.model_state(obs)
        action, state = oracle.predict(obs, state, episode_start=t == 0)
        res, i = solves[-1], t % 3
        assert len(solves) == t // 3 + 1
        np.testing.assert_allclose(action, np.clip(res.U[i] + res.K[i] @ (x - res.X[i]), lo, hi),
                                   rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(x, res.X[i], atol=1e-6)  # the true model: on the plan
        obs, *_ = env.step(action)


def test_evaluation_schedule_every_k_episodes_and_at_the_end_of_learn():
    env = gym.make("Pendulum-v1")
    agent = JacPropAgent(env, tiny_config({"collection.episode_steps": 10, "evaluation.every": 4,
                                           "evaluation.episodes": 1}),
                         cost_fn=pendulum_cost)
    agent.learn(episodes=3, progress_bar=False)
    assert [r["episode"] for r in agent.logger_rows if r["eval_returns"]] == [0, 2]
    agent.learn(total_timesteps=25, progress_bar=False)  # episodes 3, 4, 5 (5 steps)
    assert [r["episode"] for r in agent.logger_rows if r["eval_returns"]] == [0, 2, 4, 5]
    assert agent.logger_rows[-1]["env_steps"] == 55


def test_oracle_time_is_booked_once_in_its_own_phase():
    """The oracle's one-off computation is ``time_oracle`` of the episode whose evaluation ran
    it, outside ``time_eval``; computed beforehand by ``compute_oracle()`` it belongs to no
    episode (no negative ``time_eval``, no oracle time outside ``time_total``)."""
    changes = {"collection.episode_steps": 10, "planner.horizon": 4,
               "planner.first_plan_iterations": 2, "evaluation.every": 1,
               "evaluation.episodes": 1, "training.steps": 2}
    rows = {}
    for early in (False, True):
        agent = JacPropAgent(gym.make("mbtsr/TwoLinkArm-v0"), tiny_config(changes, seed=0))
        if early:
            agent.compute_oracle()
        agent.learn(episodes=1)
        rows[early] = agent.logger_rows[0]
    assert rows[False]["time_oracle"] > 0 and rows[True]["time_oracle"] == 0
    for r in rows.values():
        assert r["time_eval"] >= 0
        assert r["time_eval"] + r["time_oracle"] <= r["time_total"]
        assert r["oracle_cost"] == rows[False]["oracle_cost"]


def test_config_progress_false_shows_no_progress_bar(capsys):
    """``AgentConfig.progress`` (``--no-progress``) is what ``learn`` follows by default."""
    agent = JacPropAgent(gym.make("mbtsr/TwoLinkArm-v0"),
                         tiny_config({"collection.episode_steps": 5}, progress=False))
    agent.learn(episodes=1)
    assert "JacProp agent" not in capsys.readouterr().err
    agent.learn(episodes=1, progress_bar=True)  # an explicit argument still wins
    assert "JacProp agent" in capsys.readouterr().err


def test_evaluation_every_steps_follows_the_env_steps():
    """evaluation.every_steps=50 with 30-step episodes: the episodes that end at 60, 120 and 150
    env steps cross 50, 100 and 150 (the last one is also the final score); every=0 adds none."""
    env = gym.make("Pendulum-v1")
    agent = JacPropAgent(env, tiny_config({"evaluation.every": 0, "evaluation.every_steps": 50,
                                           "evaluation.episodes": 1}), cost_fn=pendulum_cost)
    agent.learn(episodes=5, progress_bar=False)
    assert [r["env_steps"] for r in agent.logger_rows if r["eval_returns"] is not None] == [
        60, 120, 150]
    with pytest.raises(ValueError, match="evaluation.every_steps"):
        tiny_config({"evaluation.every_steps": -1})


@pytest.mark.parametrize("broken", ["X", "K"])
def test_replan_feedback_plays_a_failed_solves_plan_open_loop(broken):
    """A solve whose ``X`` or ``K`` is not finite (a failed solve) gives no correction: the
    steps until the next solve play its controls ``U_i`` open loop, never a NaN action."""

    env, agent = _feedback_agent("ilqr")
    solves = []
    original = agent.policy.mpc.solve

    def failing_solve(*args, **kwargs):
        res = original(*args, **kwargs)
        bad = np.array(getattr(res, broken), dtype=float)
        bad[1 + len(solves) % 2] = np.nan
        solves.append(dataclasses.replace(res, **{broken: bad}))
        return solves[-1]

    agent.policy.mpc.solve = failing_solve
    rec = agent.rollout_policy(env, seed=4)
    assert len(solves) == 4
    assert np.all(np.isfinite(rec.actions))
    for j, res in enumerate(solves):
        for i in range(3):
            np.testing.assert_allclose(rec.actions[3 * j + i],
                                       np.clip(res.U[i], -2, 2).astype(np.float32), rtol=1e-5,
                                       atol=1e-6)


def test_replan_every_checks_the_observation_and_state_between_solves():
    """The steps that replay a plan (no solve) refuse a wrong-shaped or non-finite observation
    and a state that is not one ``predict`` returned, as a solving step does."""
    env, agent = _feedback_agent("ilqr")
    obs, _ = env.reset(seed=0)
    _, state = agent.predict(obs)  # a solve; the next two calls replay
    for bad, why in ((obs[:2], "shape"), (np.array([np.nan, 0.0, 0.0]), "finite")):
        with pytest.raises(ValueError, match=why):
            agent.predict(bad, state)
    assert isinstance(state, ReplanState) and state.age == 1
    H, n = agent.config.planner.horizon, agent.state_dim
    assert state.plan.shape == (H, 1) and state.states.shape == (H, n)
    assert state.gains.shape == (H, 1, n)
    nan_plan = state.plan.copy()
    nan_plan[0, 0] = np.nan
    for bad_state in (state.plan, dataclasses.replace(state, plan=state.plan[:-1]),
                      dataclasses.replace(state, plan=nan_plan),
                      dataclasses.replace(state, age=0), dataclasses.replace(state, age=1.5)):
        with pytest.raises(ValueError, match="state(.plan|.age)? must"):
            agent.predict(obs, bad_state)
    action, _ = agent.predict(obs, state)
    assert action.shape == (1,) and np.all(np.isfinite(action))


def test_the_final_evaluation_of_learn_runs_every_episode_despite_early_exit():
    """``evaluation.early_exit`` cuts the evaluations during learning short (an untrained agent
    exceeds 1.2 x the oracle's cost on its first episode), but the final score of ``learn``
    runs every episode, so a run always ends with a return. The last episode is evaluated
    once, completely (not cut short and then played again)."""
    agent = JacPropAgent(gym.make("mbtsr/TwoLinkArm-v0"), tiny_config(
        {"collection.episode_steps": 10, "planner.horizon": 4, "evaluation.every": 1,
         "evaluation.episodes": 3, "training.steps": 2}, seed=0))
    agent.compute_oracle()  # its episodes in the evaluation env, before the count starts
    played = []

    class CountResets(gym.Wrapper):
        def reset(self, **kwargs):
            played.append(kwargs.get("seed"))
            return super().reset(**kwargs)

    agent.evaluator._env = CountResets(agent.evaluator.eval_env())
    agent.learn(episodes=2)
    first, final = agent.logger_rows
    assert first["eval_episodes_run"] < 3 and first["eval_return"] is None
    assert final["eval_episodes_run"] == 3 and len(final["eval_returns"]) == 3
    assert len(played) == first["eval_episodes_run"] + 3
    assert final["eval_return"] == pytest.approx(np.mean(final["eval_returns"]))
    assert agent.summary()["final_eval_return"] == final["eval_return"]
