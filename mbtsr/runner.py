"""Monte-Carlo runner: run a function over configurations x seeds, one JSON file per run.

Used by the SB3 benchmark and the paper experiments. Each finished run is written atomically to
``out_dir/runs/<config>__seed<seed>.json``, so an interrupted sweep resumes without redoing
finished work. Three backends:

- ``"serial"``: in this process (debugging, tiny sweeps);
- ``"process"`` (default): a local process pool (``forkserver`` start method), one torch/BLAS
  thread per worker, which on a 2-core machine matches Ray for these workloads;
- ``"ray"``: Ray tasks (``pip install -e ".[distributed]"``), for going past one machine.

The run function must be importable by the workers (a module-level function) and take
``(config: dict, seed: int)``, returning a JSON-serializable ``dict``.

Example::

    from mbtsr.runner import run_sweep
    records = run_sweep(my_experiment, {"none": {"reg": 0.0}, "jacprop": {"reg": 1.0}},
                        seeds=range(10), out_dir="results/linear")
"""

from __future__ import annotations

import json
import math
import multiprocessing as mp
import os
import re
import time
import traceback
from collections.abc import Callable, Iterable, Mapping
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mbtsr.io import json_default, write_json_atomic

__all__ = ["RunSpec", "load_results", "run_sweep", "summarize", "write_json_atomic"]

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


def _normalize_configs(configs: Mapping[str, dict] | Iterable[dict]) -> dict[str, dict]:
    if isinstance(configs, Mapping):
        named = dict(configs)
    else:
        named = {}
        for i, c in enumerate(configs):
            name = str(c.get("name", f"config{i}")) if isinstance(c, Mapping) else f"config{i}"
            named[name] = c
    if not named:
        raise ValueError("configs must name at least one configuration")
    for name, c in named.items():
        if not _NAME_RE.match(name):
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
    return {k: dict(v) for k, v in named.items()}


def _canonical(obj: Any) -> str:
    return json.dumps(obj, sort_keys=True, default=json_default)


def _set_single_thread() -> None:
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ[var] = "1"
    try:
        import torch

        torch.set_num_threads(1)
    except ImportError:  # pragma: no cover - torch is a dependency
        pass


def _execute(fn: RunFunction, spec: RunSpec, single_thread: bool) -> dict:
    """Run one spec and wrap its result in a record (never raises)."""
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
    except Exception:  # noqa: BLE001 - a failed run is recorded, the sweep goes on
        result, status, error = None, "error", traceback.format_exc()
    return {
        "run_id": spec.run_id,
        "name": spec.name,
        "config": spec.config,
        "seed": spec.seed,
        "status": status,
        "error": error,
        "result": result,
        "wall_time": time.perf_counter() - t0,
    }


def _record_path(out_dir: Path, spec: RunSpec) -> Path:
    return out_dir / "runs" / f"{spec.run_id}.json"


def _error_path(out_dir: Path, spec: RunSpec) -> Path:
    return out_dir / "errors" / f"{spec.run_id}.json"


def _load_done(out_dir: Path, spec: RunSpec) -> dict | None:
    path = _record_path(out_dir, spec)
    if not path.exists():
        return None
    with open(path) as fh:
        rec = json.load(fh)
    if _canonical(rec.get("config")) != _canonical(spec.config):
        raise ValueError(
            f"{path} holds a finished run of {spec.name!r} with a different config; "
            "use a new out_dir (or delete that folder) to run the changed config"
        )
    return rec


def _store(out_dir: Path, spec: RunSpec, rec: dict) -> None:
    if rec["status"] == "ok":
        write_json_atomic(_record_path(out_dir, spec), rec)
        err = _error_path(out_dir, spec)
        if err.exists():
            err.unlink()
    else:
        write_json_atomic(_error_path(out_dir, spec), rec)


def run_sweep(
    fn: RunFunction,
    configs: Mapping[str, dict] | Iterable[dict],
    seeds: Iterable[int],
    out_dir: str | os.PathLike,
    *,
    backend: str = "process",
    workers: int | None = None,
    progress: bool = True,
    single_thread: bool = True,
    raise_on_error: bool = False,
) -> list[dict]:
    """Run ``fn(config, seed)`` for every configuration and seed; resume what is finished.

    :param fn: module-level function ``(config: dict, seed: int) -> dict`` (JSON-serializable).
    :param configs: ``{name: config}`` or a list of configs (named by their ``"name"`` key).
    :param seeds: the seeds, e.g. ``range(35)`` for the paper's 35 Monte-Carlo runs.
    :param out_dir: results folder; finished runs go to ``out_dir/runs/*.json``, failed ones to
        ``out_dir/errors/*.json`` (retried on the next call).
    :param backend: ``"process"`` (default), ``"serial"`` or ``"ray"``.
    :param workers: parallel workers (default: the number of CPU cores).
    :param single_thread: one torch/BLAS thread per worker (recommended for small models).
    :param raise_on_error: raise ``RuntimeError`` after the sweep if any run failed.
    :return: the records of all finished runs in (config, seed) order.
    """
    if backend not in ("process", "serial", "ray"):
        raise ValueError(f"backend must be 'process', 'serial' or 'ray', got {backend!r}")
    named = _normalize_configs(configs)
    seeds = [int(s) for s in seeds]
    if not seeds:
        raise ValueError("seeds must contain at least one seed")
    if len(set(seeds)) != len(seeds):
        raise ValueError("seeds must be distinct")
    if workers is not None and workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    specs = [RunSpec(n, c, s) for n, c in named.items() for s in seeds]
    done = {s.run_id: r for s in specs if (r := _load_done(out, s)) is not None}
    todo = [s for s in specs if s.run_id not in done]
    workers = workers or os.cpu_count() or 1

    bar = None
    if progress:
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
        if backend == "serial" or (backend == "process" and (workers == 1 or len(todo) <= 1)):
            for spec in todo:
                finish(spec, _execute(fn, spec, single_thread and backend != "serial"))
        elif backend == "process":
            ctx = mp.get_context("forkserver")
            with ProcessPoolExecutor(max_workers=workers, mp_context=ctx) as pool:
                pending = {pool.submit(_execute, fn, s, single_thread): s for s in todo}
                while pending:
                    finished, _ = wait(pending, return_when=FIRST_COMPLETED)
                    for fut in finished:
                        finish(pending.pop(fut), fut.result())
        else:
            _run_ray(fn, todo, workers, single_thread, finish)
    finally:
        if bar is not None:
            bar.close()
    if failures and raise_on_error:
        first = failures[0]
        raise RuntimeError(
            f"{len(failures)} run(s) failed; first {first['run_id']}:\n{first['error']}"
        )
    return [done[s.run_id] for s in specs if s.run_id in done]


def _run_ray(fn, todo, workers, single_thread, finish) -> None:
    try:
        import ray
    except ImportError:
        raise ImportError(
            "backend='ray' needs Ray: pip install -c constraints.txt -e '.[distributed]'"
        ) from None
    started = False
    if not ray.is_initialized():
        ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False)
        started = True
    try:
        remote = ray.remote(num_cpus=1)(_execute)
        refs = {remote.remote(fn, s, single_thread): s for s in todo}
        while refs:
            ready, _ = ray.wait(list(refs), num_returns=1)
            for ref in ready:
                finish(refs.pop(ref), ray.get(ref))
    finally:
        if started:
            ray.shutdown()


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
    vals = [float(v) for v in values]
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
