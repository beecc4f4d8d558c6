"""Smoke run of the planning bench (scripts/bench_planning.py): tiny model and planner, the
JSON's fields and their consistency."""

from __future__ import annotations

import json

import numpy as np
import pytest

from agents.experiments.bench_planning import Args, matmul_peak, run


def test_planning_bench_smoke_writes_every_field(tmp_path):
    path = tmp_path / "planning.json"
    fig = tmp_path / "planning.png"
    run(Args(tasks=("reacher",), steps=3, repeats=1, smoke=True, out=str(path),
             figure=str(fig)))
    out = json.loads(path.read_text())
    assert set(out["matmul_peak_gflops"]) == {"float32", "float64"}
    row = out["tasks"]["reacher"]
    assert row["env_id"] == "Reacher-v5" and row["control_period_ms"] == pytest.approx(20.0)
    assert row["precision"] == "float32" and row["planner"] == "cem-ilqr" and row["steps"] == 3
    for key in ("ms_per_step_median", "ms_per_step_p95", "cpu_ms_per_step_median",
                "cpu_ms_per_step_p95", "cold_start_s"):
        assert np.isfinite(row[key]), key
    assert row["cold_starts"] >= 1 and len(row["returns"]) >= 1
    assert row["ms_per_step_p95"] >= row["ms_per_step_median"] > 0
    assert row["fraction_of_period"] == pytest.approx(row["ms_per_step_median"] / 20.0)
    for kernel in ("cem_rollout", "jacobians"):
        k = row["kernels"][kernel]
        assert k["gflop"] > 0 and k["gflops"] == pytest.approx(k["gflop"] / k["ms"] * 1e3)
        assert k["fraction_of_peak"] == pytest.approx(
            k["gflops"] / out["matmul_peak_gflops"]["float32"])
    assert set(row["targets"]) == {"median_within_period", "p95_within_2x_period",
                                   "cpu_median_within_period", "cpu_p95_within_2x_period"}
    assert "load_average_end" in out["machine"] and fig.stat().st_size > 0


def test_planning_bench_refuses_bad_arguments():
    with pytest.raises(ValueError, match="unknown tasks"):
        run(Args(tasks=("no-such-task",), steps=3))
    with pytest.raises(ValueError, match="steps must be >= 1"):
        run(Args(steps=0))


def test_matmul_peak_is_a_rate():
    assert 0.1 < matmul_peak(np.float32, size=128, repeats=1) < 1e4
