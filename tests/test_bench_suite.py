"""The benchmark suite (agents/experiments/bench_suite.py): every task's cost compiles and its
agent runs a few steps; the smoke mode runs baselines, agents, figures and the report end to
end and resumes; the report's numbers (thresholds, normalized scores, paired comparisons, SAC's
env steps to the agent's final return) agree with hand-computed values."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from agents.experiments import bench_suite as suite

REPO = Path(__file__).resolve().parents[1]


def test_the_suite_reads_every_task_from_the_one_registry():
    """Each suite task is a registry task (same env, cost, termination, state map as
    ``make_task`` builds from its name and env keywords); the suite's budget, evaluation period
    and settings are that task's."""
    from agents.tasks import SUITE, make_task

    assert list(suite.TASKS) == list(SUITE)
    fns = ("env_id", "cost_fn", "terminal_cost_fn", "termination_fn", "state_fn", "obs_fn")
    for name, task in SUITE.items():
        fresh = make_task(task.name, **task.make_kwargs)
        assert [getattr(fresh, f) for f in fns] == [getattr(task, f) for f in fns], name
        assert task.budget > 0 and 0 < task.eval_every <= task.budget
        entry = suite.TASKS[name]
        assert (entry["task"], entry["budget"], entry["eval_every"], entry["overrides"]) == (
            task, task.budget, task.eval_every, task.settings)
        cfg = suite.agent_config(name).dotted()
        assert all(cfg[k] == v for k, v in task.settings.items()), name
    with pytest.raises(ValueError, match="unknown task 'arm-far'; known"):
        make_task("arm-far")  # a suite name, not a registry task


@pytest.mark.parametrize("name", list(suite.TASKS))
def test_every_task_runs_a_few_steps_of_its_agent(name):
    agent = suite.make_agent(name, {"evaluation.every_steps": 0}, smoke=True)
    obs = agent.env.reset(seed=0)[0]
    c = agent.task_cost.on_observations(obs[None], np.zeros((1, agent.spec.act_dim)))
    assert np.isfinite(c).all()
    agent.learn(total_timesteps=25, progress_bar=False)
    assert agent.env_steps == 25
    agent.env.close()


def test_bench_suite_smoke(tmp_path):
    out, base = tmp_path / "suite.json", tmp_path / "baselines.json"
    common = ["--smoke", "--seeds", "0", "--out", str(out), "--baselines-json", str(base),
              "--oracle-cache", str(tmp_path / "oracle"), "--tasks", "arm-open-loop",
              "inverted-pendulum"]
    state = suite.main(common + ["--baselines", "--planners", "cem-ilqr", "ilqr",
                                 "--figures", str(tmp_path), "--docs", str(tmp_path / "b.md")])
    baselines = json.loads(base.read_text())["tasks"]
    for name in ("arm-open-loop", "inverted-pendulum"):
        b = baselines[name]
        assert len(b["zero_returns"]) == len(b["oracle_returns"]) == suite.EVAL_EPISODES
        assert b["oracle_return"] > b["zero_return"]  # the oracle does better than nothing
    runs = json.loads(out.read_text())["runs"]
    assert {(r["task"], r["planner"], r["regularization"]) for r in runs} == {
        (t, p, g) for t in ("arm-open-loop", "inverted-pendulum")
        for p in ("cem-ilqr", "ilqr") for g in ("none", "sampled")}
    for r in runs:
        assert r["env_steps"] == r["budget_env_steps"] == suite.SMOKE_BUDGET
        assert r["curve"], r  # at least the final evaluation
        assert set(r["wall_seconds_per_phase"]) >= {"training", "ltv", "planning", "eval"}
        # one update record per episode: env steps grow, the update's steps within its budget
        steps = [u["env_steps"] for u in r["updates"]]
        assert steps == sorted(steps) and steps[-1] == r["env_steps"]
        budget = suite.SMOKE_OVERRIDES["training.steps"]
        assert all(0 < u["train_steps"] <= budget for u in r["updates"]), r["updates"]
    assert len(state["table"]) == 8
    assert all(row["normalized_median"] is not None for row in state["table"])
    assert (tmp_path / "bench_suite_curves.png").is_file()
    md = (tmp_path / "b.md").read_text()
    assert "bench_suite_curves.png)" in md and "| inverted-pendulum | 2000 |" in md
    assert f"from `{out.resolve()}` (agent runs)" in md  # --out, named (outside the repo)
    again = suite.main(common + ["--resume", "--planners", "cem-ilqr", "ilqr"])
    assert len(again["runs"]) == len(runs)  # resume skips finished runs


