"""Smoke and behaviour tests of the paper-reproduction scripts (``scripts/exp_*.py``).

Every ``--smoke`` mode runs for real (real MuJoCo, real training, tiny budgets) into a temporary
folder; the tests check the per-run JSON records, the figures and the summary, and that the
report step redraws everything from the stored JSON alone (without rerunning anything). The
shared helpers of ``agents.experiments.paper_common`` are checked against independent computations.
"""

from __future__ import annotations

import json
import math
import os
import runpy
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

REPO = Path(__file__).resolve().parents[1]
SCRIPTS = REPO / "scripts"
sys.path.insert(0, str(SCRIPTS))

from agents.experiments import paper_common as pc  # noqa: E402
from mbtsr.io import write_json_atomic  # noqa: E402

#: script -> (number of configs in --smoke, figures it draws, numeric result keys to check)
SMOKE = {
    "exp_linear.py": (4, ["linear_eigenvalues.png", "linear_errors.png", "linear_rounds.png"],
                      ["jac_err", "jac_rms_entry", "pred_rms", "sim_rms", "eig_match_err"]),
    "exp_weight_decay.py": (4, ["weight_decay_eigenvalues.png", "weight_decay_errors.png"],
                            ["eig_mean_abs", "eig_mean_dist_to_1", "eig_match_err"]),
    "exp_robot.py": (4, ["robot_errors.png"], ["pred_rms", "jac_err", "jac_rms_entry"]),
    "exp_activations.py": (1, ["activations.png"], []),
    "exp_deviations.py": (4, ["deviations.png"], ["pred_rms", "jac_err"]),
}


def run_script(script: str, *argv: str) -> None:
    """Run ``scripts/<script>`` as ``__main__`` in this process (shares the imports)."""
    old = sys.argv
    sys.argv = [str(SCRIPTS / script), *argv]
    try:
        runpy.run_path(str(SCRIPTS / script), run_name="__main__")
    finally:
        sys.argv = old


def snapshot(folder: Path) -> dict[str, int]:
    return {p.name: p.stat().st_mtime_ns for p in sorted(folder.glob("*.json"))}


@pytest.mark.parametrize("script", list(SMOKE))
def test_smoke_mode_writes_runs_figures_and_redraws_from_json(script, tmp_path, capsys):
    n_configs, figures, keys = SMOKE[script]
    out = tmp_path / "out"
    run_script(script, "--smoke", "--out", str(out), "--backend", "serial")

    runs = sorted((out / "runs").glob("*.json"))
    assert len(runs) == n_configs * 2  # --smoke: 2 Monte-Carlo seeds per config
    assert not (out / "errors").exists() or not list((out / "errors").iterdir())
    for path in runs:
        rec = json.loads(path.read_text())
        assert rec["status"] == "ok" and rec["seed"] in (0, 1)
        for k in keys:
            v = rec["result"][k]
            assert v is not None and math.isfinite(v) and v >= 0, (path.name, k, v)
    for fig in figures:
        assert (out / "figures" / fig).stat().st_size > 5000
    summary = json.loads((out / "summary.json").read_text())
    assert summary["n_records"] == len(runs)
    assert json.loads((out / "args.json").read_text())["args"]["smoke"] is True

    # the report step alone: redraws figures and summary from the JSON, reruns nothing
    before = snapshot(out / "runs")
    for fig in figures:
        (out / "figures" / fig).unlink()
    (out / "summary.json").unlink()
    run_script(script, "--smoke", "--out", str(out), "--report-only")
    assert snapshot(out / "runs") == before
    for fig in figures:
        assert (out / "figures" / fig).stat().st_size > 5000
    assert json.loads((out / "summary.json").read_text()) == summary
    assert len(json.loads((out / "sweeps.json").read_text())) == 1  # no second sweep

    if script != "exp_activations.py":  # the cheapest one checks resuming
        return
    # a second full invocation resumes: nothing is recomputed
    run_script(script, "--smoke", "--out", str(out), "--backend", "serial")
    assert snapshot(out / "runs") == before
    log = json.loads((out / "sweeps.json").read_text())
    assert log[-1]["runs_finished_before"] == log[-1]["runs_finished_after"] == len(runs)


