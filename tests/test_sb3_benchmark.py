"""SB3 baselines and the benchmark script (issue 7).

- the callback's evaluation cost is minus the return SB3's own ``evaluate_policy`` measures on
  the same targets and resets (raw observations for SAC, ``VecNormalize`` for PPO);
- the censored-median / best-of / ratio helpers agree with brute force over completions of the
  censored values (hypothesis);
- ``scripts/benchmark_sb3.py --quick`` runs end to end and writes JSON, PNG and markdown, with
  unsolved runs reported as lower bounds.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
from helpers_sb3 import SMALL_RUNS, ScriptedResets, sb3_returns
from hypothesis import given, settings
from hypothesis import strategies as st

import envs  # noqa: F401  (registers mbtsr/TwoLinkArm-v0)
from agents.sb3_baselines import best_of, censored_median, default_hyperparams, train_sb3

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "scripts" / "benchmark_sb3.py"
ARM = "mbtsr/TwoLinkArm-v0"
TARGETS = [[0.4, -0.3], [-0.8, 0.5], [1.0, 0.2]]
EVAL_SEED = 1000


@pytest.fixture(autouse=True)
def _one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def _load_script():
    from agents.experiments import benchmark_sb3

    return benchmark_sb3


# ---------------------------------------------------------------------------------------------
# the callback's cost is minus SB3's episode return
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("algo, budget, every, hyperparams", SMALL_RUNS)
def test_callback_cost_is_minus_sb3_return(algo, budget, every, hyperparams):
    rec = train_sb3(algo, ARM, budget, seed=3, eval_every=every, eval_targets=TARGETS,
                    threshold=None, hyperparams=hyperparams, eval_seed=EVAL_SEED,
                    return_model=True)
    model = rec.pop("model")
    json.dumps(rec)  # the record is JSON-serializable
    assert [s for s, _ in rec["curve"]] == list(range(0, budget + 1, every))
    assert rec["env_steps"] == budget and not rec["solved"] and rec["steps_to_solve"] is None

    returns, lengths = sb3_returns(model, ScriptedResets(gym.make(ARM), EVAL_SEED, TARGETS),
                                   len(TARGETS), bool(hyperparams.get("normalize")))
    assert lengths == [100] * len(TARGETS)
    # the final curve point is the final policy; rewards pass through float32 in the VecEnv
    assert rec["curve"][-1][1] == pytest.approx(-np.mean(returns), rel=1e-5)


def test_stops_at_first_solved_evaluation():
    # the untrained policy's cost on these targets, then a threshold just above it: solved at 0
    probe = train_sb3("td3", ARM, 1, seed=0, eval_every=1, eval_targets=TARGETS[:1],
                      threshold=None, hyperparams={"learning_starts": 10}, eval_seed=EVAL_SEED)
    cost0 = probe["curve"][0][1]
    rec = train_sb3("td3", ARM, 10_000, seed=0, eval_every=50, eval_targets=TARGETS[:1],
                    threshold=cost0 * 1.0001, hyperparams={"learning_starts": 10},
                    eval_seed=EVAL_SEED)
    assert rec["solved"] and rec["steps_to_solve"] == 0
    assert rec["env_steps"] <= 1  # stopped at the first on_step after the solved evaluation
    assert rec["curve"] == [[0, pytest.approx(cost0, rel=1e-12)]]
    assert 0 <= rec["wall_seconds_to_solve"] <= rec["wall_seconds_to_solve_incl_eval"]


@pytest.mark.parametrize(
    "kwargs, msg",
    [
        ({"algo": "a2c"}, "algo"),
        ({"budget_steps": 0}, "budget_steps"),
        ({"eval_every": 1.5}, "eval_every"),
        ({"seed": -1}, "seed"),
        ({"eval_targets": [[0.1, np.nan]]}, "eval_targets"),
        ({"eval_targets": [0.1, 0.2]}, "eval_targets"),
        ({"threshold": -1.0}, "threshold"),
        ({"threshold": np.inf}, "threshold"),
        ({"hyperparams": {"no_such_kwarg": 1}}, "hyperparams"),
        ({"hyperparams": {"action_noise_std": 0.1}, "algo": "ppo"}, "action_noise_std"),
    ],
)
def test_bad_arguments(kwargs, msg):
    args = {"algo": "sac", "env_id": ARM, "budget_steps": 10, "seed": 0, "eval_every": 5,
            "eval_targets": TARGETS, "threshold": 1.0}
    args.update(kwargs)
    with pytest.raises(ValueError, match=msg):
        train_sb3(**args)


def test_default_hyperparams_are_documented_choices():
    assert default_hyperparams("sac") == {}
    assert default_hyperparams("td3") == {"action_noise_std": 0.1}
    assert default_hyperparams("ppo") == {"normalize": True}


# ---------------------------------------------------------------------------------------------
# censored statistics: brute force over completions of the censored values
# ---------------------------------------------------------------------------------------------

values_and_flags = st.lists(
    st.tuples(st.integers(1, 50).map(float), st.booleans()), min_size=1, max_size=7
)


@settings(max_examples=200, deadline=None)
@given(values_and_flags, st.lists(st.integers(0, 60), min_size=7, max_size=7))
def test_censored_median_bounds_every_completion(pairs, extra):
    values = [v for v, _ in pairs]
    lower = [b for _, b in pairs]
    med, is_lb = censored_median(values, lower)
    # completions: each censored value raised by 0, some amount, or a lot
    completions = [
        [v + (e * scale if b else 0) for (v, b), e in zip(pairs, extra)]
        for scale in (0, 1, 1000)
    ]
    medians = [float(np.median(c)) for c in completions]
    assert all(m >= med for m in medians)  # always a valid lower bound ...
    assert medians[0] == med  # ... attained when the censored values are at their bounds
    if not is_lb:  # an exact median does not move whatever the censored values are
        assert all(m == med for m in medians)
    if not any(lower):
        assert not is_lb and med == float(np.median(values))


@settings(max_examples=200, deadline=None)
@given(st.dictionaries(st.sampled_from("abcd"), st.tuples(st.integers(1, 20).map(float),
                                                          st.booleans()), min_size=1),
       st.integers(0, 30))
def test_best_of_bounds_the_true_minimum(medians, raise_by):
    name, value, is_lb = best_of(medians)
    assert medians[name] == (value, is_lb)
    # a completion: every lower bound replaced by a larger true value
    true = {n: v + (raise_by if lb else 0) for n, (v, lb) in medians.items()}
    assert min(true.values()) >= value
    if not is_lb:
        assert min(true.values()) == value


def test_ratio_kinds_and_targets():
    bench = _load_script()
    exact = bench.bound(100.0, False)
    lower = bench.bound(4000.0, True)
    r = bench.ratio(lower, exact)  # SB3 censored, agent solved
    assert r["kind"] == "lower" and r["display"] == ">= 40" and bench.target_met(r, 20) is True
    r = bench.ratio(bench.bound(1000.0, True), exact)
    assert bench.target_met(r, 20) is None  # >= 10 cannot tell whether >= 20
    r = bench.ratio(exact, lower)  # agent censored: only an upper bound
    assert r["kind"] == "upper" and bench.target_met(r, 20) is False
    assert bench.ratio(lower, lower)["kind"] == "undetermined"
    assert bench.target_met(bench.ratio(exact, exact), 1.0, strict=True) is False


# ---------------------------------------------------------------------------------------------
# the script's --quick mode, end to end
# ---------------------------------------------------------------------------------------------


def test_quick_benchmark_writes_json_png_markdown(tmp_path):
    out = tmp_path / "report.json"
    docs = tmp_path / "docs" / "benchmark.md"
    cmd = [sys.executable, str(SCRIPT), "--quick", "--json", str(out), "--docs", str(docs),
           "--out-dir", str(tmp_path / "runs"), "--no-tensorboard"]
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]

    report = json.loads(out.read_text())
    assert report["quick"] and report["n_failed_runs"] == 0
    assert set(report["methods"]) == {"jacprop", "none", "sac", "td3", "ppo"}
    assert report["threshold"] == pytest.approx(1.2 * report["oracle_cost"])
    for name, m in report["methods"].items():
        assert m["n_runs"] == 1, name
        run = m["runs"][0]
        assert run["curve"], name
        steps = run["steps_to_solve"]
        if not run["solved"]:  # reported as a lower bound at the budget actually spent
            assert steps["lower_bound"] and steps["value"] == run["env_steps"]
            assert steps["display"] == f">= {run['env_steps']}"
            assert m["median_steps_to_solve"]["lower_bound"]
            assert run["wall_seconds_to_solve"]["display"].startswith(">= ")
    # tiny SB3 budgets cannot solve the task: their numbers must be lower bounds
    for name in ("sac", "td3", "ppo"):
        assert not report["methods"][name]["runs"][0]["solved"]
    for agent in ("jacprop", "none"):
        run = report["methods"][agent]["runs"][0]
        assert run["agent_oracle_cost"] == pytest.approx(report["oracle_cost"], rel=1e-9)

    png = docs.with_name("benchmark_curves.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000
    md = docs.read_text()
    assert "scripts/benchmark_sb3.py --quick" in md and "](benchmark_curves.png)" in md
    assert "| SB3 SAC | 200 | 0/1 | **>= 200**" in md