@given(st.floats(-1e6, 1e6))
def test_solved_is_within_five_percent_below_the_oracle(oracle):
    thr = suite.solved_return(oracle)
    assert thr <= oracle
    assert oracle - thr == pytest.approx(0.05 * abs(oracle), rel=1e-9, abs=1e-9)


def test_normalized_score_hand_computed():
    b = {"zero_return": -11.0, "oracle_return": -3.0}
    assert suite.normalized(-11.0, b) == 0.0 and suite.normalized(-3.0, b) == 1.0
    assert suite.normalized(-5.0, b) == pytest.approx(0.75)
    assert suite.normalized(None, b) is None and suite.normalized(-5.0, None) is None


def test_regenerating_the_report_keeps_the_hand_written_notes(tmp_path):
    doc = tmp_path / "benchmark.md"
    state = {"table": [], "runs": [], "git": "abc"}
    suite.write_markdown(state, doc, tmp_path, {}, [], [], ("r.json", "b.json", "s.json", "p.json"))
    doc.write_text(doc.read_text() + "\nWhat the numbers say, by hand.\n")
    state["git"] = "def"
    suite.write_markdown(state, doc, tmp_path, {}, [], [], ("r.json", "b.json", "s.json", "p.json"))
    text = doc.read_text()
    assert "git def; the agent runs at -." in text and "git abc" not in text
    assert text.count(suite.NOTES_MARKER) == 1
    assert text.endswith("\nWhat the numbers say, by hand.\n")


@pytest.mark.parametrize("flag", ["--regularizations", "--planners", "--tasks", "--sb3"])
def test_unknown_names_exit_2_with_one_line(flag, capsys):
    with pytest.raises(SystemExit) as e:
        suite.main([flag, "bogus", "--out", "/tmp/never_written.json"])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip()
    assert flag in err and "\n" not in err


def _run(reg, seed, steps, score, planner="cem-ilqr", task="inverted-pendulum"):
    return {"task": task, "planner": planner, "regularization": reg, "seed": seed,
            "env_steps_to_solve": steps, "final_score": score, "budget_env_steps": 2000,
            "env_steps": 2000, "wall_seconds": 10.0 + seed,
            "curve": [{"env_steps": 1000, "score": score / 2}, {"env_steps": 2000, "score": score}],
            "wall_seconds_per_phase": {"total": 10.0 + seed}}


def test_comparisons_pair_the_seeds_both_regularizers_ran():
    none = [_run("none", k, s, 200.0) for k, s in enumerate([500, 100, 300, 50, 60])]
    exact = [_run("exact", k, s, 190.0) for k, s in enumerate([200, 100, None])]
    (c,) = suite.comparisons(none + exact)
    assert c["regularization"] == "exact" and c["seeds"] == [0, 1, 2]
    # medians on seeds 0-2 only: exact {200, 100, >=2000} -> 200; none {500, 100, 300} -> 300
    assert c["steps_to_solve"] == "200 vs 300"
    assert c["wins_ties_losses"] == "1/1/1"  # seed 0 fewer, seed 1 equal, seed 2 unsolved
    assert c["final_score"] == "190 vs 200"
    assert c["final_scores_better_equal_worse"] == "0/0/3"  # a return: 190 < 200 is worse
    assert c["wall_ratio"] == 1.0  # same seeds, same per-seed walls


