import json
import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from helpers_runner import fail_on_odd, noisy_mean, raise_or_die, torch_threads

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


def _check_raise_and_kill(recs, out):
    """8 runs, seed 2 raised and seed 5 was SIGKILLed: the other 6 are stored, both failures too."""
    assert [r["seed"] for r in recs] == [0, 1, 3, 4, 6, 7]
    assert sorted(p.name for p in (out / "runs").glob("*.json")) == sorted(
        f"x__seed{s}.json" for s in (0, 1, 3, 4, 6, 7))
    raised = json.loads((out / "errors" / "x__seed2.json").read_text())
    killed = json.loads((out / "errors" / "x__seed5.json").read_text())
    assert raised["status"] == "error" and "ValueError: bad seed 2" in raised["error"]
    assert killed["status"] == "error" and "died" in killed["error"]
    return {r["seed"]: r["result"] for r in recs}


def test_pool_survives_raising_and_killed_runs(tmp_path):
    cfg = {"x": {"raise_seed": 2, "kill_seed": 5}}
    recs = run_sweep(raise_or_die, cfg, range(8), tmp_path, backend="process", workers=2,
                     progress=False)
    pool = _check_raise_and_kill(recs, tmp_path)
    killed = json.loads((tmp_path / "errors" / "x__seed5.json").read_text())
    assert "SIGKILL" in killed["error"]
    serial = run_sweep(noisy_mean, {"x": {"mu": 0.0, "n": 10}}, [0, 1, 3, 4, 6, 7],
                       tmp_path / "serial", backend="serial", progress=False)
    assert pool == {r["seed"]: r["result"] for r in serial}


def test_pool_records_os_exit(tmp_path):
    recs = run_sweep(raise_or_die, {"x": {"exit_seed": 1}}, range(3), tmp_path,
                     backend="process", workers=2, progress=False)
    assert [r["seed"] for r in recs] == [0, 2]
    err = json.loads((tmp_path / "errors" / "x__seed1.json").read_text())
    assert "exit code 3" in err["error"]


def test_resume_reruns_only_failed_runs(tmp_path):
    recs = run_sweep(fail_on_odd, {"x": {}}, range(4), tmp_path, backend="process", workers=2,
                     progress=False)
    assert [r["seed"] for r in recs] == [0, 2]
    mtimes = {p.name: p.stat().st_mtime_ns for p in (tmp_path / "runs").glob("*.json")}
    recs = run_sweep(fail_on_odd, {"x": {}}, range(4), tmp_path, backend="process", workers=2,
                     progress=False)
    assert [r["seed"] for r in recs] == [0, 2]
    assert mtimes == {p.name: p.stat().st_mtime_ns for p in (tmp_path / "runs").glob("*.json")}
    assert sorted(p.name for p in (tmp_path / "errors").glob("*.json")) == [
        "x__seed1.json", "x__seed3.json"]


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # a zombie awaiting its reaper counts as gone
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().split(")")[-1].split()[0] != "Z"
    except OSError:
        return False


def test_pool_workers_exit_when_the_driver_is_killed(tmp_path):
    pid_dir = tmp_path / "pids"
    pid_dir.mkdir()
    driver = textwrap.dedent(f"""
        import sys
        sys.path.insert(0, {str(Path(__file__).parent)!r})
        from helpers_runner import sleep_forever
        from mbtsr.runner import run_sweep
        if __name__ == "__main__":
            run_sweep(sleep_forever, {{"s": {{"pid_dir": {str(pid_dir)!r}}}}}, [0, 1],
                      {str(tmp_path / "out")!r}, workers=2, progress=False)
    """)
    script = tmp_path / "driver.py"
    script.write_text(driver)
    proc = subprocess.Popen([sys.executable, str(script)], env=os.environ.copy())
    try:
        deadline = time.monotonic() + 120
        while len(list(pid_dir.glob("*.pid"))) < 2:
            assert proc.poll() is None, "the driver exited early"
            assert time.monotonic() < deadline, "workers did not start"
            time.sleep(0.2)
        pids = [int(p.read_text()) for p in pid_dir.glob("*.pid")]
        assert all(_alive(p) for p in pids)
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        deadline = time.monotonic() + 30
        while any(_alive(p) for p in pids) and time.monotonic() < deadline:
            time.sleep(0.2)
        assert not any(_alive(p) for p in pids), "orphaned workers outlived the driver"
    finally:
        if proc.poll() is None:
            proc.kill()


def test_unpicklable_run_function_is_refused(tmp_path):
    with pytest.raises(ValueError, match="fn must be a module-level function"):
        run_sweep(lambda c, s: {}, {"a": {}}, [0, 1], tmp_path, workers=2, progress=False)


