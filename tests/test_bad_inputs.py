"""The bad-input battery (issue 14): every public boundary refuses bad input with an error that
names the argument or file at fault, never a crash or a silently wrong result.

- parametrized bad inputs per public function: shapes, dtypes, NaN/inf, ranges, empty, complex;
- hypothesis properties at the boundaries;
- corrupted checkpoints and model files: truncation, bit flip, foreign kind/version, foreign
  architecture (optimizer state), foreign config and env on resume, stale temp files;
- a sweep with a run that raises and one whose worker is killed: tests/test_runner.py.
"""

from __future__ import annotations

import json
import os
import warnings

import gymnasium as gym
import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import envs  # noqa: F401  (registers mbtsr/TwoLinkArm-v0)
from agents.checkpoint import (
    CheckpointError,
    check_same,
    env_fingerprint,
    load_checkpoint,
    save_checkpoint,
)
from envs.collect import rollout_open_loop
from envs.rendering import save_video
from envs.two_link_arm import MAX_DT, VELOCITY_LIMIT, TwoLinkArmEnv
from mbtsr import ltv
from mbtsr.costs import quadratic_cost
from mbtsr.dynamics import LinearDynamics, rollout
from mbtsr.ensemble import DynamicsEnsemble, EnsembleConfig, MemberSpec, load_model, save_model
from mbtsr.excitation import filtered_gaussian, multisine
from mbtsr.ilqr import ilqr
from mbtsr.io import remove_stale_temp_files, temp_path
from mbtsr.metrics import jacobian_error, prediction_rms
from mbtsr.runner import summarize
from mbtsr.training import RegularizationConfig, TrainConfig, train_ensemble
from mbtsr.trajectory import Trajectory, save_trajectories, stack_trajectories
from mbtsr.validation import as_array, check_bool, check_int

torch.set_num_threads(1)

A2 = np.array([[1.0, 0.01], [-0.01, 0.99]])
B2 = np.array([[0.0], [0.01]])