def test_comparisons_leave_runs_without_a_final_score_out_of_the_score_columns():
    # a budget shorter than the first evaluation (HalfCheetah's smoke run) leaves no score
    def run(reg, seed, score):
        return {**_run(reg, seed, None, 1.0), "final_score": score, "curve": []}

    none = [run("none", k, sc) for k, sc in enumerate([None, 200.0, 100.0])]
    sampled = [run("sampled", k, sc) for k, sc in enumerate([150.0, None, 120.0])]
    (c,) = suite.comparisons(none + sampled)
    assert c["seeds"] == [0, 1, 2] and c["wins_ties_losses"] == "0/3/0"
    assert c["final_score"] == "120 vs 100"  # seed 2 only: the one pair with both scores
    assert c["final_scores_better_equal_worse"] == "1/0/0"
    (c,) = suite.comparisons([run("none", 0, None), run("sampled", 0, None)])
    assert c["final_score"] == "- vs -" and c["final_scores_better_equal_worse"] == "0/0/0"


def test_settings_comparison_pairs_seeds_and_draws_both(tmp_path):
    base = [_run("none", k, None, f, task="reacher") for k, f in enumerate([-5.0, -6.0, -7.0])]
    base += [_run("sampled", 0, None, -1.0, task="reacher")]  # another regularizer: not paired
    variant = [_run("none", k, None, f, task="reacher") for k, f in ((1, -4.0), (2, -7.0),
                                                                       (3, -1.0))]
    for runs, seconds in ((base, 1.0), (variant, 2.0)):
        for r in runs:
            r["wall_seconds_per_phase"]["training"] = seconds
    baselines = {"reacher": {"zero_return": -12.0, "oracle_return": -4.0}}
    (row,) = suite.settings_comparison(base, variant, baselines)
    assert row["seeds"] == [1, 2]  # seed 3 has no suite run, seed 0 no variant run
    assert row["finals"] == [[-6.0, -7.0], [-4.0, -7.0]]
    assert row["final_median"] == [-6.5, -5.5]
    assert row["normalized_median"] == [pytest.approx(5.5 / 8), pytest.approx(6.5 / 8)]
    assert row["better_equal_worse"] == "1/1/0"
    # no run records CPU seconds: the median wall seconds of seeds 1-2 (11, 12) of both
    assert row["seconds"] == "wall_seconds" and row["seconds_median"] == [11.5, 11.5]
    assert row["training_seconds_median"] == [1.0, 2.0]
    path = suite.settings_figure(base, variant, "p20", tmp_path / "s.png")
    assert path.stat().st_size > 10_000
    # another budget (a smoke run) or a run without a final score does not pair
    variant[0]["budget_env_steps"] = 200
    variant[1]["final_score"] = None
    assert suite.settings_comparison(base, variant, baselines) == []


def test_settings_labels_name_the_base_and_only_what_the_variant_changes():
    p20 = {"training.patience": 20, "training.steps": 4000}
    assert suite.settings_labels({}, p20) == (
        "the suite's", "training.patience=20, training.steps=4000")
    base, label = suite.settings_labels(p20, {**p20, "collection.exploration_window": 8})
    assert base == "base (training.patience=20, training.steps=4000)"
    assert label == "collection.exploration_window=8"
    assert suite.settings_labels(p20, {"training.patience": 20})[1] == (
        "training.steps=default")
    assert suite.settings_labels(p20, dict(p20))[1] == "same"
    # runs that differ by code, not settings, name themselves (a compared JSON's "label"),
    # and settings that also differ stay visible after the label
    assert suite.settings_labels(p20, dict(p20), "sin/cos pitch") == (
        "base (training.patience=20, training.steps=4000)", "sin/cos pitch")
    assert suite.settings_labels(p20, {**p20, "training.patience": 5}, " v2 ")[1] == (
        "v2; training.patience=5")
    for bad in (2, ["a"], "", "  ", False):
        with pytest.raises(ValueError, match="non-blank string"):
            suite.settings_labels(p20, dict(p20), bad)


