import json
import os

import numpy as np
import pytest
from helpers_runner import fail_on_odd, noisy_mean, torch_threads

from mbtsr.runner import load_results, run_sweep, summarize


def test_serial_and_process_agree(tmp_path):
    configs = {"a": {"mu": 0.0}, "b": {"mu": 5.0}}
    serial = run_sweep(noisy_mean, configs, [1, 2, 3], tmp_path / "s", backend="serial",
                       progress=False)
    proc = run_sweep(noisy_mean, configs, [1, 2, 3], tmp_path / "p", backend="process",
                     workers=2, progress=False)
    assert [r["result"] for r in serial] == [r["result"] for r in proc]
    # the result is the seeded computation, not something made up by the runner
    expect = np.random.default_rng(2).normal(5.0, 1.0, size=100).mean()
    rec = next(r for r in proc if r["name"] == "b" and r["seed"] == 2)
    assert rec["result"]["mean"] == pytest.approx(expect, rel=1e-15)
    assert len(load_results(tmp_path / "p")) == 6
    assert len(load_results(tmp_path / "p", name="a")) == 3


def test_resume_does_not_redo_finished_runs(tmp_path):
    log = tmp_path / "log"
    log.mkdir()
    configs = {"a": {"mu": 1.0, "log_dir": str(log)}}
    run_sweep(noisy_mean, configs, [0, 1], tmp_path / "out", backend="serial", progress=False)
    assert len(os.listdir(log)) == 2
    # simulate an interrupted sweep: one finished record is lost
    (tmp_path / "out" / "runs" / "a__seed1.json").unlink()
    recs = run_sweep(noisy_mean, configs, [0, 1, 2], tmp_path / "out", backend="serial",
                     progress=False)
    assert len(recs) == 3
    runs = {name.split("_")[1]: len((log / name).read_text()) for name in os.listdir(log)}
    assert runs == {"0": 1, "1": 2, "2": 1}  # seed 0 not rerun; seed 1 rerun; seed 2 new


def test_changed_config_is_refused(tmp_path):
    run_sweep(noisy_mean, {"a": {"mu": 1.0}}, [0], tmp_path, backend="serial", progress=False)
    with pytest.raises(ValueError, match="different config"):
        run_sweep(noisy_mean, {"a": {"mu": 2.0}}, [0], tmp_path, backend="serial",
                  progress=False)


def test_failed_runs_are_recorded_and_retried(tmp_path):
    recs = run_sweep(fail_on_odd, {"x": {}}, [0, 1, 2], tmp_path, backend="serial",
                     progress=False)
    assert [r["seed"] for r in recs] == [0, 2]
    err = json.loads((tmp_path / "errors" / "x__seed1.json").read_text())
    assert err["status"] == "error" and "odd seed 1" in err["error"]
    with pytest.raises(RuntimeError, match="1 run\\(s\\) failed"):
        run_sweep(fail_on_odd, {"x": {}}, [0, 1, 2], tmp_path, backend="serial",
                  progress=False, raise_on_error=True)


def test_workers_run_single_threaded(tmp_path):
    recs = run_sweep(torch_threads, {"t": {}}, [0, 1], tmp_path, backend="process", workers=2,
                     progress=False)
    assert all(r["result"]["threads"] == 1 for r in recs)


@pytest.mark.parametrize(
    "kwargs, msg",
    [
        ({"backend": "dask"}, "backend"),
        ({"seeds": []}, "at least one seed"),
        ({"seeds": [1, 1]}, "distinct"),
        ({"configs": {"bad name/": {}}}, "config name"),
        ({"configs": {"a": {"f": object()}}}, "JSON-serializable"),
        ({"workers": 0}, "workers"),
    ],
)
def test_bad_arguments(tmp_path, kwargs, msg):
    args = {"configs": {"a": {"mu": 0.0}}, "seeds": [0], "backend": "serial"}
    args.update(kwargs)
    with pytest.raises(ValueError, match=msg):
        run_sweep(noisy_mean, args.pop("configs"), args.pop("seeds"), tmp_path, progress=False,
                  **args)


def test_summarize_counts_nonfinite():
    s = summarize([1.0, 2.0, 3.0, float("nan"), float("inf")])
    assert s["n"] == 3 and s["n_nonfinite"] == 2
    assert s["mean"] == 2.0 and s["median"] == 2.0 and s["std"] == pytest.approx(1.0)