def linear_trajs(scale: float = 1.0, n: int = 4, T: int = 50, seed: int = 0) -> list:
    """Trajectories of a lightly nonlinear 2-state system (``scale`` multiplies x and u)."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        x = np.zeros((T + 1, 2))
        x[0] = rng.normal(size=2)
        u = rng.normal(size=(T, 1))
        for t in range(T):
            x[t + 1] = A2 @ x[t] + B2 @ u[t] + 0.01 * np.sin(x[t])
        out.append(Trajectory(scale * x, scale * u, 0.01))
    return out


def small_model(width: int = 8, seed: int = 0) -> DynamicsEnsemble:
    return DynamicsEnsemble(EnsembleConfig(state_dim=2, action_dim=1,
                                           members=(MemberSpec(width=width),), seed=seed))


NAN = float("nan")
INF = float("inf")
X_OK = np.zeros((3, 2))
U_OK = np.zeros((3, 1))


# ------------------------------------------------------------------------------ battery
def _ens():
    return small_model()


def _cost():
    return quadratic_cost(np.eye(2), np.eye(1), np.zeros(2))


CASES = [
    # (id, callable, exception, regex the message must match: the argument named)
    ("as_array complex", lambda: as_array("v", np.array([1 + 2j])), ValueError, "v must be real"),
    ("Trajectory x NaN", lambda: Trajectory(np.full((3, 2), NAN), np.zeros((2, 1))),
     ValueError, "^x contains"),
    ("Trajectory u complex", lambda: Trajectory(np.zeros((3, 2)), np.ones((2, 1)) * 1j),
     ValueError, "^u must be real"),
    ("Trajectory empty", lambda: Trajectory(np.zeros((1, 2)), np.zeros((0, 1))),
     ValueError, "T >= 1"),
    ("Trajectory lengths", lambda: Trajectory(np.zeros((3, 2)), np.zeros((3, 1))),
     ValueError, "len\\(x\\) == len\\(u\\) \\+ 1"),
    ("Trajectory dt nan", lambda: Trajectory(np.zeros((3, 2)), np.zeros((2, 1)), NAN),
     ValueError, "^dt must"),
    ("Trajectory x 1-D", lambda: Trajectory(np.zeros(3), np.zeros((2, 1))),
     ValueError, "^x must be 2-dim"),
    ("LinearDynamics A NaN", lambda: LinearDynamics(np.full((2, 2), NAN), B2), ValueError, "A"),
    ("rollout u inf", lambda: rollout(LinearDynamics(A2, B2), np.zeros(2),
                                      np.full((3, 1), INF)), ValueError, "^u "),
    ("rollout u complex", lambda: rollout(LinearDynamics(A2, B2), np.zeros(2),
                                          np.ones((3, 1)) * 1j), ValueError, "^u must be real"),
    ("ensemble step x shape", lambda: _ens().step(np.zeros((3, 3)), U_OK), ValueError, "^x "),
    ("ensemble step u NaN", lambda: _ens().step(X_OK, np.full((3, 1), NAN)), ValueError, "^u "),
    ("ensemble step u complex", lambda: _ens().step(X_OK, U_OK + 1j), ValueError,
     "^u must be real"),
    ("ensemble jacobians x inf", lambda: _ens().jacobians(np.full((3, 2), INF), U_OK),
     ValueError, "^x "),
    ("ensemble no members", lambda: EnsembleConfig(state_dim=2, action_dim=1, members=()),
     ValueError, "members"),
    ("ensemble state_dim 0", lambda: EnsembleConfig(state_dim=0, action_dim=1), ValueError,
     "state_dim"),
    ("train empty", lambda: train_ensemble(_ens(), []), ValueError, "trajs"),
    ("train lr nan", lambda: TrainConfig(lr=NAN), ValueError, "lr"),
    ("train weight_decay nan", lambda: TrainConfig(weight_decay=NAN), ValueError,
     "weight_decay"),
    ("reg weight nan", lambda: RegularizationConfig(sampled_weight=NAN), ValueError,
     "sampled_weight"),
    ("reg weight inf", lambda: RegularizationConfig(exact_weight=INF), ValueError,
     "exact_weight"),
    ("fit_ltv lam nan", lambda: ltv.fit_ltv(linear_trajs(n=1, T=10), NAN), ValueError, "lam"),
    ("fit_ltv lam negative", lambda: ltv.fit_ltv(linear_trajs(n=1, T=10), -1.0), ValueError,
     "lam"),
    ("select_lambda empty grid", lambda: ltv.select_lambda(linear_trajs(n=2, T=20), []),
     ValueError, "lambdas"),
    ("select_lambda zero", lambda: ltv.select_lambda(linear_trajs(n=2, T=20), [0.0, 1.0]),
     ValueError, "lambdas"),
    ("select_lambda inf", lambda: ltv.select_lambda(linear_trajs(n=2, T=20), [INF]),
     ValueError, "lambdas"),
    ("select_lambda method", lambda: ltv.select_lambda(linear_trajs(n=2, T=20), method="x"),
     ValueError, "method"),
    ("quadratic_cost Q NaN", lambda: quadratic_cost(np.full((2, 2), NAN), np.eye(1),
                                                     np.zeros(2)), ValueError, "^Q "),
    ("quadratic_cost R not PSD", lambda: quadratic_cost(np.eye(2), -np.eye(1), np.zeros(2)),
     ValueError, "^R "),
    ("quadratic_cost goal complex", lambda: quadratic_cost(np.eye(2), np.eye(1),
                                                           np.zeros(2) + 1j), ValueError,
     "x_goal must be real"),
    ("cost total all-NaN X", lambda: _cost().total(np.full((4, 2), NAN), np.zeros((3, 1))),
     ValueError, "^X "),
    ("ilqr x0 NaN", lambda: ilqr(_cost(), LinearDynamics(A2, B2), np.full(2, NAN),
                                 np.zeros((5, 1))), ValueError, "x0"),
    ("ilqr U0 complex", lambda: ilqr(_cost(), LinearDynamics(A2, B2), np.zeros(2),
                                     np.zeros((5, 1)) + 1j), ValueError, "U0 must be real"),
    ("ilqr U0 empty", lambda: ilqr(_cost(), LinearDynamics(A2, B2), np.zeros(2),
                                   np.zeros((0, 1))), ValueError, "U0"),
    ("prediction_rms NaN", lambda: prediction_rms(LinearDynamics(A2, B2),
                                                  [Trajectory(np.zeros((3, 2)),
                                                              np.zeros((2, 1)))] * 0),
     ValueError, "trajs"),
    ("jacobian_error shapes", lambda: jacobian_error(np.zeros((3, 2, 2)), np.zeros((3, 2, 3))),
     ValueError, "J_hat|J_true"),
    ("filtered_gaussian T", lambda: filtered_gaussian(0, 1, seed=0), ValueError, "^T "),
    ("multisine amplitude nan", lambda: multisine(10, 1, amplitude=NAN, seed=0), ValueError,
     "amplitude"),
    ("arm dt absurd", lambda: TwoLinkArmEnv(dt=0.3), ValueError, "^dt must be <= MAX_DT"),
    ("arm dt nan", lambda: TwoLinkArmEnv(dt=NAN), ValueError, "^dt must"),
    ("arm width 0", lambda: TwoLinkArmEnv(width=0, height=0), ValueError, "width"),
    ("arm cost_Q NaN", lambda: TwoLinkArmEnv(cost_Q=[NAN, 1, 1, 1]), ValueError, "cost_Q"),
    ("arm cost_R negative", lambda: TwoLinkArmEnv(cost_R=[-1, 1]), ValueError, "cost_R"),
    ("stack_trajectories empty", lambda: stack_trajectories([]), ValueError, "^trajs"),
    ("save_trajectories empty", lambda: save_trajectories("/tmp/never.npz", []), ValueError,
     "^trajs"),
    ("rollout x0 shape", lambda: rollout(LinearDynamics(A2, B2), np.zeros(3), U_OK),
     ValueError, "^x0 "),
    ("ilqr dynamics None", lambda: ilqr(_cost(), None, np.zeros(2), np.zeros((5, 1))),
     TypeError, "^dynamics"),
    ("rollout_open_loop u complex", lambda: rollout_open_loop(
        gym.make("mbtsr/TwoLinkArm-v0"), np.zeros((3, 2)) + 1j), ValueError, "^u must be real"),
    ("rollout_open_loop u shape", lambda: rollout_open_loop(
        gym.make("mbtsr/TwoLinkArm-v0"), np.zeros((3, 3))), ValueError, "^u must"),
    ("save_video 0x0", lambda: save_video([np.zeros((0, 0, 3), np.uint8)], "/tmp/x.gif"),
     ValueError, "frames"),
    ("summarize strings", lambda: summarize(["a"]), ValueError, "values"),
    ("save_video NaN frames", lambda: save_video([np.full((4, 4, 3), NAN)], "/tmp/x.gif"),
     ValueError, "frames\\[0\\]"),
]


@pytest.mark.parametrize("fn, exc, match", [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_bad_input_is_refused_naming_the_argument(fn, exc, match):
    with warnings.catch_warnings():
        warnings.simplefilter("error", np.exceptions.ComplexWarning)
        with pytest.raises(exc, match=match):
            fn()


@pytest.mark.parametrize("action", [np.array([1 + 1j, 0]), [NAN, 0.0], [0.0, INF], [0.0],
                                    np.zeros((1, 2)), "ab", None])
def test_arm_step_refuses_bad_actions(action):
    env = TwoLinkArmEnv()
    env.reset(seed=0)
    with pytest.raises(ValueError, match="^action"):
        env.step(action)


# ------------------------------------------------------------------------------ hypothesis
finite = st.floats(-1e6, 1e6, allow_nan=False)


@settings(max_examples=40, deadline=None)
@given(st.lists(st.one_of(finite, st.just(NAN), st.just(INF), st.just(-INF)), min_size=1,
                max_size=8))
def test_as_array_finite_check_is_exact(values):
    arr = np.array(values)
    if np.all(np.isfinite(arr)):
        np.testing.assert_array_equal(as_array("v", values), arr)
    else:
        with pytest.raises(ValueError, match="^v contains"):
            as_array("v", values)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.floats(1e-9, 10.0), st.floats(-2.0, 2.0))
def test_arm_dt_boundary(dt, a):
    """Every dt in (0, MAX_DT] builds a stable env; above it is refused."""
    if dt > MAX_DT:
        with pytest.raises(ValueError, match="dt"):
            TwoLinkArmEnv(dt=dt)
        return
    env = TwoLinkArmEnv(dt=dt, episode_steps=5)
    env.reset(seed=0)
    for _ in range(5):
        obs, _, _, trunc, info = env.step([a, -a])
        assert np.all(np.isfinite(obs)) and not info["unstable"]


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 30), st.integers(0, 7))
def test_any_single_bit_flip_is_detected(byte_frac, bit):
    path = _CKPT_DIR / "flip.pt"
    save_checkpoint(path, {"w": np.arange(4.0), "n": 3})
    data = bytearray(path.read_bytes())
    i = int(len(data) * byte_frac / 31)
    data[i] ^= 1 << bit
    path.write_bytes(bytes(data))
    with pytest.raises(CheckpointError, match=str(path)):
        load_checkpoint(path)


_CKPT_DIR = None


@pytest.fixture(autouse=True)
def _ckpt_dir(tmp_path_factory):
    global _CKPT_DIR
    if _CKPT_DIR is None:
        _CKPT_DIR = tmp_path_factory.mktemp("ckpt")


# ------------------------------------------------------------------------------ instability
def test_arm_surfaces_mujoco_instability():
    """An arm whose torque blows the simulation up: truncated with an info flag, not hidden."""
    env = gym.make("mbtsr/TwoLinkArm-v0", params={"torque_limit": (1e4, 1e4)})
    env.reset(seed=0)
    _, _, terminated, truncated, info = env.step(np.ones(2))
    assert truncated and not terminated and info["unstable"]
    assert "VELOCITY_LIMIT" in info["instability"] or "MuJoCo" in info["instability"]
    assert np.abs(info["state"][2:]).max() > VELOCITY_LIMIT or not np.any(info["state"])
    _, _, _, truncated, info = env.step(np.ones(2))
    assert truncated and info["unstable"] and "MuJoCo" in info["instability"]
    # a normal arm never raises the flag
    env = gym.make("mbtsr/TwoLinkArm-v0")
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    for _ in range(20):
        _, _, _, truncated, info = env.step(rng.uniform(-1, 1, 2))
        assert not info["unstable"] and not truncated


# ------------------------------------------------------------------------------ checkpoints
def test_checkpoint_truncation_bitflip_and_foreign_files(tmp_path):
    path = tmp_path / "checkpoint.pt"
    save_checkpoint(path, {"w": np.arange(10.0), "s": "x"})
    good = path.read_bytes()
    assert load_checkpoint(path)["s"] == "x"
    for _name, data in [("truncated", good[: len(good) // 2]), ("header only", good[:40]),
                        ("empty", b""), ("padded", good + b"\0")]:
        path.write_bytes(data)
        with pytest.raises(CheckpointError, match=f"{path}.*(truncated|damaged|not an)"):
            load_checkpoint(path)
    flipped = bytearray(good)
    flipped[len(good) - 100] ^= 0x10
    path.write_bytes(bytes(flipped))
    with pytest.raises(CheckpointError, match=f"{path} is corrupted.*delete"):
        load_checkpoint(path)
    # another kind of file, another version, a plain torch file
    save_model(small_model(), path)
    with pytest.raises(CheckpointError, match="not a 'agent-checkpoint'"):
        load_checkpoint(path)
    path.write_bytes(good.replace(b"version=2", b"version=9", 1))
    with pytest.raises(CheckpointError, match="format version 9"):
        load_checkpoint(path)
    torch.save({"format": 1}, path)
    with pytest.raises(CheckpointError, match="plain torch file"):
        load_checkpoint(path)


def test_model_file_bitflip_and_round_trip(tmp_path):
    model = small_model()
    model.set_normalization(linear_trajs(n=1))
    path = tmp_path / "model.pt"
    save_model(model, path)
    x, u = np.ones((2, 2)), np.ones((2, 1))
    np.testing.assert_array_equal(load_model(path).step(x, u), model.step(x, u))
    data = bytearray(path.read_bytes())
    data[-50] ^= 1
    path.write_bytes(bytes(data))
    with pytest.raises(CheckpointError, match=f"{path} is corrupted"):
        load_model(path)


def test_stale_temp_files_are_removed_at_the_next_start(tmp_path):
    path = tmp_path / "checkpoint.pt"
    dead = temp_path(path, 999999999)  # no such pid
    dead_old = tmp_path / ".checkpoint.pt.999999998.tmp"  # the name earlier versions used
    alive = temp_path(path, os.getppid())  # a live writer: kept
    other = temp_path(tmp_path / "model.pt", 999999999)
    for p in (dead, dead_old, alive, other):
        p.write_bytes(b"partial")
    save_checkpoint(path, {"a": 1})
    assert not dead.exists() and not dead_old.exists() and alive.exists() and other.exists()
    dead.write_bytes(b"partial")
    load_checkpoint(path)
    assert not dead.exists()
    assert remove_stale_temp_files(tmp_path / "model.pt") == [other]


def test_foreign_architecture_optimizer_state_is_refused_before_loading():
    trajs = linear_trajs(n=2, T=20)
    cfg = TrainConfig(epochs=2, seed=0, progress=False)
    h = train_ensemble(small_model(width=8), trajs, cfg)
    with pytest.raises(ValueError, match="optimizer_state does not fit this model.*shape"):
        train_ensemble(small_model(width=16), trajs, cfg, optimizer_state=h.optimizer_state)
    two = DynamicsEnsemble(EnsembleConfig(state_dim=2, action_dim=1,
                                          members=(MemberSpec(width=8, depth=2),), seed=0))
    with pytest.raises(ValueError, match="optimizer_state does not fit this model"):
        train_ensemble(two, trajs, cfg, optimizer_state=h.optimizer_state)
    with pytest.raises(ValueError, match="optimizer_state must be"):
        train_ensemble(small_model(), trajs, cfg, optimizer_state={"x": 1})


def test_resume_checks_name_the_differing_field(tmp_path):
    a = gym.make("mbtsr/TwoLinkArm-v0")
    b = gym.make("mbtsr/TwoLinkArm-v0", dt=0.01)
    c = gym.make("mbtsr/TwoLinkArm-v0", preset="paper")
    check_same(env_fingerprint(a), env_fingerprint(gym.make("mbtsr/TwoLinkArm-v0")),
               what="env", path="ck.pt")
    with pytest.raises(CheckpointError, match="cannot resume ck.pt: the env differs in 'dt'"):
        check_same(env_fingerprint(a), env_fingerprint(b), what="env", path="ck.pt")
    with pytest.raises(CheckpointError, match="'kwargs.preset'"):
        check_same(env_fingerprint(a), env_fingerprint(c), what="env", path="ck.pt")
    with pytest.raises(CheckpointError, match="'horizon'.*checkpoint: 20.*now: 30"):
        check_same({"horizon": 20, "seed": 0}, {"horizon": 30, "seed": 0}, what="config",
                   path="ck.pt")
    assert json.loads(json.dumps(env_fingerprint(a))) == env_fingerprint(a)


# ------------------------------------------------------------------------------ numerics
def test_tiny_scale_data_trains_as_well_as_scale_one():
    """Relative std floor: data in units 1e6 times smaller gives the same relative error."""
    errs = {}
    for scale in (1.0, 1e-6):
        model = small_model(width=16)
        train_ensemble(model, linear_trajs(scale), TrainConfig(epochs=40, seed=0,
                                                               progress=False))
        test = linear_trajs(scale, seed=1)
        err = np.concatenate([model.step(t.x[:-1], t.u) - t.x[1:] for t in test])
        res = np.concatenate([t.x[1:] - t.x[:-1] for t in test])
        errs[scale] = np.sqrt((err ** 2).mean() / (res ** 2).mean())
    assert errs[1.0] < 0.5
    assert errs[1e-6] == pytest.approx(errs[1.0], rel=1e-3)


def test_overflowing_regularizer_term_is_named():
    trajs = linear_trajs(n=2, T=20)
    reg = RegularizationConfig(exact_weight=1.0)
    huge = [ltv.LTVModel(np.full((20, 2, 2), 1e30), np.full((20, 2, 1), 1e30), None,
                         np.zeros((20, 2, 3, 3)))] * 2
    model = small_model()
    with pytest.raises(FloatingPointError, match="'exact' regularizer term"):
        train_ensemble(model, trajs, TrainConfig(epochs=2, progress=False), reg,
                       ltv_models=huge)
    assert all(torch.isfinite(p).all() for p in model.parameters())  # no step was taken


def test_select_lambda_handles_huge_grids_and_is_continuous_at_the_limit():
    trajs = linear_trajs(n=3, T=30)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        lam, curve = ltv.select_lambda(trajs, np.logspace(0, 300, 10))
    assert np.isfinite(lam) and all(np.isfinite(curve["score"]))
    # the lam -> inf branch of the score continues the banded computation
    prob = ltv._problem(trajs, False)
    s2 = float(np.trace(prob.G.sum(0))) / (prob.T * prob.p)
    edge = np.sqrt(ltv._LIMIT * s2)
    for method in ("marginal_likelihood", "gcv"):
        below = ltv._score(prob, 0.999 * edge, method)
        above = ltv._score(prob, 1.001 * edge, method)
        assert above == pytest.approx(below, rel=1e-4)


def test_agent_boundaries_name_the_argument():
    from agents.config import AgentConfig
    from agents.jacprop_agent import JacPropAgent
    from agents.tasks import env_spec

    env = gym.make("mbtsr/TwoLinkArm-v0")
    with pytest.raises(ValueError, match="^episode_steps must"):
        env_spec(env, 0)
    agent = JacPropAgent(env, AgentConfig.default({"model.ensemble_size": 1,
                                                   "model.hidden_width": 4},
                                                  progress=False, tensorboard=False))
    for obs, match in [(np.full(6, NAN), "^observation contains"),
                       (np.zeros(6) + 1j, "^observation must be real"),
                       (np.zeros(5), "^observation must have shape")]:
        with pytest.raises(ValueError, match=match):
            agent.predict(obs)
    with pytest.raises(FileNotFoundError, match="h14_missing.pt"):
        JacPropAgent.load("/nonexistent/h14_missing.pt")


@given(st.one_of(st.integers(-10**6, 10**6), st.booleans(), st.floats(allow_nan=True),
                 st.text(max_size=3), st.none()),
       st.one_of(st.none(), st.integers(-5, 5)))
def test_check_int_accepts_exactly_the_integers_at_or_above_the_minimum(value, minimum):
    ok = (isinstance(value, int) and not isinstance(value, bool)
          and (minimum is None or value >= minimum))
    if ok:
        assert check_int("k", value, minimum) == value
        assert type(check_int("k", np.int64(value), minimum)) is int
    else:
        with pytest.raises(ValueError, match=r"^k must be an integer"):
            check_int("k", value, minimum)


@pytest.mark.parametrize("value", [True, False, np.True_, np.False_])
def test_check_bool_returns_a_python_bool(value):
    assert check_bool("flag", value) is bool(value)


@pytest.mark.parametrize("value", [0, 1, 1.0, "yes", None, np.array([True])])
def test_check_bool_refuses_what_is_not_a_bool(value):
    with pytest.raises(ValueError, match=r"^flag must be a bool"):
        check_bool("flag", value)