@pytest.mark.parametrize("extra", [[], ["--report-only", "--docs", "d.md"]])
def test_compare_needs_report_only_without_docs(tmp_path, extra):
    with pytest.raises(SystemExit) as e:
        suite.main(["--compare", str(tmp_path / "v.json"), "--out", str(tmp_path / "x.json"),
                    *extra])
    assert e.value.code == 2


def test_compare_refuses_a_missing_file_and_runs_that_pair_with_none(tmp_path, capsys):
    base, variant = tmp_path / "suite.json", tmp_path / "v.json"
    base.write_text(json.dumps({"runs": [_run("none", 0, None, -5.0, task="reacher")]}))
    variant.write_text(json.dumps({"runs": [_run("none", 1, None, -4.0, task="reacher")]}))
    labelled = tmp_path / "labelled.json"
    labelled.write_text(json.dumps({"label": 2, "runs": [_run("none", 0, None, -4.0,
                                                                task="reacher")]}))
    for path, says in ((tmp_path / "nope.json", "not a readable JSON"),
                       (variant, "none of its runs pairs"),
                       (labelled, f"--compare {labelled}: the compared JSON's \"label\"")):
        with pytest.raises(SystemExit):
            suite.main(["--report-only", "--out", str(base), "--compare", str(path)])
        assert says in capsys.readouterr().err


def test_reference_rows_hand_computed():
    runs = [_run("none", k, None, -4.0 - k, task="reacher") for k in range(3)]
    baselines = {"reacher": {"zero_return": -12.0, "oracle_return": -4.0,
                             "oracle_ms_per_step_bound": 30.0}}
    sac = [{"task": "reacher", "method": "sac", "seed": 0, "curve": [
        {"env_steps": 0, "score": -12.0}, {"env_steps": 50_000, "score": -6.0},
        {"env_steps": 100_000, "score": -4.5}]}]
    pets = [{"task": "reacher", "seed": s, "wall_seconds": 100.0 * (s + 1), "env_steps": 2000,
             "curve": [{"env_steps": 1000, "score": -8.0 + s},
                       {"env_steps": 2000, "score": -6.0 + s}]} for s in (0, 1)]
    pets.append({"task": "reacher", "seed": 2, "wall_seconds": 50.0, "env_steps": 1000,
                 "curve": [{"env_steps": 1000, "score": -9.0}]})  # stopped at 1,000
    state = {"runs": runs, "table": suite.aggregate(runs, baselines)}
    row = next(r for r in suite.reference_rows(state, baselines, sac, pets)
               if r["task"] == "reacher")
    assert row["best"]["final_score_median"] == -5.0  # finals -4, -5, -6
    assert row["best"]["normalized_median"] == pytest.approx((-5 + 12) / 8)
    assert row["sac_50k"] == -6.0 and row["sac_100k"] == -4.5
    # SAC reaches -5.0 first at 100,000 env steps: 50x the agent's 2,000
    assert row["sac_steps_to_agent_final"] == {"value": 100_000.0, "lower_bound": False}
    assert row["sac_ratio"]["value"] == pytest.approx(50.0)
    # the agent's seeds are at -2, -2.5, -3 (>= -5) from their first evaluation at 1,000
    assert row["agent_steps_to_final"] == 1000.0
    assert row["sac_ratio_first_reach"] == {"value": pytest.approx(100.0), "lower_bound": False}
    # at 1,000 every PETS run counts (-8, -7, -9 -> -8); at 2,000 only seeds 0-1 (-6, -5)
    (at_1k, at_2k) = row["pets_points"]
    assert at_1k["env_steps"] == 1000 and at_1k["pets"] == -8.0
    assert at_1k["pets_seeds"] == [0, 1, 2] and at_1k["agent"] == -2.5  # agent: -2, -2.5, -3 @ 1000
    assert at_2k["pets"] == -5.5 and at_2k["pets_seeds"] == [0, 1]
    assert row["pets"] == -5.5 and row["pets_env_steps"] == 2000
    assert row["agent_at_pets_steps"] == -5.0
    assert row["pets_wall_per_step"] == pytest.approx(0.05)  # of 100/2000, 200/2000, 50/1000


