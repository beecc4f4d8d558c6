"""SB3 baselines on the benchmark suite (issue 12, item 6).

- ``train_sb3`` on an env without targets scores the deterministic policy by the env's own
  return: equal to SB3's ``evaluate_policy`` on the same reset seeds, and ``solved_return`` stops
  training at the first evaluation that reaches it (a negative cost threshold);
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
from hypothesis import given
from hypothesis import strategies as st

from agents.experiments import bench_suite as suite
from agents.sb3_baselines import train_sb3

IP = "InvertedPendulum-v5"
EVAL_SEED = 1000


@pytest.fixture(autouse=True)
def _one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


# ---------------------------------------------------------------------------------------------
# train_sb3 on an env's own return
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("algo, budget, every, hyperparams", SMALL_RUNS)
def test_return_evaluation_is_sb3_return(algo, budget, every, hyperparams):
    rec = train_sb3(algo, IP, budget, seed=2, eval_every=every, eval_targets=None,
                    threshold=None, hyperparams=hyperparams, eval_seed=EVAL_SEED,
                    n_eval_episodes=3, eval_max_steps=200, env_kwargs={"max_episode_steps": 200},
                    return_model=True)
    model = rec.pop("model")
    json.dumps(rec)
    assert rec["n_eval_episodes"] == 3 and rec["n_eval_targets"] == 0
    assert [s for s, _ in rec["curve"]] == list(range(0, budget + 1, every))
    assert not rec["solved"] and rec["steps_to_solve"] is None

    returns, _ = sb3_returns(model, ScriptedResets(gym.make(IP, max_episode_steps=200), EVAL_SEED),
                             3, bool(hyperparams.get("normalize")))
    assert rec["curve"][-1][1] == pytest.approx(-np.mean(returns), rel=1e-6)


def test_solved_return_stops_at_first_solved_evaluation():
    probe = train_sb3("sac", IP, 1, seed=0, eval_every=1, eval_targets=None, threshold=None,
                      hyperparams={"learning_starts": 10}, eval_seed=EVAL_SEED,
                      n_eval_episodes=2)
    return0 = -probe["curve"][0][1]
    assert return0 > 0  # IP pays +1 per step alive: the threshold on the cost is negative
    rec = train_sb3("sac", IP, 5_000, seed=0, eval_every=50, eval_targets=None, threshold=None,
                    hyperparams={"learning_starts": 10}, eval_seed=EVAL_SEED,
                    n_eval_episodes=2, solved_return=return0)
    assert rec["solved"] and rec["steps_to_solve"] == 0 and rec["env_steps"] <= 1
    assert rec["threshold"] == -return0 and rec["solved_return"] == return0


@pytest.mark.parametrize(
    "kwargs, msg",
    [
        ({"eval_targets": None}, "n_eval_episodes"),
        ({"eval_targets": None, "n_eval_episodes": 0}, "n_eval_episodes"),
        ({"eval_targets": None, "n_eval_episodes": 2, "eval_max_steps": 0}, "max_steps"),
        ({"n_eval_episodes": 2}, "n_eval_episodes"),
        ({"threshold": 1.0, "solved_return": 1.0}, "not both"),
        ({"threshold": None, "solved_return": np.nan}, "solved_return"),
    ],
)
def test_bad_return_arguments(kwargs, msg):
    args = {"algo": "sac", "env_id": IP, "budget_steps": 10, "seed": 0, "eval_every": 5,
            "eval_targets": [[0.1, 0.2]], "threshold": None}
    args.update(kwargs)
    with pytest.raises(ValueError, match=msg):
        train_sb3(**args)


# ---------------------------------------------------------------------------------------------
# thresholds and censored summaries against hand-computed values
# ---------------------------------------------------------------------------------------------


def test_return_thresholds_hand_computed():
    assert suite.solved_return("inverted-pendulum", 200.0) == pytest.approx(190.0, abs=1e-12)
    assert suite.solved_return("reacher", -3.9172403724873845) == pytest.approx(
        -4.1131023911, abs=1e-9)


@given(st.floats(-1e6, 1e6))
def test_return_threshold_is_within_the_margin_below_the_oracle(oracle):
    thr = suite.solved_return("reacher", oracle)
    assert thr <= oracle
    assert oracle - thr == pytest.approx(0.05 * abs(oracle), rel=1e-9, abs=1e-9)


def test_budgets_are_the_stated_multiples():
    assert suite.agent_budget_env_steps("arm-far") == 800  # 8 episodes x 100 steps
    assert suite.sb3_budget("arm-far", "sac") == 16_000
    assert suite.sb3_budget("arm-open-loop", "ppo") == 160_000
    assert suite.sb3_budget("reacher", "sac") == 40_000  # 2,000 agent steps (issue 21)
    assert suite.sb3_budget("inverted-pendulum", "sac") == 40_000
    assert suite.sb3_budget("inverted-pendulum", "ppo") == 400_000


def _sb3(method, seed, solved_at, budget):
    return {"task": "arm-far", "method": method, "seed": seed, "env_steps_to_solve": solved_at,
            "env_steps": budget if solved_at is None else solved_at + 1,
            "budget_env_steps": budget}


def _agent(config, seed, solved_at, budget=800):
    planner, reg = config.split("/")
    return {"task": "arm-far", "planner": planner, "regularization": reg, "seed": seed,
            "env_steps_to_solve": solved_at, "env_steps": budget if solved_at is None else 400,
            "budget_env_steps": budget}


def test_censored_comparison_hand_computed():
    sb3 = [_sb3("sac", 0, 3000, 16_000), _sb3("sac", 1, None, 16_000),
           _sb3("sac", 2, 5000, 16_000)] + [_sb3("ppo", s, None, 160_000) for s in range(3)]
    agent = ([_agent("ilqr/none", 0, 200), _agent("ilqr/none", 1, 400),
              _agent("ilqr/none", 2, None)]
             + [_agent("cem/sampled", 0, None), _agent("cem/sampled", 1, None),
                _agent("cem/sampled", 2, 200)])
    (row,) = suite.sb3_comparison(sb3, agent)
    # SAC: 3000, >= 16000, 5000 -> median 5000, exact (the censored value is above it)
    sac = row["sb3"]["sac"]
    assert sac["solved"] == "2/3"
    assert [v["display"] for v in sac["per_seed"]] == ["3000", ">= 16000", "5000"]
    assert sac["median"]["display"] == "5000" and not sac["median"]["lower_bound"]
    assert row["sb3"]["ppo"]["median"]["display"] == ">= 160000"
    assert row["best_sb3"]["method"] == "sac" and row["best_sb3"]["value"] == 5000
    # agent: ilqr/none 200, 400, >= 800 -> 400 exact; cem/sampled >= 800, >= 800, 200 -> >= 800
    assert row["best_agent"]["config"] == "ilqr/none" and row["best_agent"]["value"] == 400
    assert not row["best_agent"]["lower_bound"]
    assert row["ratio"]["value"] == pytest.approx(12.5) and row["ratio"]["kind"] == "exact"
    assert row["target_met"] is False

    # SAC never solves: best SB3 >= 16000, ratio >= 40 -> the 20x target is met
    sb3_unsolved = [_sb3("sac", s, None, 16_000) for s in range(3)]
    (row,) = suite.sb3_comparison(sb3_unsolved, agent)
    assert row["best_sb3"]["display"] == ">= 16000"
    assert row["ratio"]["display"] == ">= 40" and row["target_met"] is True

    # the agent never solves either: both bounds, the ratio is undetermined
    agent_unsolved = [_agent("ilqr/none", s, None) for s in range(3)]
    (row,) = suite.sb3_comparison(sb3_unsolved, agent_unsolved)
    assert row["ratio"]["kind"] == "undetermined" and row["target_met"] is None

    lines = "\n".join(suite.sb3_markdown_lines(sb3, agent))
    assert "| arm-far | SAC | 16000 | 2/3 | 5000 (3000, >= 16000, 5000) |" in lines
    assert "| arm-far | SAC 5000 | ilqr/none 400 | 12.5 | no |" in lines


# ---------------------------------------------------------------------------------------------
# the command line, end to end
# ---------------------------------------------------------------------------------------------


def test_bench_suite_sb3_smoke(tmp_path):
    out = tmp_path / "suite.json"
    args = ["--sb3", "sac", "--smoke", "--seeds", "0", "--json", str(out),
            "--oracle-cache", str(tmp_path / "oracle"), "--tasks", "inverted-pendulum"]
    state = suite.main(args)
    assert not out.exists()  # the agent runs' JSON is never written by --sb3
    saved = json.loads((tmp_path / "suite_sb3.json").read_text())
    assert saved["runs"] == json.loads(json.dumps(state["runs"]))
    (run,) = saved["runs"]
    problem = saved["problems"]["inverted-pendulum"]
    assert problem["solved_return"] == pytest.approx(
        suite.solved_return("inverted-pendulum", problem["oracle_mean_return"]))
    assert run["task"] == "inverted-pendulum" and run["method"] == "sac" and run["seed"] == 0
    assert run["budget_env_steps"] == run["env_steps"] == suite.SB3_SMOKE["budget"]
    # 256 training steps cannot balance the pole for 190 of 200 steps: a censored run
    assert not run["solved"] and run["env_steps_to_solve"] is None
    assert all(c["score"] < problem["solved_return"] for c in run["curve"])
    assert [c["env_steps"] for c in run["curve"]] == [0, 128, 256]
    (row,) = saved["comparison"]
    assert row["sb3"]["sac"]["per_seed"] == [
        {"value": 256.0, "lower_bound": True, "display": ">= 256"}]
    # the report reads both JSONs: agent runs from --json, SB3 runs from <stem>_sb3.json
    agent_rec = {"task": "inverted-pendulum", "planner": "ilqr", "regularization": "none",
                 "seed": 0, "env_steps_to_solve": 200, "env_steps": 200,
                 "budget_env_steps": 2000, "episodes_to_solve": 1, "final_score": 200.0,
                 "curve": [{"env_steps": 200, "score": 200.0, "returns": [200.0]}],
                 "wall_seconds_per_phase": {k: 1.0 for k in
                                            ("training", "ltv", "planning", "eval", "total")},
                 "wall_seconds": 5.0}
    out.write_text(json.dumps({"runs": [agent_rec], "oracles": {
        "inverted-pendulum": {"mean_return": problem["oracle_mean_return"]}}}))
    suite.main(["--report-only", "--json", str(out), "--figures", str(tmp_path / "fig"),
                "--docs", str(tmp_path / "bench.md"), "--tasks", "inverted-pendulum"])
    md = (tmp_path / "bench.md").read_text()
    assert "| inverted-pendulum | SAC | 256 | 0/1 | >= 256 (>= 256) |" in md
    assert "| inverted-pendulum | SAC >= 256 | ilqr/none 200 | >= 1.28 | undetermined |" in md
    assert (tmp_path / "fig" / "bench_suite_sb3_curves.png").is_file()
    assert "](fig/bench_suite_sb3_curves.png)" in md
    # resume skips the finished run
    again = suite.main(args + ["--resume"])
    assert len(again["runs"]) == 1 and again["runs"][0]["wall_seconds"] == run["wall_seconds"]
