"""Monte-Carlo runner: run a module-level ``fn(config: dict, seed: int) -> dict`` over
configurations x seeds, one JSON file per run (``out_dir/runs/<config>__seed<seed>.json``,
written atomically; failed runs in ``out_dir/errors/``, retried next call), so an interrupted
sweep resumes. Backends ``"serial"``, ``"process"`` (a forkserver pool, one thread per worker)
and ``"ray"``; a run that raises or whose worker dies is recorded as failed and the others go
on. Failure handling and Ray clusters: docs/troubleshooting.md, "Sweeps".

Example::

    records = run_sweep(my_experiment, {"none": {"reg": 0.0}, "jacprop": {"reg": 1.0}},
                        seeds=range(10), out_dir="results/linear")
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import multiprocessing as mp
import multiprocessing.connection as mpc
import os
import pickle
import re
import shutil
import signal
import sys
import tempfile
import threading
import time
import traceback
from collections import deque
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mbtsr.io import json_default, write_json_atomic
from mbtsr.validation import check_choice, check_int

__all__ = ["RunSpec", "load_results", "run_sweep", "summarize"]

RunFunction = Callable[[dict, int], dict]
_NAME_RE = re.compile(r"^[A-Za-z0-9_.+-]+$")


@dataclass(frozen=True)
class RunSpec:
    """One unit of work: a named configuration and a seed."""

    name: str
    config: dict
    seed: int

    @property
    def run_id(self) -> str:
        return f"{self.name}__seed{self.seed}"


def _normalize_configs(configs: Mapping[str, dict]) -> dict[str, dict]:
    if not isinstance(configs, Mapping) or not configs:
        raise ValueError("configs must be a non-empty dict {name: config}")
    for name, c in configs.items():
        if not isinstance(name, str) or not _NAME_RE.match(name):
            raise ValueError(
                f"config name {name!r} may only contain letters, digits and _ . + - "
                "(it becomes a file name)"
            )
        if not isinstance(c, Mapping):
            raise ValueError(f"config {name!r} must be a dict, got {type(c).__name__}")
        try:
            json.dumps(dict(c), default=json_default)
        except TypeError as err:
            raise ValueError(f"config {name!r} must be JSON-serializable: {err}") from None
    return {k: dict(v) for k, v in configs.items()}


def _canonical(obj: Any) -> str:
    return json.dumps(obj, sort_keys=True, default=json_default)


def _set_single_thread() -> None:
    """One BLAS/OpenMP/torch thread: environment variables for libraries imported later (torch
    reads ``OMP_NUM_THREADS`` at import), ``torch.set_num_threads`` if torch is loaded already."""
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ[var] = "1"
    torch = sys.modules.get("torch")
    if torch is not None:
        torch.set_num_threads(1)


def _record(spec: RunSpec, status: str, error: str | None, result: dict | None,
            wall_time: float) -> dict:
    return {
        "run_id": spec.run_id,
        "name": spec.name,
        "config": spec.config,
        "seed": spec.seed,
        "status": status,
        "error": error,
        "result": result,
        "wall_time": wall_time,
    }


def _execute(fn: RunFunction, spec: RunSpec, single_thread: bool) -> dict:
    """Run one spec and wrap its result in a record (never raises); ``single_thread``: first
    :func:`_set_single_thread` (a worker)."""
    if single_thread:
        _set_single_thread()
    t0 = time.perf_counter()
    try:
        result = fn(dict(spec.config), spec.seed)
        if not isinstance(result, Mapping):
            raise TypeError(f"run function must return a dict, got {type(result).__name__}")
        # plain JSON types from here on: what is returned equals what a resumed sweep loads
        result = json.loads(json.dumps(result, default=json_default))
        status, error = "ok", None
    except (Exception, SystemExit):  # noqa: BLE001 - a failed run is recorded, the sweep goes on
        result, status, error = None, "error", traceback.format_exc()
    return _record(spec, status, error, result, time.perf_counter() - t0)


def _path(out_dir: Path, spec: RunSpec, folder: str = "runs") -> Path:
    """The record file of ``spec``: ``runs/`` for finished runs, ``errors/`` for failed ones."""
    return out_dir / folder / f"{spec.run_id}.json"


def _load_done(out_dir: Path, spec: RunSpec) -> dict | None:
    path = _path(out_dir, spec)
    if not path.exists():
        return None
    try:
        with open(path) as fh:
            rec = json.load(fh)
        if not isinstance(rec, dict) or rec.get("status") != "ok":
            raise ValueError("not a finished run record")
    except (OSError, ValueError) as err:  # unreadable: treat as missing, run it again
        logging.getLogger(__name__).warning("%s is unreadable (%s); rerunning %s",
                                            path, err, spec.run_id)
        return None
    if _canonical(rec.get("config")) != _canonical(spec.config):
        raise ValueError(
            f"{path} holds a finished run of {spec.name!r} with a different config; "
            "use a new out_dir (or delete that folder) to run the changed config"
        )
    return rec


def _store(out_dir: Path, spec: RunSpec, rec: dict) -> None:
    if rec["status"] == "ok":
        write_json_atomic(_path(out_dir, spec), rec)
        err = _path(out_dir, spec, "errors")
        if err.exists():
            err.unlink()
    else:
        write_json_atomic(_path(out_dir, spec, "errors"), rec)


def run_sweep(
    fn: RunFunction,
    configs: Mapping[str, dict],
    seeds: Iterable[int],
    out_dir: str | os.PathLike,
    *,
    backend: str = "process",
    workers: int | None = None,
    progress: bool = True,
    raise_on_error: bool = False,
    address: str | None = None,
) -> list[dict]:
    """Run ``fn(config, seed)`` for every configuration and seed; resume what is finished.

    :param fn: module-level function ``(config: dict, seed: int) -> dict`` (JSON-serializable).
    :param configs: ``{name: config}``.
    :param seeds: the seeds, e.g. ``range(35)`` for the paper's 35 Monte-Carlo runs.
    :param out_dir: results folder; finished runs go to ``out_dir/runs/*.json``, failed ones to
        ``out_dir/errors/*.json`` (retried on the next call).
    :param backend: ``"process"`` (default), ``"serial"`` or ``"ray"``.
    :param workers: parallel workers, one torch/BLAS thread each (default: the number of CPU
        cores; with ``address`` the cluster's CPUs decide).
    :param raise_on_error: raise ``RuntimeError`` after the sweep if any run failed.
    :param address: Ray only: the address of an existing Ray cluster (``"auto"`` for the one
        started on this machine with ``ray start --head``, or ``"ray://host:10001"``); ``None``
        starts a private local Ray instance for the sweep and removes it afterwards.
    :return: the records of all finished runs in (config, seed) order.
    """
    check_choice("backend", backend, ("process", "serial", "ray"))
    if not callable(fn):
        raise ValueError(f"fn must be a callable (config, seed) -> dict, got {type(fn).__name__}")
    if address is not None and backend != "ray":
        raise ValueError(f"address is for backend='ray' only, got backend={backend!r}")
    if address is not None and (not isinstance(address, str) or not address):
        raise ValueError(f"address must be a non-empty string such as 'auto', got {address!r}")
    named = _normalize_configs(configs)
    try:
        seeds = [int(s) for s in seeds]
    except (TypeError, ValueError) as err:
        raise ValueError(f"seeds must be integers: {err}") from None
    if not seeds:
        raise ValueError("seeds must contain at least one seed")
    if len(set(seeds)) != len(seeds):
        raise ValueError("seeds must be distinct")
    if workers is not None:
        check_int("workers", workers, 1)
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ValueError(f"out_dir {out} exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)
    specs = [RunSpec(n, c, s) for n, c in named.items() for s in seeds]
    done = {s.run_id: r for s in specs if (r := _load_done(out, s)) is not None}
    todo = [s for s in specs if s.run_id not in done]
    workers = int(workers or os.cpu_count() or 1)

    bar = None
    if progress and todo:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(specs), initial=len(done), desc="runs", unit="run")
    failures: list[dict] = []

    def finish(spec: RunSpec, rec: dict) -> None:
        _store(out, spec, rec)
        if rec["status"] == "ok":
            done[spec.run_id] = rec
        else:
            failures.append(rec)
        if bar is not None:
            bar.update(1)
            bar.set_postfix(failed=len(failures))

    try:
        if not todo:  # nothing left: no pool, no Ray
            pass
        elif backend == "serial":
            for spec in todo:
                finish(spec, _execute(fn, spec, False))
        elif backend == "process":
            _run_pool(fn, todo, workers, finish)
        else:
            _run_ray(fn, todo, workers, finish, address)
    finally:
        if bar is not None:
            bar.close()
    if failures and raise_on_error:
        first = failures[0]
        raise RuntimeError(
            f"{len(failures)} run(s) failed; first {first['run_id']}:\n{first['error']}"
        )
    return [done[s.run_id] for s in specs if s.run_id in done]


# ------------------------------------------------------------------------------ process pool
def _watch_driver(alive: mpc.Connection) -> None:
    """Worker thread: block on a pipe the driver never writes to; EOF means the driver died."""
    try:
        alive.recv_bytes()
    except (EOFError, OSError):
        pass
    os._exit(1)  # the driver is gone: stop now, whatever the run was doing


def _worker_main(conn: mpc.Connection, alive: mpc.Connection) -> None:
    """Pool worker: receive ``(spec, pickled fn)``, send back the run record; one at a time."""
    threading.Thread(target=_watch_driver, args=(alive,), daemon=True).start()
    _set_single_thread()
    fns: dict[bytes, RunFunction] = {}
    while True:
        try:
            spec, fn_bytes = pickle.loads(conn.recv_bytes())
        except (EOFError, OSError):
            return  # the driver closed the pipe: no more work
        t0 = time.perf_counter()
        try:
            if fn_bytes not in fns:
                fns[fn_bytes] = pickle.loads(fn_bytes)
            fn = fns[fn_bytes]
        except Exception:  # noqa: BLE001 - e.g. the run function's module does not import
            rec = _record(spec, "error", "the run function could not be loaded on the worker:\n"
                          + traceback.format_exc(), None, time.perf_counter() - t0)
        else:
            rec = _execute(fn, spec, False)
        conn.send_bytes(pickle.dumps(rec))


def _death_reason(exitcode: int | None) -> str:
    if exitcode is not None and exitcode < 0:
        with contextlib.suppress(ValueError):  # not every number has a name
            return f"killed by signal {signal.Signals(-exitcode).name}"
        return f"killed by signal {-exitcode}"
    return "exit status unknown" if exitcode is None else f"exit code {exitcode}"


class _PoolWorker:
    """One worker process with a task pipe and a driver-alive pipe (see :func:`_watch_driver`)."""

    def __init__(self, ctx) -> None:
        self.conn, child = ctx.Pipe(duplex=True)
        alive_child, self.alive = ctx.Pipe(duplex=False)
        self.proc = ctx.Process(target=_worker_main, args=(child, alive_child),
                                name="mbtsr-runner-worker")
        self.proc.start()
        child.close()
        alive_child.close()
        self.spec: RunSpec | None = None
        self.t0 = 0.0

    def submit(self, spec: RunSpec, fn_bytes: bytes) -> None:
        self.spec, self.t0 = spec, time.perf_counter()
        self.conn.send_bytes(pickle.dumps((spec, fn_bytes)))

    def close(self, timeout: float = 5.0) -> None:
        for c in (self.conn, self.alive):
            c.close()
        self.proc.join(timeout)
        if self.proc.is_alive():
            self.proc.kill()
            self.proc.join()


def _run_pool(fn, todo, workers, finish) -> None:
    try:
        fn_bytes = pickle.dumps(fn)
    except Exception as err:  # noqa: BLE001 - lambdas, closures, ...
        raise ValueError(
            f"fn must be a module-level function the workers can import; pickling failed: {err}"
        ) from None
    ctx = mp.get_context("forkserver")
    queue = deque(todo)
    active: list[_PoolWorker] = []

    def start_next(worker: _PoolWorker | None) -> None:
        while queue:
            worker = worker or _PoolWorker(ctx)
            try:
                worker.submit(queue[0], fn_bytes)
            except OSError:  # died before it took the run: replace it, keep the run queued
                worker.close(0.0)
                worker = None
                continue
            queue.popleft()
            active.append(worker)
            return
        if worker is not None:
            worker.close()

    try:
        for _ in range(min(workers, len(queue))):
            start_next(None)
        while active:
            ready = set(mpc.wait([w.conn for w in active] + [w.proc.sentinel for w in active]))
            for w in [w for w in active if w.conn in ready or w.proc.sentinel in ready]:
                rec = None
                try:
                    if w.conn.poll():
                        rec = pickle.loads(w.conn.recv_bytes())
                except (EOFError, OSError):
                    rec = None
                if rec is None and w.proc.is_alive() and w.proc.sentinel not in ready:
                    continue  # spurious wake-up
                active.remove(w)
                if rec is None:  # the worker died while running w.spec
                    w.proc.join()
                    rec = _record(
                        w.spec, "error",
                        f"worker process {w.proc.pid} died while running {w.spec.run_id} "
                        f"({_death_reason(w.proc.exitcode)}); nothing was returned",
                        None, time.perf_counter() - w.t0)
                    w.close(0.0)
                    finish(w.spec, rec)
                    start_next(None)
                else:
                    finish(w.spec, rec)
                    start_next(w)
    finally:
        for w in active:
            w.close(0.0)


# ------------------------------------------------------------------------------ Ray
_PROJECT_PACKAGES = ("mbtsr", "agents", "envs")


def _is_installed(path: str | None) -> bool:
    return path is None or any(p in Path(path).parts for p in ("site-packages", "dist-packages"))


def _ray_shipping(fn) -> tuple[list, list]:
    """What the Ray workers need to import the run function: ``(py_modules, by_value)``.

    The project's packages and the run function's top-level package are shipped as
    ``runtime_env`` ``py_modules`` unless they come from an installed distribution; a run
    function from a single-file module (a test helper, a script's module) is pickled by value.
    """
    roots = list(_PROJECT_PACKAGES)
    module = getattr(fn, "__module__", None) or "__main__"
    root = module.split(".")[0]
    if root not in roots:
        roots.append(root)
    py_modules, by_value = [], []
    for name in roots:
        mod = sys.modules.get(name)
        if mod is None or name == "__main__":
            continue  # cloudpickle ships functions defined in __main__ by value already
        if hasattr(mod, "__path__"):  # a package
            if not _is_installed(getattr(mod, "__file__", None) or next(iter(mod.__path__), None)):
                py_modules.append(mod)
        elif not _is_installed(getattr(mod, "__file__", None)):
            by_value.append(mod)
    return py_modules, by_value


def _run_ray(fn, todo, workers, finish, address) -> None:
    try:
        import ray
        import ray.cloudpickle
    except ImportError:
        raise ImportError(
            "backend='ray' needs Ray: pip install -c constraints.txt -e '.[ray]'"
        ) from None
    py_modules, by_value = _ray_shipping(fn)
    registered = set(ray.cloudpickle.list_registry_pickle_by_value())
    by_value = [m for m in by_value if m.__name__ not in registered]
    for mod in by_value:
        ray.cloudpickle.register_pickle_by_value(mod)
    started, temp_dir = False, None
    try:
        if not ray.is_initialized():
            runtime_env = {"py_modules": py_modules} if py_modules else None
            kw = {"runtime_env": runtime_env, "log_to_driver": False,
                  "logging_level": logging.WARNING}
            if address is None:
                temp_dir = tempfile.mkdtemp(prefix="mbtsr-ray-")
                ray.init(num_cpus=workers, include_dashboard=False, _temp_dir=temp_dir, **kw)
            else:
                ray.init(address=address, **kw)
            started = True
        remote = ray.remote(num_cpus=1, max_retries=0)(_execute)
        refs = {remote.remote(fn, s, True): (s, time.perf_counter()) for s in todo}
        while refs:
            ready, _ = ray.wait(list(refs), num_returns=1)
            for ref in ready:
                spec, t0 = refs.pop(ref)
                try:
                    rec = ray.get(ref)
                except Exception as err:  # noqa: BLE001 - worker died, fn not importable, ...
                    rec = _record(spec, "error",
                                  f"Ray task for {spec.run_id} failed on the worker "
                                  f"({type(err).__name__}): {err}",
                                  None, time.perf_counter() - t0)
                finish(spec, rec)
    finally:
        if started:
            ray.shutdown()
        for mod in by_value:
            ray.cloudpickle.unregister_pickle_by_value(mod)
        if temp_dir is not None:
            shutil.rmtree(temp_dir, ignore_errors=True)


def load_results(out_dir: str | os.PathLike, name: str | None = None) -> list[dict]:
    """Load finished run records from ``out_dir/runs`` (optionally only config ``name``).

    Records are sorted by (name, seed). Non-finite floats written by Python's json module
    (``NaN``, ``Infinity``) are read back as floats.
    """
    runs = Path(out_dir) / "runs"
    if not runs.is_dir():
        return []
    records = []
    for path in sorted(runs.glob("*.json")):
        with open(path) as fh:
            rec = json.load(fh)
        if name is None or rec.get("name") == name:
            records.append(rec)
    records.sort(key=lambda r: (r["name"], r["seed"]))
    return records


def summarize(values: Iterable[float]) -> dict:
    """Mean, std, median, min, max and count of the finite values (and the non-finite count)."""
    try:
        vals = [float(v) for v in values]
    except (TypeError, ValueError) as err:
        raise ValueError(f"values must be real numbers: {err}") from None
    finite = sorted(v for v in vals if math.isfinite(v))
    k = len(finite)
    if k == 0:
        return {"n": 0, "n_nonfinite": len(vals)}
    mean = sum(finite) / k
    var = sum((v - mean) ** 2 for v in finite) / (k - 1) if k > 1 else 0.0
    med = finite[k // 2] if k % 2 else 0.5 * (finite[k // 2 - 1] + finite[k // 2])
    return {
        "n": k,
        "n_nonfinite": len(vals) - k,
        "mean": mean,
        "std": math.sqrt(var),
        "median": med,
        "min": finite[0],
        "max": finite[-1],
    }