def test_agent_steps_to_its_final_take_the_lower_median_seed():
    """Two seeds: finals -5 (reached at 2,000) and -6 (at -6.5 until then) -> F = -5.5; seed 0
    reaches it at 2,000 (-5 >= -5.5), seed 1 never (-6): the lower median is 2,000, a finite
    ratio (np.median would give inf with half the seeds short)."""
    runs = [_run("none", k, None, f, task="reacher") for k, f in enumerate([-5.0, -6.0])]
    for r in runs:
        r["curve"] = [{"env_steps": 1000, "score": -6.5}, {"env_steps": 2000,
                                                            "score": r["final_score"]}]
    baselines = {"reacher": {"zero_return": -12.0, "oracle_return": -4.0,
                             "oracle_ms_per_step_bound": 30.0}}
    sac = [{"task": "reacher", "method": "sac", "seed": 0, "curve": [
        {"env_steps": 50_000, "score": -6.0}, {"env_steps": 100_000, "score": -5.0}]},
        {"task": "reacher", "method": "sac", "seed": 1, "curve": []}]  # empty: not counted
    state = {"runs": runs, "table": suite.aggregate(runs, baselines)}
    (row,) = [r for r in suite.reference_rows(state, baselines, sac, [])
              if r["task"] == "reacher"]
    assert row["best"]["final_score_median"] == -5.5
    assert row["agent_steps_to_final"] == 2000.0
    assert row["sac_steps_to_agent_final"] == {"value": 100_000.0, "lower_bound": False}
    assert row["sac_ratio_first_reach"] == {"value": pytest.approx(50.0), "lower_bound": False}
    runs[0]["curve"][1]["score"] = -5.6  # now neither seed reaches F = -5.5 on its curve
    row = next(r for r in suite.reference_rows(state, baselines, sac, [])
               if r["task"] == "reacher")
    assert row["agent_steps_to_final"] == float("inf")
    assert row["sac_ratio_first_reach"]["value"] is None
    assert suite._bound(row["sac_ratio_first_reach"]) == "-"


def test_solved_is_read_from_the_curve_against_the_stored_oracle():
    run = _run("none", 0, None, -4.0, task="reacher")  # curve: -2.0 at 1000, -4.0 at 2000
    b = {"reacher": {"oracle_return": -3.0, "zero_return": -12.0}}  # solved at >= -3.15
    (r,) = suite.with_solved([run], b)
    assert r["env_steps_to_solve"] == 1000 and run["env_steps_to_solve"] is None
    (r,) = suite.with_solved([run], {"reacher": {"oracle_return": -1.0, "zero_return": -9.0}})
    assert r["env_steps_to_solve"] is None  # -2.0 < -1.05
    assert suite.with_solved([run], {})[0] is run  # no baseline: the run's own value


def test_the_report_names_the_commits_its_runs_were_produced_at():
    """The report's "git" is the commit of the last call (a --resume or a regenerated report
    may come later): the commits of the runs themselves are named too, each with its count."""
    runs = [{"git_sessions": ["abc"]}, {"git_sessions": ["abc", "def-dirty"]},
            {"git_sessions": ["abc", "abc"]}, {}]
    assert suite._run_commits(runs) == "abc (3 runs), def-dirty (1 run), unrecorded (1 run)"
    assert suite._run_commits([]) == "-"


