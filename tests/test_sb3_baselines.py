"""SB3 baselines (issues 7 and 12): on the two-link arm's targets and on the benchmark suite.

- on the arm's targets the callback's evaluation cost is minus the return SB3's own
  ``evaluate_policy`` measures on the same targets and resets (raw observations for SAC,
  ``VecNormalize`` for PPO); bad arguments are refused;
- ``train_sb3`` on an env without targets scores the deterministic policy by the env's own
  return: equal to SB3's ``evaluate_policy`` on the same reset seeds;
- the suite's thresholds and censored summaries agree with hand-computed values;
- ``scripts/bench_suite.py --sb3 --smoke`` runs end to end, writes its own JSON (never the agent
  runs' one), marks budget-censored results as lower bounds and resumes without re-running.
"""

from __future__ import annotations

import json

import gymnasium as gym
import numpy as np
import pytest
import torch
from helpers_sb3 import SMALL_RUNS, ScriptedResets, sb3_returns

import envs  # noqa: F401  (registers mbtsr/TwoLinkArm-v0)
from agents.experiments import bench_suite as suite
from agents.sb3_baselines import default_hyperparams, train_sb3

IP = "InvertedPendulum-v5"
ARM = "mbtsr/TwoLinkArm-v0"
TARGETS = [[0.4, -0.3], [-0.8, 0.5], [1.0, 0.2]]
EVAL_SEED = 1000


@pytest.fixture(autouse=True)
def _one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


# ---------------------------------------------------------------------------------------------
# the callback's cost is minus SB3's episode return
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("algo, budget, every, hyperparams", SMALL_RUNS)
def test_callback_cost_is_minus_sb3_return(algo, budget, every, hyperparams):
    rec = train_sb3(algo, ARM, budget, seed=3, eval_every=every, eval_targets=TARGETS,
                    hyperparams=hyperparams, eval_seed=EVAL_SEED,
                    return_model=True)
    model = rec.pop("model")
    json.dumps(rec)  # the record is JSON-serializable
    assert [s for s, _ in rec["curve"]] == list(range(0, budget + 1, every))
    assert rec["env_steps"] == budget

    returns, lengths = sb3_returns(model, ScriptedResets(gym.make(ARM), EVAL_SEED, TARGETS),
                                   len(TARGETS), bool(hyperparams.get("normalize")))
    assert lengths == [100] * len(TARGETS)
    # the final curve point is the final policy; rewards pass through float32 in the VecEnv
    assert rec["curve"][-1][1] == pytest.approx(-np.mean(returns), rel=1e-5)


@pytest.mark.parametrize(
    "kwargs, msg",
    [
        ({"algo": "a2c"}, "algo"),
        ({"budget_steps": 0}, "budget_steps"),
        ({"eval_every": 1.5}, "eval_every"),
        ({"seed": -1}, "seed"),
        ({"eval_targets": [[0.1, np.nan]]}, "eval_targets"),
        ({"eval_targets": [0.1, 0.2]}, "eval_targets"),
        ({"hyperparams": {"no_such_kwarg": 1}}, "hyperparams"),
        ({"hyperparams": {"action_noise_std": 0.1}, "algo": "ppo"}, "action_noise_std"),
    ],
)
def test_bad_arguments(kwargs, msg):
    args = {"algo": "sac", "env_id": ARM, "budget_steps": 10, "seed": 0, "eval_every": 5,
            "eval_targets": TARGETS}
    args.update(kwargs)
    with pytest.raises(ValueError, match=msg):
        train_sb3(**args)


def test_default_hyperparams_are_documented_choices():
    assert default_hyperparams("sac") == {}
    assert default_hyperparams("td3") == {"action_noise_std": 0.1}
    assert default_hyperparams("ppo") == {"normalize": True}