def test_ray_matches_pool_run_for_run(tmp_path, monkeypatch):
    """A real local Ray instance: the same records as the pool for 8 runs with one raising and
    one SIGKILLed worker; the Ray temp folder is removed; with nothing left Ray is not started."""
    ray = pytest.importorskip("ray", reason="the [ray] extra is not installed")
    import tempfile

    cfg = {"x": {"raise_seed": 2, "kill_seed": 5}}
    before = set(Path(tempfile.gettempdir()).glob("mbtsr-ray-*"))
    recs = run_sweep(raise_or_die, cfg, range(8), tmp_path / "ray", backend="ray", workers=2,
                     progress=False)
    assert not ray.is_initialized()
    assert set(Path(tempfile.gettempdir()).glob("mbtsr-ray-*")) == before
    on_ray = _check_raise_and_kill(recs, tmp_path / "ray")
    pool = run_sweep(raise_or_die, cfg, range(8), tmp_path / "pool", backend="process",
                     workers=2, progress=False)
    assert on_ray == {r["seed"]: r["result"] for r in pool}
    # every run finished: Ray is not started at all
    run_sweep(raise_or_die, {"x": {}}, [0, 1], tmp_path / "ok", backend="serial",
              progress=False)
    monkeypatch.setattr(ray, "init", lambda *a, **k: pytest.fail("ray.init was called"))
    assert len(run_sweep(raise_or_die, {"x": {}}, [0, 1], tmp_path / "ok", backend="ray",
                         progress=False)) == 2


@pytest.mark.slow  # starts a Ray head node (about 20 s on a busy 2-core machine)
def test_ray_existing_cluster_and_resume(tmp_path):
    """``address=`` joins a cluster started with ``ray start --head``; resuming reruns only
    the failed runs and leaves the cluster running."""
    pytest.importorskip("ray", reason="the [ray] extra is not installed")
    import shutil
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    temp = Path(tempfile_dir := __import__("tempfile").mkdtemp(prefix="mbtsr-rayhead-"))
    ray_bin = str(Path(sys.executable).with_name("ray"))
    head = subprocess.Popen(
        [ray_bin, "start", "--head", "--block", f"--port={port}", "--num-cpus=2",
         "--include-dashboard=false", f"--temp-dir={temp}", "--disable-usage-stats"],
        start_new_session=True, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        env={**os.environ, "RAY_AUTH_MODE": "disabled"})  # as the driver's default
    try:
        for line in head.stdout:  # wait until the head is up
            if "Ray runtime started" in line:
                break
        assert head.poll() is None, "ray start --head failed"
        threading.Thread(target=head.stdout.read, daemon=True).start()  # drain
        address = f"127.0.0.1:{port}"
        cfg = {"x": {"raise_seed": 2}}
        t0 = time.perf_counter()
        recs = run_sweep(raise_or_die, cfg, range(4), tmp_path, backend="ray",
                         address=address, progress=False)
        print(f"first sweep on the cluster: {time.perf_counter() - t0:.1f} s")
        assert [r["seed"] for r in recs] == [0, 1, 3]
        mtimes = {p.name: p.stat().st_mtime_ns for p in (tmp_path / "runs").glob("*")}
        again = run_sweep(raise_or_die, cfg, range(4), tmp_path, backend="ray",
                          address=address, progress=False)
        assert again == recs
        assert mtimes == {p.name: p.stat().st_mtime_ns for p in (tmp_path / "runs").glob("*")}
        # a run function whose module needs another module found only on the driver's
        # sys.path: recorded as failed with the import error, the sweep completes
        mod_dir = tmp_path / "driver_only"
        mod_dir.mkdir()
        (mod_dir / "driver_only_dep.py").write_text("VALUE = 3\n")
        (mod_dir / "driver_only_fn.py").write_text(
            "import driver_only_dep\n\n\ndef run(config, seed):\n"
            "    return {'v': driver_only_dep.VALUE + seed}\n")
        sys.path.insert(0, str(mod_dir))
        try:
            import driver_only_fn

            bad = run_sweep(driver_only_fn.run, {"d": {}}, [0, 1], tmp_path / "d",
                            backend="ray", address=address, progress=False)
            # the pool's workers see the driver's sys.path: there it works
            good = run_sweep(driver_only_fn.run, {"d": {}}, [0, 1], tmp_path / "p",
                             backend="process", workers=2, progress=False)
        finally:
            sys.path.remove(str(mod_dir))
        assert bad == [] and [r["result"]["v"] for r in good] == [3, 4]
        for seed in (0, 1):
            err = json.loads((tmp_path / "d" / "errors" / f"d__seed{seed}.json").read_text())
            assert "driver_only_dep" in err["error"]
        assert head.poll() is None  # the cluster is the user's: still up
    finally:
        os.killpg(head.pid, signal.SIGTERM)  # the head's session: the processes it started
        try:
            head.wait(60)
        except subprocess.TimeoutExpired:
            pass
        time.sleep(3)
        try:
            os.killpg(head.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        shutil.rmtree(tempfile_dir, ignore_errors=True)