def test_a_stored_baseline_of_other_planner_settings_is_refused():
    """The oracle's return sets the solved threshold: one computed with another horizon or
    terminal weight than the task's settings now is refused, naming the command to recompute."""
    from agents.config import PlannerConfig
    from agents.experiments.bench_suite import _check_baseline_settings, _planner_settings

    cfg = PlannerConfig(horizon=15, terminal_weight=100.0)
    stored = {"planner": _planner_settings(cfg)}
    _check_baseline_settings("inverted-double-pendulum", stored, cfg)  # same settings: fine
    _check_baseline_settings("x", stored, PlannerConfig(kind="ilqr", horizon=15,
                                                        terminal_weight=100.0))  # kind aside
    old = dataclasses.replace(cfg, warm_samples=None)  # warm solves sampled all 64 before
    _check_baseline_settings("x", {"planner": {"kind": "cem-ilqr", "horizon": 15}}, old)
    with pytest.raises(ValueError, match=r"'warm_samples': None.*'warm_samples': 32"):
        _check_baseline_settings("x", {"planner": {"kind": "cem-ilqr", "horizon": 15}}, cfg)
    with pytest.raises(ValueError, match=r"horizon.*--baselines --tasks inverted-double"):
        _check_baseline_settings("inverted-double-pendulum", stored,
                                 PlannerConfig().for_task(None, None))
    # the proposal's samples are part of the oracle too (stored since 2026-12-03)
    fewer = PlannerConfig(horizon=15, terminal_weight=100.0,
                          proposal=dataclasses.replace(cfg.proposal, samples=32))
    with pytest.raises(ValueError, match=r"'samples': 64.*'samples': 32"):
        _check_baseline_settings("inverted-double-pendulum", stored, fewer)


def test_a_paused_checkpointed_run_ends_as_an_uninterrupted_one(tmp_path, monkeypatch):
    """--checkpoints with --stop-after-steps: the run pauses (nothing recorded), continues from
    its checkpoint at the next call and ends with the same curve as a run without pauses; a
    checkpoint of other settings is refused."""
    common = ["--smoke", "--seeds", "0", "--tasks", "reacher", "--regularizations", "sampled",
              "--oracle-cache", str(tmp_path / "oracle"), "--baselines-json",
              str(tmp_path / "none.json")]
    straight = suite.main(common + ["--out", str(tmp_path / "a.json")])["runs"]
    assert straight[0]["git_sessions"] == [suite._git()]  # without checkpoints too
    assert straight[0]["versions"]["numpy"] == np.__version__
    paused = common + ["--out", str(tmp_path / "b.json"), "--resume",
                       "--checkpoints", str(tmp_path / "ckpt"), "--stop-after-steps", "120"]
    assert suite.main(paused)["runs"] == []  # 150 of 200 steps: paused, not recorded
    from agents.jacprop_agent import JacPropAgent

    episodes, run_episode = [], JacPropAgent._episode
    monkeypatch.setattr(JacPropAgent, "_episode",
                        lambda self, **kw: episodes.append(1) or run_episode(self, **kw))
    # another oracle cache is a path, not a setting of the run: accepted
    resumed = suite.main(paused + ["--oracle-cache", str(tmp_path / "oracle2")])["runs"]
    assert len(episodes) == 1  # the last 50-step episode only: continued, not started over
    assert len(resumed) == 1 and resumed[0]["env_steps"] == suite.SMOKE_BUDGET
    assert resumed[0]["curve"] == straight[0]["curve"]
    assert resumed[0]["final_score"] == straight[0]["final_score"]
    assert resumed[0]["cpu_seconds"] > 0 and len(resumed[0]["git_sessions"]) == 2
    folder = tmp_path / "ckpt" / "reacher_cem-ilqr_sampled_seed0"
    with pytest.raises(ValueError, match=r"config differs in 'evaluation.every_steps' "
                       r"\(checkpoint: 100, now: 250\)"):
        suite.run_one("reacher", "cem-ilqr", "sampled", 0, smoke=False,
                      oracle_cache=str(tmp_path / "oracle"), baseline=None,
                      checkpoint_dir=folder)


def test_stop_after_steps_needs_checkpoints(capsys, tmp_path):
    with pytest.raises(SystemExit) as exc:
        suite.main(["--smoke", "--stop-after-steps", "100"])
    assert exc.value.code == 2 and "--checkpoints" in capsys.readouterr().err
    with pytest.raises(ValueError, match="needs checkpoint_dir"):
        suite.run_one("reacher", "cem-ilqr", "none", 0, smoke=True, oracle_cache=str(tmp_path),
                      baseline=None, stop_after=50)