def test_cli_with_process_pool(tmp_path):
    """The real command line with the forkserver process pool (module-level run functions)."""
    out = tmp_path / "lin"
    proc = subprocess.run(
        [sys.executable, str(SCRIPTS / "exp_linear.py"), "--smoke", "--mc", "1", "--rounds",
         "1", "--out", str(out), "--backend", "process", "--workers", "2"],
        capture_output=True, text=True, timeout=300, cwd=tmp_path,
        env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert proc.returncode == 0, proc.stderr[-2000:]
    recs = [json.loads(p.read_text()) for p in (out / "runs").glob("*.json")]
    assert sorted(r["name"] for r in recs) == ["exact", "none", "sampled", "smooth"]
    # all methods of a seed share the system and the initial weights: same true eigenvalues
    true = {json.dumps(r["result"]["eig_true"]) for r in recs}
    assert len(true) == 1


def test_report_only_without_runs_fails_clearly(tmp_path):
    with pytest.raises(SystemExit, match="no finished runs"):
        run_script("exp_robot.py", "--smoke", "--out", str(tmp_path), "--report-only")


# ------------------------------------------------------------------------------------------------
# paper_common helpers against independent computations


def test_linear_dataset_follows_algorithm_2_and_the_recursion():
    cfg = pc.LinearData(n_val=2, n_sim=1, n_train=2)
    d = pc.linear_dataset(cfg, seed=3)
    A, B = d["A"], d["B"]
    # Algorithm 2: expm of a shifted skew matrix -> every |eigenvalue| = exp(-dt^2)
    np.testing.assert_allclose(np.abs(np.linalg.eigvals(A)), np.exp(-cfg.dt**2), rtol=1e-10)
    for tr in d["val"] + d["sim"]:  # noise-free: exact linear recursion
        np.testing.assert_allclose(tr.x[1:], tr.x[:-1] @ A.T + tr.u @ B.T, atol=1e-10)
    for tr in d["train"]:  # training states carry N(0, 0.01^2) noise
        resid = tr.x[1:] - tr.x[:-1] @ A.T - tr.u @ B.T
        assert 0.005 < resid.std() < 0.03
    # the input: 5-tap moving average of 10 N(0,1), steady-state std 10/sqrt(5)
    u = np.concatenate([tr.u[10:] for tr in d["train"] + d["val"]])
    assert abs(u.std() / (10 / np.sqrt(5)) - 1) < 0.15
    # same seed, same data; the bug flag only touches the last training state
    d2 = pc.linear_dataset(pc.LinearData(n_val=2, n_sim=1, n_train=2, last_state_zero=True), 3)
    np.testing.assert_array_equal(d2["val"][0].x, d["val"][0].x)
    np.testing.assert_array_equal(d2["train"][0].x[:-1], d["train"][0].x[:-1])
    assert np.abs(d2["train"][0].x[-1]).max() < 0.1 < np.abs(d["train"][0].x[-1]).max()


def test_held_input_resamples_the_nominal_signal():
    from mbtsr.excitation import filtered_gaussian

    base = filtered_gaussian(41, 2, window=100, scale=3.0, seed=np.random.default_rng(5))
    same = pc.held_filtered_gaussian(40, 2, np.random.default_rng(5), dt=0.02, scale=3.0)
    np.testing.assert_array_equal(same, base[:40])
    fast = pc.held_filtered_gaussian(200, 2, np.random.default_rng(5), dt=0.004, scale=3.0)
    np.testing.assert_array_equal(fast, np.repeat(base[:40], 5, axis=0))
    slow = pc.held_filtered_gaussian(8, 2, np.random.default_rng(5), dt=0.1, scale=3.0)
    np.testing.assert_array_equal(slow, base[:40:5])


def test_robot_data_covers_the_same_experiment_at_other_sample_rates():
    from envs.collect import rollout_open_loop

    nominal = pc.robot_dataset(pc.RobotData(n_train=1, n_val=1, n_sim=1), seed=2)
    slow = pc.robot_dataset(pc.RobotData(n_train=1, n_val=1, n_sim=1, dt=0.1), seed=2)
    x0, tr = nominal["val"][0].x, slow["val"][0]
    assert x0.shape == (201, 4) and tr.x.shape == (41, 4)
    np.testing.assert_array_equal(tr.x[0], x0[0])  # same start state
    np.testing.assert_array_equal(tr.u, nominal["val"][0].u[::5])  # same signal, subsampled
    # the same continuous-time system: replaying the 0.1-s held input at the nominal rate
    # gives the 0.1-s samples (up to the Euler substep size, 0.002 vs 0.01 s)
    env = pc.arm_env(pc.RobotData())
    x, _, _ = rollout_open_loop(env, np.repeat(tr.u, 5, axis=0), reset_options={"state": tr.x[0]})
    assert np.abs(x[::5] - tr.x).max() < 0.01 * np.abs(tr.x).max()
    assert np.all(np.abs(x0[:, :2]) < 0.9 * np.pi)


def test_evaluate_is_zero_for_the_true_model():
    """The metric bundle on the true linear model: zero errors, no divergence."""
    from mbtsr.dynamics import LinearDynamics

    d = pc.linear_dataset(pc.LinearData(n_val=2, n_sim=2, n_train=1), seed=0)

    class Exact(LinearDynamics):
        def member_jacobians(self, x, u):
            A, B = self.jacobians(x, u)
            return A[None], B[None]

    X, U = pc.evaluation_points(d["val"], 3)
    A = np.broadcast_to(d["A"], (len(X), 10, 10))
    B = np.broadcast_to(d["B"], (len(X), 10, 10))
    m = pc.evaluate(Exact(d["A"], d["B"]), d["val"], d["sim"], X, U, A, B)
    assert m["pred_rms"] < 1e-12 and m["sim_rms"] < 1e-10 and m["jac_err"] == 0.0
    assert m["sim_diverged"] == 0
    wrong = pc.evaluate(Exact(d["A"] * 0.9, d["B"]), d["val"], d["sim"], X, U, A, B)
    # the Jacobian error of a uniformly scaled A is exactly 0.1 ||A||_F
    assert wrong["jac_err"] == pytest.approx(0.1 * np.linalg.norm(d["A"]), rel=1e-12)
    assert wrong["jac_rms_entry"] == pytest.approx(wrong["jac_err"] / np.sqrt(200), rel=1e-12)


complex_lists = st.lists(st.complex_numbers(max_magnitude=3, allow_nan=False,
                                            allow_infinity=False), min_size=1, max_size=6)


@settings(max_examples=50, deadline=None)
@given(complex_lists, st.randoms(use_true_random=False))
def test_eigenvalue_matching_error_properties(ev, rnd):
    ev = np.array(ev)
    perm = ev.copy()
    rnd.shuffle(perm)
    assert pc.eigenvalue_matching_error(ev[None], perm) == 0.0  # order does not matter
    shifted = ev + 0.5
    e = pc.eigenvalue_matching_error(shifted[None], ev)
    e_sym = pc.eigenvalue_matching_error(ev[None], shifted)
    assert e == pytest.approx(e_sym)  # symmetric
    assert e <= np.sqrt(2 * len(ev)) * 0.5 + 1e-12  # each term <= |shift|^2


@settings(max_examples=20, deadline=None)
@given(st.lists(st.floats(-5, 5), min_size=6, max_size=30), st.floats(0.01, 3))
def test_paired_comparison_detects_a_constant_shift(base, shift):
    b = np.array(base)
    worse = pc.paired_comparison(b + shift, b)
    assert worse["median_diff"] == pytest.approx(shift)
    assert worse["frac_lower"] == 0.0
    better = pc.paired_comparison(b - shift, b)
    assert better["median_diff"] == pytest.approx(-shift) and better["frac_lower"] == 1.0
    assert better["p_value"] < 0.05  # >= 6 pairs, all in one direction


def test_paired_comparison_with_ties_is_the_tie_corrected_normal_approximation():
    """Six equal differences: signed-rank sum 21 of mean 10.5; variance 6*7*13/24 - (6^3 - 6)/48
    = 18.375 with the tie correction (scipy's exact test would enumerate 2^n sign patterns)."""
    from scipy.stats import norm

    p = pc.paired_comparison(np.ones(6), np.zeros(6))["p_value"]
    assert p == pytest.approx(2 * norm.sf(10.5 / np.sqrt(18.375)), rel=1e-9)
    d = np.r_[0.0, np.arange(1.0, 13.0)]  # a zero difference: scipy's exact test permutes too
    from scipy.stats import wilcoxon

    assert pc.paired_comparison(d, np.zeros(13))["p_value"] == pytest.approx(
        wilcoxon(d, method="approx").pvalue, rel=1e-12)


@settings(max_examples=25, deadline=None)
@given(st.lists(complex_lists, min_size=1, max_size=4).filter(
    lambda rows: len({len(r) for r in rows}) == 1))
def test_stored_eigenvalues_round_trip(rows):
    z = np.array(rows)
    back = pc.complex_from_pairs(json.loads(json.dumps(pc.complex_to_pairs(z, digits=6))))
    assert back.shape == z.shape
    np.testing.assert_allclose(back, z, atol=1e-6)


def test_parse_args_smoke_overrides_only_unset_fields(capsys):
    from agents.experiments import exp_robot

    args = pc.parse_args(exp_robot.Args, ["--smoke", "--mc", "3"])
    assert args.mc == 3 and args.epoch_scale == exp_robot.Args.SMOKE["epoch_scale"]
    full = pc.parse_args(exp_robot.Args, [])
    assert full.mc == 35 and full.epoch_scale == 1.0 and not full.smoke
    for bad in (["--mc", "0"], ["--workers", "0"], ["--backend", "threads"]):
        with pytest.raises(SystemExit) as exc:  # a bad option: exit code 2, the flag named
            pc.parse_args(exp_robot.Args, bad)
        err = capsys.readouterr().err
        assert exc.value.code == 2 and bad[0] in err and "Traceback" not in err


@pytest.mark.parametrize("bad", [
    ["--windows", "shrt"], ["--n-trains", "1,x"], ["--epochs", "0"], ["--frictions", "of"],
    ["--label-cells", "paper-of"], ["--activations", "relx"], ["--batch", "ful"],
    ["--label-n-trains", ""], ["--n-trains", "1,2", "--label-n-trains", "3"]])
def test_regime_options_are_checked_before_any_run(bad, capsys):
    """A wrong comma-list value of the regime sweep stops at the command line (exit code 2, the
    flag named) instead of failing every run or being stored as given."""
    from agents.experiments import exp_regime

    with pytest.raises(SystemExit) as exc:
        pc.parse_args(exp_regime.Args, ["--smoke", *bad])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and bad[0] in err and "Traceback" not in err


def test_regime_options_may_narrow_the_grid():
    """One window, one friction or no label cells still parse (label cells outside the grid are
    not run)."""
    from agents.experiments import exp_regime

    for argv in (["--windows", "short"], ["--frictions", "off"], ["--label-cells", ""],
                 ["--n-trains", "1", "--label-cells", ""]):
        pc.parse_args(exp_regime.Args, ["--smoke", *argv])


def test_unknown_method_and_deviation_are_rejected():
    from agents.experiments import exp_deviations

    with pytest.raises(ValueError, match="method"):
        pc.regularization("dropout")
    args = pc.parse_args(exp_deviations.Args, ["--deviations", "nominal,bogus"])
    with pytest.raises(ValueError, match="bogus"):
        exp_deviations.make_configs(args)


# ------------------------------------------------------------------------------------------------
# the regime sweep (exp_regime) and the claim evidence (exp_claims)


def test_regime_smoke_runs_every_method_at_equal_steps_and_redraws(tmp_path):
    out = tmp_path / "regime"
    run_script("exp_regime.py", "--smoke", "--out", str(out), "--backend", "serial")
    recs = [json.loads(p.read_text()) for p in sorted((out / "runs").glob("*.json"))]
    # 2 windows x 2 frictions x 1 trajectory count x 2 epoch counts x (none, sampled) plus
    # oracle / exact / prior on the paper-friction cells, plus none / sampled / oracle under the
    # paper's protocol (4 members, one step per trajectory) at its shortest run; 2 seeds each
    assert len(recs) == 2 * (2 * 2 * 2 * 2 + 3 * 2 + 3)
    cells: dict = {}
    for r in recs:
        assert r["status"] == "ok"
        res, c = r["result"], r["config"]
        for k in ("jac_err", "jac_pos", "jac_vel", "frac_still"):
            assert res[k] is not None and math.isfinite(res[k]) and res[k] >= 0
        # eq. (jacerr) splits into row groups: all^2 = pos^2 + vel^2
        assert res["jac_err"] ** 2 == pytest.approx(res["jac_pos"] ** 2 + res["jac_vel"] ** 2)
        assert res["net_train_jac"]["epoch"][-1] == c["epochs"]
        if c["method"] != "none":
            assert res["label_jac_vel"] >= 0
        if c["method"] == "oracle":  # true-Jacobian labels have no Jacobian error
            assert res["label_jac_pos"] == res["label_jac_vel"] == 0.0
        key = (c["data"]["window"], c["data"]["friction"], c["n_train"], c["epochs"], r["seed"],
               c.get("paper_protocol", False))
        cells.setdefault(key, set()).add(res["steps"])
    # every method of a cell took the same number of optimizer steps: epochs (full batch), or
    # epochs x trajectories (the paper's protocol)
    assert all(len(s) == 1 and next(iter(s)) == k[3] * (k[2] if k[5] else 1)
               for k, s in cells.items())
    summary_pp = json.loads((out / "summary.json").read_text())["paper_protocol"]
    assert set(summary_pp["methods"]) == {"none", "sampled", "oracle"}
    fig = out / "figures" / "regime_map.png"
    assert fig.stat().st_size > 5000
    summary = json.loads((out / "summary.json").read_text())
    assert summary["n_runs"] + 2 * 3 == len(recs)  # the map's runs; paper protocol apart
    fig.unlink()
    run_script("exp_regime.py", "--smoke", "--out", str(out), "--report-only")
    assert fig.stat().st_size > 5000
    assert json.loads((out / "summary.json").read_text()) == summary
    assert "sampled: change, wins" in (out / "table.md").read_text()


def test_regime_paired_relative_change_and_wins():
    from agents.experiments import exp_regime as er

    def rec(method, seed, v):
        return {"config": {"method": method, "data": {"window": "paper", "friction": True},
                           "n_train": 3, "epochs": 10}, "seed": seed, "result": {"jac_err": v}}

    none = [1.0, 2.0, 4.0, 5.0]
    samp = [0.9, 2.2, 3.0, 5.0]  # -10 %, +10 %, -25 %, 0 %
    records = [rec("none", s, v) for s, v in enumerate(none)]
    records += [rec("sampled", s, v) for s, v in enumerate(samp)]
    s = er.paired_relative(records, "sampled", ("paper", True, 3, 10))
    assert s["total"] == 4 and s["wins"] == 2
    assert s["median_pct"] == pytest.approx(np.median([-10.0, 10.0, -25.0, 0.0]))


def test_jacobian_diagnostics_split_is_consistent():
    rng = np.random.default_rng(0)
    P = 50
    X = rng.normal(size=(P, 4)) * np.array([1, 1, 0.05, 0.05])
    A, B = rng.normal(size=(P, 4, 4)), rng.normal(size=(P, 4, 2))
    dA = np.zeros_like(A)
    dA[:, 2:] = rng.normal(size=(P, 2, 4))  # error in the velocity rows only
    d = pc.jacobian_diagnostics(X, A, B, A + dA, B, still_speed=0.05)
    assert d["jac_pos"] == 0.0
    assert d["jac_vel"] == pytest.approx(d["jac_all"])
    f = d["frac_still"]
    assert 0 < f < 1
    assert d["jac_all"] ** 2 == pytest.approx(f * d["jac_still_all"] ** 2
                                              + (1 - f) * d["jac_moving_all"] ** 2)
    still = (np.abs(X[:, 2:]) < 0.05).any(1)
    expect = np.sqrt((dA[still] ** 2).sum((1, 2)).mean())
    assert d["jac_still_vel"] == pytest.approx(expect)


def test_oracle_labels_are_the_first_order_expansion_around_the_measured_next_state():
    from mbtsr.trajectory import Trajectory

    rng = np.random.default_rng(1)
    T = 12
    tr = Trajectory(rng.normal(size=(T + 1, 4)), rng.normal(size=(T, 2)), dt=0.02)
    A, B = rng.normal(size=(1, T, 4, 4)), rng.normal(size=(1, T, 4, 2))
    (lm,) = pc.oracle_ltv_models([tr], A, B)
    dx, du = 0.01 * rng.normal(size=(T, 4)), 0.01 * rng.normal(size=(T, 2))
    got = lm.predict(tr.x[:-1] + dx, tr.u + du)
    expect = tr.x[1:] + np.einsum("tij,tj->ti", A[0], dx) + np.einsum("tij,tj->ti", B[0], du)
    np.testing.assert_allclose(got, expect, atol=1e-12)


def test_fused_labels_with_equal_confidence_average_the_two_jacobians():
    from mbtsr.ltv import fit_ltv
    from mbtsr.trajectory import Trajectory

    d = pc.regime_dataset(pc.RegimeData(duration=1.0, n_train_max=1, n_val=1, n_sim=1), 0)
    tr = d["train"][0]
    lm = fit_ltv(tr, 30.0)
    model = pc.build_ensemble(4, 2, activations=("tanh",), seed=0)
    model.set_normalization([tr])
    (fused,) = pc.fused_ltv_models([lm], model, [Trajectory(tr.x, tr.u, dt=tr.dt)], 1.0)
    A_net, B_net = model.jacobians(tr.x[:-1], tr.u)
    np.testing.assert_allclose(fused.A, 0.5 * (lm.A + A_net), atol=1e-9)
    np.testing.assert_allclose(fused.B, 0.5 * (lm.B + B_net), atol=1e-9)


def test_friction_free_arm_matches_the_analytic_twin_even_at_rest():
    """With Coulomb friction off, MuJoCo's step Jacobian and the analytic twin's (whose only
    non-smooth part is the friction tanh) agree at zero joint speed too, where with friction on
    they differ (stiction)."""
    x = np.array([0.3, -0.5, 0.0, 0.0])
    u = np.array([0.1, -0.2])
    errs = {}
    for friction in (True, False):
        env = pc.arm_env(pc.RegimeData(friction=friction))
        A, B = env.linearize(x, u)
        A_tw, B_tw = env.analytic_model().jacobians(x[None], u[None])
        errs[friction] = np.abs(np.concatenate([A - A_tw[0], B - B_tw[0]], 1)).max()
    assert errs[False] < 1e-5
    assert errs[True] > 100 * errs[False]


@pytest.mark.parametrize("friction", [True, False])
def test_arm_env_follows_the_configs_friction(friction):
    """``arm_env(cfg)`` takes the config's friction: Coulomb friction on the paper arm, none for
    ``RegimeData(friction=False)``."""
    env = pc.arm_env(pc.RegimeData(friction=friction))
    assert (np.asarray(env.unwrapped.model.dof_frictionloss) > 0).all() == friction


def test_truth_diagnostics_best_constant_and_labels():
    d = pc.robot_truth_diagnostics(pc.RobotData(duration=1.0, n_val=2), 0)
    for k, v in d.items():
        assert math.isfinite(v) and v >= 0, k
    assert d["const_eval"] <= d["const_train"] + 1e-12  # the mean is the best constant
    assert d["twin_moving"] < d["twin_still"]


def test_claims_statistics_match_a_direct_computation(tmp_path):
    from agents.experiments import exp_claims

    rng = np.random.default_rng(3)
    a, b = rng.normal(size=9), rng.normal(size=9)
    for name, vals in (("none", b), ("sampled", a)):
        for s, v in enumerate(vals):
            write_json_atomic(tmp_path / "robot" / "runs" / f"{name}__seed{s}.json",
                          {"name": name, "seed": s, "status": "ok", "result": {"jac_err": v}})
    runs = exp_claims._load(tmp_path, "robot")
    r = exp_claims.evaluate(exp_claims.Comparison(12, "robot", "sampled", "none", "jac_err"),
                            runs)
    assert r["total"] == 9 and r["wins"] == int((a < b).sum())
    assert r["paired"]["median"] == pytest.approx(np.median(a - b))
    assert r["a_stats"]["q1"] == pytest.approx(np.percentile(a, 25))


@pytest.mark.parametrize("method", ["sampeld", "", None])
def test_run_regime_rejects_an_unknown_method(method):
    """An unknown method used to fall back silently to sampled JacProp."""
    with pytest.raises(ValueError, match=r"config\['method'\] must be one of"):
        pc.run_regime({"method": method}, 0)
