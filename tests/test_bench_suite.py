"""Smoke test of agents/experiments/bench_suite.py (tiny budgets): every task runs with every
planner and regularizer, the JSON holds the thresholds stated in the script, per-run curves, env
steps to solve (or None), and wall time per phase; the table aggregates them."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _suite():
    from agents.experiments import bench_suite  # scripts/bench_suite.py is its command line

    return bench_suite


def test_bench_suite_smoke(tmp_path):
    suite = _suite()
    out = tmp_path / "suite.json"
    state = suite.main(["--smoke", "--seeds", "0", "--json", str(out), "--figures", str(tmp_path),
                        "--oracle-cache", str(tmp_path / "oracle"),
                        "--tasks", "arm-open-loop", "inverted-pendulum"])
    saved = json.loads(out.read_text())
    assert saved["thresholds"]["arm-far"] == {"solved_ratio": 1.05}
    # the Gymnasium task's threshold: within 5 % of its own oracle's return
    ip = saved["thresholds"]["inverted-pendulum"]
    R = saved["oracles"]["inverted-pendulum"]["mean_return"]
    assert ip == {"solved_return": R - 0.05 * abs(R), "oracle_return": R}
    assert "reacher" not in saved["thresholds"]  # not run: no oracle, no threshold
    runs = saved["runs"]
    assert {(r["task"], r["planner"], r["regularization"]) for r in runs} == {
        (t, p, g) for t in ("arm-open-loop", "inverted-pendulum")
        for p in ("ilqr", "cem") for g in ("none", "sampled")}
    for r in runs:
        assert r["env_steps"] <= r["budget_env_steps"]
        assert r["curve"], r  # at least the final evaluation
        assert set(r["wall_seconds_per_phase"]) >= {"training", "ltv", "planning", "eval"}
        if r["env_steps_to_solve"] is not None:
            assert r["env_steps_to_solve"] <= r["env_steps"]
    assert len(state["table"]) == 8
    assert (tmp_path / "bench_suite_curves.png").is_file()
    assert (tmp_path / "bench_suite_planner_x_regularizer.png").is_file()
    # resume skips finished runs
    again = suite.main(["--smoke", "--seeds", "0", "--json", str(out), "--resume",
                        "--tasks", "arm-open-loop", "--oracle-cache", str(tmp_path / "oracle")])
    assert len(again["runs"]) == len(runs)


@pytest.mark.parametrize("name", ["reacher", "inverted-pendulum"])
def test_gymnasium_task_costs_compile(name):
    import gymnasium as gym
    import numpy as np

    from agents.config import AgentConfig
    from agents.jacprop_agent import JacPropAgent

    suite = _suite()
    task = suite.TASKS[name]
    env = gym.make(task["env_id"], **task["make"])
    agent = JacPropAgent(env, AgentConfig.default({"evaluation.every": 0}, progress=False),
                         cost_fn=task["cost"],
                         terminal_cost_fn=task.get("terminal"),
                         termination_fn=task.get("termination"))
    obs = env.reset(seed=0)[0]
    c = agent.task_cost.on_observations(obs[None], np.zeros((1, env.action_space.shape[0])))
    assert np.isfinite(c).all()


def test_regenerating_the_report_keeps_the_hand_written_notes(tmp_path):
    suite = _suite()
    doc = tmp_path / "benchmark.md"
    state = {"table": [], "runs": [], "thresholds": {}, "git": "abc"}
    suite.write_markdown(state, doc, tmp_path)
    doc.write_text(doc.read_text() + "\nWhat the numbers say, by hand.\n")
    state["git"] = "def"
    suite.write_markdown(state, doc, tmp_path)
    text = doc.read_text()
    assert "git def" in text and "git abc" not in text
    assert text.count(suite.NOTES_MARKER) == 1
    assert text.endswith("\nWhat the numbers say, by hand.\n")


@pytest.mark.parametrize("flag", ["--regularizations", "--planners", "--tasks"])
def test_unknown_names_exit_2_with_one_line(flag, capsys):
    with pytest.raises(SystemExit) as e:
        _suite().main([flag, "bogus", "--json", "/tmp/never_written.json"])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip()
    assert flag in err and "\n" not in err


def test_comparisons_pair_the_seeds_both_regularizers_ran():
    suite = _suite()

    def run(reg, seed, steps, score):
        return {"task": "inverted-pendulum", "planner": "ilqr", "regularization": reg,
                "seed": seed, "env_steps_to_solve": steps, "final_score": score,
                "budget_env_steps": 2000, "wall_seconds_per_phase": {"total": 10.0 + seed}}

    none = [run("none", k, s, 200.0) for k, s in enumerate([500, 100, 300, 50, 60])]
    exact = [run("exact", k, s, 190.0) for k, s in enumerate([200, 100, None])]
    (c,) = suite.comparisons(none + exact)
    assert c["regularization"] == "exact" and c["seeds"] == [0, 1, 2]
    # medians on seeds 0-2 only: exact {200, 100, >=2000} -> 200; none {500, 100, 300} -> 300
    assert c["steps_to_solve"] == "200 vs 300"
    assert c["wins_ties_losses"] == "1/1/1"  # seed 0 fewer, seed 1 equal, seed 2 unsolved
    assert c["final_score"] == "190 vs 200"
    assert c["final_scores_better_equal_worse"] == "0/0/3"  # a return: 190 < 200 is worse
    assert c["final_score_ratio"] is None  # positive returns are not costs
    assert c["wall_ratio"] == 1.0  # same seeds, same per-seed walls