def test_agent_settings_reach_every_run_and_keep_their_json_apart(tmp_path, capsys):
    out = tmp_path / "suite.json"
    common = ["--smoke", "--seeds", "0", "--baselines-json", str(tmp_path / "b.json"),
              "--oracle-cache", str(tmp_path / "oracle"), "--tasks", "inverted-pendulum",
              "--regularizations", "none"]
    # nested sections are flattened; a re-plan period beyond the smoke horizon lengthens it
    settings = {"model": {"hidden_width": 5}, "planner.replan_every": 8}
    state = suite.main(common + ["--out", str(out), "--agent-settings", json.dumps(settings)])
    (run,) = state["runs"]
    flat = {"model.hidden_width": 5, "planner.replan_every": 8}
    assert run["agent_settings"] == state["agent_settings"] == flat
    assert run["model"]["hidden_width"] == 5  # the setting reached the agent
    with pytest.raises(SystemExit) as e:
        suite.main(common + ["--out", str(out), "--resume",
                             "--agent-settings", '{"model.hidden_width": 6}'])
    assert e.value.code == 2 and "holds runs with agent settings" in capsys.readouterr().err
    fresh = tmp_path / "fresh.json"
    for bad, why in (('{"seed": 3}', "suite's own"), ('{"evaluation.episodes": 1}', "suite's own"),
                     ('{"evaluation": {"episodes": 1}}', "suite's own"),
                     ('{"evaluation": 1}', "suite's own"),
                     ('{"planner": {"kind": "cem"}}', "suite's own"),
                     ('{"regularization": "exact"}', "suite's own"),
                     ('{"torch_threads": 2}', "suite's own"),
                     ('{"planner": "cem"}', "unknown AgentConfig field"),
                     ('{"planner.cem": 5}', "unknown AgentConfig field"),
                     ('{"planner.replan_evry": 8}', "closest valid field is "
                                                     "'planner.replan_every'"),
                     ('{"video": true}', "suite's own"),
                     ('{"model": {"hidden_width": 5}, "model.hidden_width": 6}', "given twice"),
                     # weights that would make the "none" runs another regularizer
                     ('{"regularization.sampled_weight": 1.0}', "make the 'none' runs"),
                     ('{"planner.horizon": 20}', "true-model oracle"),
                     ('{"planner": {"cem": {"samples": 9}}}', "true-model oracle"),
                     # a value the config refuses fails before the first run starts
                     ('{"planner.replan_feedback": true}', "inverted-pendulum with cem-ilqr"),
                     ("[1]", "JSON object"), ("nope", "not JSON")):
        with pytest.raises(SystemExit) as e:
            suite.main(common + ["--out", str(fresh), "--agent-settings", bad])
        err = capsys.readouterr().err
        assert e.value.code == 2 and why in err, (bad, err)
        assert not fresh.exists()
    for only in (["--report-only"], ["--sb3", "sac"]):
        with pytest.raises(SystemExit) as e:
            suite.main(only + ["--out", str(out), "--agent-settings", json.dumps(flat)])
        assert e.value.code == 2 and "--report-only and --sb3 run none" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:  # a report of no file would be a report of nothing
        suite.main(["--report-only", "--out", str(tmp_path / "missing.json")])
    assert e.value.code == 2 and "missing.json is no file" in capsys.readouterr().err


def test_every_suite_task_plans_with_the_settings_of_its_stored_baseline():
    """The stored oracle of each suite task (docs/results/bench_suite_baselines.json) was
    computed with the planner the task's agent builds now, the horizon rule resolved: a run of
    the suite from a clean checkout is not refused."""
    stored = suite.load_baselines()
    for name in suite.TASKS:
        agent = suite.make_agent(name)
        suite._check_baseline_settings(name, stored[name], agent.config.planner)
        terminates = agent.termination_fn is not None
        assert (agent.config.planner.horizon, agent.config.planner.terminal_weight) == (
            (15, 100.0) if terminates else (30, 1.0)), name
        agent.env.close()