# ---------------------------------------------------------------------------------------------
# train_sb3 on an env's own return
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("algo, budget, every, hyperparams", SMALL_RUNS)
def test_return_evaluation_is_sb3_return(algo, budget, every, hyperparams):
    rec = train_sb3(algo, IP, budget, seed=2, eval_every=every, eval_targets=None,
                    hyperparams=hyperparams, eval_seed=EVAL_SEED,
                    n_eval_episodes=3, eval_max_steps=200, env_kwargs={"max_episode_steps": 200},
                    return_model=True)
    model = rec.pop("model")
    json.dumps(rec)
    assert rec["n_eval_episodes"] == 3 and rec["n_eval_targets"] == 0
    assert [s for s, _ in rec["curve"]] == list(range(0, budget + 1, every))

    returns, _ = sb3_returns(model, ScriptedResets(gym.make(IP, max_episode_steps=200), EVAL_SEED),
                             3, bool(hyperparams.get("normalize")))
    assert rec["curve"][-1][1] == pytest.approx(-np.mean(returns), rel=1e-6)


@pytest.mark.parametrize(
    "kwargs, msg",
    [
        ({"eval_targets": None}, "n_eval_episodes"),
        ({"eval_targets": None, "n_eval_episodes": 0}, "n_eval_episodes"),
        ({"eval_targets": None, "n_eval_episodes": 2, "eval_max_steps": 0}, "max_steps"),
        ({"n_eval_episodes": 2}, "n_eval_episodes"),
    ],
)
def test_bad_return_arguments(kwargs, msg):
    args = {"algo": "sac", "env_id": IP, "budget_steps": 10, "seed": 0, "eval_every": 5,
            "eval_targets": [[0.1, 0.2]]}
    args.update(kwargs)
    with pytest.raises(ValueError, match=msg):
        train_sb3(**args)


# ---------------------------------------------------------------------------------------------
# the suite's SB3 runs: a fixed budget on the suite's evaluation episodes
# ---------------------------------------------------------------------------------------------


def test_bench_suite_sb3_smoke(tmp_path):
    sb3_json = tmp_path / "sac.json"
    args = ["--sb3", "sac", "--smoke", "--seeds", "0", "--out", str(tmp_path / "agent.json"),
            "--sb3-json", str(sb3_json), "--tasks", "inverted-pendulum", "arm-open-loop",
            "--baselines-json", str(tmp_path / "baselines.json")]
    state = suite.main(args)
    assert not (tmp_path / "agent.json").exists()  # --sb3 never writes the agent runs' JSON
    saved = json.loads(sb3_json.read_text())
    assert saved["runs"] == json.loads(json.dumps(state["runs"]))
    ip, arm = saved["runs"]
    assert (ip["task"], ip["method"], ip["seed"]) == ("inverted-pendulum", "sac", 0)
    assert ip["budget_env_steps"] == ip["env_steps"] == 256
    assert [c["env_steps"] for c in ip["curve"]] == list(range(0, 257, 12))[:22] or \
        ip["curve"][0]["env_steps"] == 0
    assert all(0 < c["score"] <= 200 for c in ip["curve"])  # IP's returns: 1 per step alive
    assert all(c["score"] < 0 for c in arm["curve"])  # the arm's returns: minus its cost
    # resume skips the finished runs
    again = suite.main(args + ["--resume"])
    assert [r["wall_seconds"] for r in again["runs"]] == [ip["wall_seconds"], arm["wall_seconds"]]


def test_steps_to_reach_hand_computed():
    curve = [{"env_steps": 0, "score": -10.0}, {"env_steps": 5000, "score": -6.0},
             {"env_steps": 10000, "score": -4.0}]
    assert suite.steps_to_reach(curve, -6.5) == (5000.0, False)
    assert suite.steps_to_reach(curve, -4.0) == (10000.0, False)
    assert suite.steps_to_reach(curve, -3.0) == (10000.0, True)  # never: a lower bound
    assert suite.score_at(curve, 7000) == -6.0 and suite.score_at(curve, -1) is None
