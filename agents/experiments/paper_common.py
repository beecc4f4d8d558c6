"""Shared code of the paper experiments (``agents.experiments.exp_*``, run by ``scripts/exp_*.py``).

How the experiment scripts are laid out: docs/experiments.md, section ``paper_common``.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import os
import re
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from mbtsr.io import write_json_atomic

REPO = Path(__file__).resolve().parents[2]

# ------------------------------------------------------------------------------------------------
# command line


@dataclass
class ExperimentArgs:
    """The command-line fields every experiment script shares (the sweep through
    :func:`mbtsr.runner.run_sweep`); a script's ``Args`` subclasses this, redefines ``mc`` with
    its own default and adds its own fields."""

    smoke: bool = field(default=False, metadata={
        "help": "tiny smoke-test run (options not given take the script's SMOKE values)"})
    workers: int = field(default=2, metadata={"help": "parallel worker processes"})
    backend: Literal["process", "serial", "ray"] = field(default="process", metadata={
        "help": "mbtsr.runner backend"})
    address: str = field(default="", metadata={
        "help": "Ray only: address of an existing cluster (auto, host:6379); empty: a private "
                "local Ray instance for the sweep (docs/troubleshooting.md)"})
    report_only: bool = field(default=False, metadata={
        "help": "no new runs: report the finished ones from their JSON"})
    mc: int = field(default=1, metadata={"help": "Monte-Carlo runs"})
    out: str = field(default="", metadata={
        "help": "results folder (runs, summary.json; default docs/results/<experiment>, "
                "with --smoke runs/smoke/<experiment>)"})
    figures: str = field(default="", metadata={"help": "figure folder"})

    def __post_init__(self) -> None:
        """``--workers`` and ``--mc`` at least 1."""
        for name in ("mc", "workers"):
            if getattr(self, name) < 1:
                raise ValueError(f"--{name} must be >= 1, got {getattr(self, name)}")


@dataclass
class TrainingArgs(ExperimentArgs):
    """:class:`ExperimentArgs` plus the fields of the experiments that fit models."""

    lr: float = field(default=0.01, metadata={"help": "Adam step size"})
    n_val: int = field(default=10, metadata={"help": "validation trajectories"})


@dataclass
class LinearRoundsArgs(TrainingArgs):
    """:class:`TrainingArgs` of the random-linear-system experiments (original README): models
    trained in rounds, one new trajectory per round, warm-started."""

    mc: int = field(default=20, metadata={"help": "Monte-Carlo runs (random systems)"})
    rounds: int = field(default=3, metadata={"help": "training rounds (one trajectory each)"})
    epochs_per_round: int = field(default=200, metadata={"help": "epochs per round"})


def print_medians(configs: dict[str, dict], columns: dict[str, str], width: int) -> None:
    """One line per config: ``name`` then ``label median`` of each ``columns`` entry
    (``label -> "key:format"``) from a summary's ``configs`` of :func:`spread` values."""
    for name, s in configs.items():
        cells = []
        for label, spec in columns.items():
            key, fmt = spec.split(":")
            cells.append(f"{label} {format(s[key].get('median', float('nan')), fmt)}")
        print(f"{name:{width}s} " + " ".join(cells))


def parse_args(args_cls: type, argv: Sequence[str] | None = None):
    """The experiment's command line from the dataclass ``args_cls`` (:func:`agents.cli.parse`);
    with ``--smoke`` the class attribute ``SMOKE`` (field overrides) supplies the defaults."""
    from agents.cli import parse

    return parse(args_cls, args=argv, presets={"--smoke": {
        "smoke": True, **getattr(args_cls, "SMOKE", {})}})


def comma_list(flag: str, text: str, kind: type = str, allowed: Sequence | None = None,
               empty: bool = False) -> list:
    """``"a,b"`` as ``[a, b]`` of ``kind``, or a ``ValueError`` naming ``--flag``: empty (unless
    ``empty``), not a ``kind``, an int below 1, or not one of ``allowed``."""
    items = [v.strip() for v in text.split(",") if v.strip()]
    if not items and not empty:
        raise ValueError(f"--{flag} must list at least one value, got {text!r}")
    try:
        values = [kind(v) for v in items]
    except ValueError:
        raise ValueError(f"--{flag} must be a comma list of {kind.__name__}s, got {text!r}"
                         ) from None
    for v in values:
        if allowed is not None and v not in allowed:
            raise ValueError(f"--{flag}: {v!r} is not one of {', '.join(map(str, allowed))}")
        if kind is int and v < 1:
            raise ValueError(f"--{flag} values must be >= 1, got {v}")
    return values


def output_dirs(args, experiment: str) -> tuple[Path, Path]:
    """``(out, figures)``: default ``docs/results/<experiment>`` and ``docs/figures``; with
    ``--smoke`` ``runs/smoke/<experiment>`` (git-ignored) and its ``figures`` sub-folder."""
    if args.out:
        out = Path(args.out)
    else:
        out = REPO / ("runs/smoke" if args.smoke else "docs/results") / experiment
    figures = (Path(args.figures) if args.figures
               else out / "figures" if args.smoke or args.out else REPO / "docs" / "figures")
    out.mkdir(parents=True, exist_ok=True)
    figures.mkdir(parents=True, exist_ok=True)
    return out, figures


def blas_threads_from_env() -> None:
    """A command's BLAS threads: ``OMP_NUM_THREADS``, else 1 (numpy's BLAS has loaded by the
    time a command parses its flags, so the limit is set through threadpoolctl)."""
    from threadpoolctl import threadpool_limits

    threadpool_limits(int(os.environ.get("OMP_NUM_THREADS", "1")))


def command_line() -> str:
    """The command that regenerates a result, as typed from the repository root."""
    script = Path(sys.argv[0])
    try:
        script = script.resolve().relative_to(REPO)
    except ValueError:
        pass
    return " ".join(["python", str(script), *sys.argv[1:]])


def library_version() -> dict:
    """The git commit of the checkout and whether ``mbtsr/``, ``envs/`` or ``agents/`` differ
    from it (the results depend on that code, so every sweep and benchmark records it)."""
    import subprocess

    def git(*cmd: str) -> str:
        try:
            return subprocess.run(["git", *cmd], cwd=REPO, capture_output=True, text=True,
                                  timeout=10).stdout.strip()
        except (OSError, subprocess.SubprocessError):
            return ""

    return {"commit": git("rev-parse", "HEAD"),
            "library_dirty": bool(git("status", "--porcelain", "--untracked-files=no", "--",
                                      "mbtsr", "envs", "agents"))}


def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo``, else ``platform.processor()``)."""
    import platform

    p = Path("/proc/cpuinfo")
    names = re.findall(r"model name\s*:\s*(.+)", p.read_text()) if p.is_file() else []
    return names[0].strip() if names else platform.processor()


def machine_info(load_start: tuple[float, ...] | None = None, **extra) -> dict:
    """Where a timing was measured, for a result's ``"machine"``: platform, Python, cores, torch
    threads (when torch is loaded), the load average (at ``load_start``, from
    ``os.getloadavg()`` at the start, and now), :func:`library_version`, and ``extra``."""
    import platform

    info = {"platform": platform.platform(), "python": platform.python_version(),
            "cpu_count": os.cpu_count(), "cpu": cpu_model()}
    if "torch" in sys.modules:
        info["torch_threads"] = sys.modules["torch"].get_num_threads()
    if load_start is not None:
        info["load_average_start"] = load_start
    return {**info, "load_average_end": os.getloadavg(), **library_version(), **extra}


def write_result(path: str | os.PathLike | None, result: dict, indent: int = 1) -> None:
    """Write a command's ``--out`` JSON atomically and say so (nothing without a path)."""
    if path:
        write_json_atomic(path, result, indent=indent)
        print(f"wrote {path}")


def _sweep(args, out: Path, experiment: str, run_fn: Callable[[dict, int], dict],
           configs: dict[str, dict], stages: Sequence[tuple[str, dict[str, dict]]] | None) -> None:
    """The sweep of :func:`run_experiment`, with ``<out>/args.json`` (the arguments and the
    command line) and one more entry of ``<out>/sweeps.json``: start, wall and driver CPU time,
    runs finished before and after, workers, load, library version at start and end."""
    from mbtsr.runner import load_results, run_sweep

    write_json_atomic(out / "args.json",
                      {"args": dataclasses.asdict(args), "command": command_line()})
    n_before, library = len(load_results(out)), library_version()
    t0, c0 = time.perf_counter(), time.process_time()
    sweep = functools.partial(run_sweep, run_fn, out_dir=out, backend=args.backend,
                              workers=args.workers, address=args.address or None)
    if stages is None:
        n_after = len(sweep(configs, range(args.mc), progress=not args.smoke))
    else:
        for label, todo in stages:
            for seed in range(args.mc):
                sweep(todo, [seed], progress=False)
                if not args.smoke:
                    print(f"[{experiment}] {label}: seed {seed} done, "
                          f"{time.perf_counter() - t0:.0f} s", flush=True)
        n_after = len(load_results(out))
    wall = time.perf_counter() - t0
    log_path = out / "sweeps.json"
    log = json.loads(log_path.read_text()) if log_path.exists() else []
    log.append({"started": time.strftime("%Y-%m-%dT%H:%M:%S", time.localtime(time.time() - wall)),
                "wall_s": round(wall, 1), "cpu_s_driver": round(time.process_time() - c0, 1),
                "runs_finished_before": n_before, "runs_finished_after": n_after,
                "workers": args.workers, "backend": args.backend,
                "load_avg_1min": round(os.getloadavg()[0], 2),
                "library_at_start": library, "library_at_end": library_version()})
    write_json_atomic(log_path, log)
    print(f"[{experiment}] sweep finished in {wall:.1f} s")


def run_experiment(
    args,
    experiment: str,
    run_fn: Callable[[dict, int], dict],
    configs: dict[str, dict],
    report_fn: Callable[[list[dict], Path, Path, object], dict],
    stages: Sequence[tuple[str, dict[str, dict]]] | None = None,
) -> dict:
    """Sweep ``run_fn`` over ``configs`` x ``range(args.mc)`` (unless ``--report-only``), then
    report from the stored JSON alone. Returns the summary written to ``<out>/summary.json``.

    :param stages: ``[(label, configs), ...]`` to run one after another instead, each seed by
        seed (an interrupted sweep then leaves every cell of a stage with the same number of
        seeds, give or take the last seed's); ``None``: all ``configs`` in one sweep."""
    from mbtsr.runner import load_results

    out, figures = output_dirs(args, experiment)
    if not args.report_only:
        _sweep(args, out, experiment, run_fn, configs, stages)
    records = [r for r in load_results(out) if r["name"] in configs or args.report_only]
    if not records:
        failed = [p for p in (out / "errors").glob("*.json")
                  if json.loads(p.read_text()).get("name") in configs]
        raise SystemExit(f"no finished runs in {out}/runs: " + (
            f"all {len(failed)} failed, tracebacks in {out}/errors" if failed and not
            args.report_only else "run without --report-only first"))
    summary = report_fn(records, out, figures, args)
    summary = {"experiment": experiment, "n_records": len(records), **summary}
    write_json_atomic(out / "summary.json", summary)
    return summary


# ------------------------------------------------------------------------------------------------
# small numerical helpers


def seed_sequence(seed: int, *tags: int) -> np.random.Generator:
    """An independent generator for (seed, tags...), e.g. ``seed_sequence(seed, 1, k)``."""
    return np.random.default_rng(np.random.SeedSequence([int(seed), *map(int, tags)]))


def child_seed(seed: int, *tags: int) -> int:
    """A 31-bit integer seed derived from (seed, tags...) (for APIs that take an int)."""
    return int(np.random.SeedSequence([int(seed), *map(int, tags)]).generate_state(1)[0] >> 1)


def finite_or_none(v: float | None) -> float | None:
    """``v`` as a float, ``None`` when it is ``None`` or not finite (strict JSON has no NaN)."""
    if v is None:
        return None
    v = float(v)
    return v if math.isfinite(v) else None


def values(records: list[dict], name: str, key: str) -> np.ndarray:
    """``[runs]`` array of ``result[key]`` for the records of config ``name`` (None -> nan); a
    ``log10_<k>`` the results do not store: log10 of ``<k>``."""
    results = [r["result"] for r in records if r["name"] == name]
    if key.startswith("log10_") and results and key not in results[0]:
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.log10(values(records, name, key[6:]))
    return np.array([res.get(key) for res in results], dtype=float)


def spread(v: np.ndarray) -> dict:
    """Median, inter-quartile range, mean, std and count of the finite values."""
    v = np.asarray(v, dtype=float)
    f = v[np.isfinite(v)]
    if f.size == 0:
        return {"n": 0, "n_nonfinite": int(v.size)}
    q1, med, q3 = np.percentile(f, [25, 50, 75])
    return {"n": int(f.size), "n_nonfinite": int(v.size - f.size), "median": float(med),
            "q1": float(q1), "q3": float(q3), "mean": float(f.mean()),
            "std": float(f.std(ddof=1)) if f.size > 1 else 0.0}


def spreads(records: list[dict], names: Sequence[str], keys: Sequence[str]) -> dict:
    """``{name: {key: spread(values(records, name, key))}}``: a report's per-config table."""
    return {n: {k: spread(values(records, n, k)) for k in keys} for n in names}


def compare(records: list[dict], a: str, b: str, keys: Sequence[str]) -> dict:
    """``{key: paired_comparison(config a, config b)}`` over the keys (paired by seed)."""
    return {k: paired_comparison(values(records, a, k), values(records, b, k)) for k in keys}


def compare_pairs(records: list[dict], pairs: Sequence[tuple[str, str]],
                  keys: Sequence[str]) -> dict:
    """``{"<a>_vs_<b>": compare(records, a, b, keys)}`` for the pairs whose configs both ran."""
    ran = {r["name"] for r in records}
    return {f"{a}_vs_{b}": compare(records, a, b, keys) for a, b in pairs if {a, b} <= ran}


def paired_comparison(a: np.ndarray, b: np.ndarray) -> dict:
    """Paired samples ``a`` vs ``b``: median of ``a - b``, fraction with ``a < b``, two-sided
    Wilcoxon signed-rank p-value (pairs with a non-finite member dropped; with tied or zero
    ``a - b`` the normal approximation: scipy's exact test then enumerates 2^n sign patterns)."""
    from scipy.stats import wilcoxon

    a, b = np.asarray(a, float), np.asarray(b, float)
    ok = np.isfinite(a) & np.isfinite(b)
    d = a[ok] - b[ok]
    res = {"n_pairs": int(ok.sum()), "median_diff": float(np.median(d)) if d.size else None,
           "frac_lower": float(np.mean(d < 0)) if d.size else None, "p_value": None}
    if d.size >= 5 and np.any(d != 0):
        ties = np.unique(np.abs(d)).size < d.size or bool(np.any(d == 0))
        res["p_value"] = float(wilcoxon(d, method="approx" if ties else "auto").pvalue)
    return res


# ------------------------------------------------------------------------------------------------
# plotting


def pyplot():
    """matplotlib.pyplot on the Agg backend (headless)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path: str | os.PathLike, dpi: int = 110) -> None:
    """Lay out (unless the figure has its own layout engine), save (folders created), close."""
    if fig.get_layout_engine() is None:  # a figure made with layout="constrained" keeps it
        fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    pyplot().close(fig)


def violins(ax, groups: dict[str, np.ndarray], *, ylabel: str, title: str = "",
            annotate: dict[str, str] | None = None) -> None:
    """One violin per group (finite values only) with the median marked and the points jittered.

    :param annotate: optional text per group placed above its violin (e.g. a diverged count)."""
    names = list(groups)
    data = [np.asarray(groups[k], float) for k in names]
    finite = [d[np.isfinite(d)] for d in data]
    pos = np.arange(1, len(names) + 1)
    ok = [i for i, d in enumerate(finite) if d.size >= 2 and np.ptp(d) > 0]
    if ok:
        parts = ax.violinplot([finite[i] for i in ok], positions=pos[ok], showmedians=True,
                              showextrema=False, widths=0.8)
        for body in parts["bodies"]:
            body.set_alpha(0.45)
    rng = np.random.default_rng(0)
    for i, d in enumerate(finite):
        if d.size:
            ax.plot(pos[i] + rng.uniform(-0.08, 0.08, d.size), d, ".", ms=3, color="k",
                    alpha=0.6)
    ax.set_xticks(pos, names, rotation=30, ha="right")
    ax.set_ylabel(ylabel)
    if title:
        ax.set_title(title)
    if annotate:
        lo, hi = ax.get_ylim()
        ax.set_ylim(lo, hi + 0.12 * (hi - lo))  # room for the labels inside the axes
        trans = ax.get_xaxis_transform()  # x in data, y in axes coordinates
        for i, k in enumerate(names):
            if k in annotate:
                ax.text(pos[i], 0.98, annotate[k], ha="center", va="top", fontsize=8,
                        transform=trans)


def eigen_limits(learned: Sequence[np.ndarray], true: np.ndarray) -> tuple[float, float, float]:
    """Square axis limits ``(re_min, re_max, im_max)`` around the bulk of the learned eigenvalues
    (1st .. 99th percentile), all true ones and the point 1."""
    pts = np.concatenate([np.asarray(z).ravel() for z in learned])
    pts = pts[np.isfinite(pts)]
    lo_re, hi_re, hi_im = 0.9, 1.05, 0.05
    if pts.size:
        lo_re, hi_re = np.percentile(pts.real, [1.0, 99.0])
        hi_im = np.percentile(np.abs(pts.imag), 99.0)
    true = np.asarray(true).ravel()
    lo_re, hi_re = min(lo_re, true.real.min()), max(hi_re, true.real.max())
    hi_im = max(hi_im, np.abs(true.imag).max())
    lo_re, hi_re = min(lo_re, 0.9), max(hi_re, 1.05)
    half = 1.1 * max((hi_re - lo_re) / 2, hi_im, 0.05)
    mid = (lo_re + hi_re) / 2
    return mid - half, mid + half, half


def eigen_scatter(ax, learned: np.ndarray, true: np.ndarray, title: str,
                  limits: tuple[float, float, float]) -> None:
    """Scatter learned eigenvalues (blue) and true ones (red) in the complex plane with the unit
    circle, like the paper's eigenvalue figures, in ``limits`` (:func:`eigen_limits`)."""
    th = np.linspace(0, 2 * np.pi, 2000)
    ax.plot(np.cos(th), np.sin(th), "k-", lw=0.6)
    learned, true = np.asarray(learned).ravel(), np.asarray(true).ravel()
    ax.plot(learned.real, learned.imag, ".", ms=2, color="tab:blue", alpha=0.35,
            label="learned")
    ax.plot(true.real, true.imag, "o", ms=4, mfc="none", color="tab:red", label="true")
    lo, hi, half = limits
    ax.set(xlim=(lo, hi), ylim=(-half, half), aspect="equal", xlabel="Re", ylabel="Im")
    ax.set_title(title, fontsize=9)


def complex_from_pairs(pairs: dict) -> np.ndarray:
    """Inverse of :func:`complex_to_pairs`: the stored form -> complex array ``[...]``."""
    a = np.array(pairs["re_im"].split(), dtype=float).reshape(*pairs["shape"], 2)
    return a[..., 0] + 1j * a[..., 1]


def complex_to_pairs(z: np.ndarray, digits: int = 4) -> dict:
    """Complex ``[...]`` -> ``{"shape": [...], "re_im": "re im re im ..."}`` with ``digits``
    decimals: one JSON string instead of one line per number keeps the per-run files small."""
    z = np.asarray(z)
    flat = np.stack([z.real, z.imag], axis=-1).ravel()
    return {"shape": list(z.shape), "re_im": " ".join(f"{v:.{digits}f}" for v in flat)}


# ------------------------------------------------------------------------------------------------
# data: random stable linear systems (paper Algorithm 2; original code section 4)


@dataclass(frozen=True)
class Sampling:
    """What the linear and the arm data share (docs/experiments.md, "paper_common")."""

    dt: float = 0.02
    noise_std: float = 0.01
    n_val: int = 10
    n_sim: int = 3
    eval_stride: int = 3


@dataclass(frozen=True)
class LinearData(Sampling):
    """Data of the random-linear-system experiments (docs/experiments.md, "paper_common")."""

    n: int = 10
    m: int = 10
    T: int = 200
    input_window: int = 5
    input_scale: float = 10.0
    n_train: int = 3
    last_state_zero: bool = False


def simulate_linear(A: np.ndarray, B: np.ndarray, x0: np.ndarray, u: np.ndarray) -> np.ndarray:
    """``x_{t+1} = A x_t + B u_t``. ``x0: [n]``, ``u: [T, m]`` -> ``x: [T+1, n]``."""
    x = np.empty((u.shape[0] + 1, A.shape[0]))
    x[0] = x0
    Bu = u @ B.T
    for t in range(u.shape[0]):
        x[t + 1] = A @ x[t] + Bu[t]
    return x


def linear_dataset(cfg: LinearData, seed: int) -> dict:
    """A random stable system (seeded by ``seed``) and its train / validation / simulation sets.

    :return: ``{"A": [n, n], "B": [n, m], "train": [Trajectory], "val": [...], "sim": [...]}``;
        only the training states carry measurement noise."""
    from envs.linear_system import random_stable_system
    from mbtsr.excitation import filtered_gaussian
    from mbtsr.trajectory import Trajectory

    A, B = random_stable_system(n=cfg.n, m=cfg.m, dt=cfg.dt, seed=child_seed(seed, 0))

    def trajectory(split: int, k: int, noise_std: float) -> Trajectory:
        rng = seed_sequence(seed, split, k)
        u = filtered_gaussian(cfg.T, cfg.m, window=cfg.input_window, scale=cfg.input_scale,
                              seed=child_seed(seed, split, k, 1))
        x = simulate_linear(A, B, rng.standard_normal(cfg.n), u)
        if cfg.last_state_zero and split == 1:
            x[-1] = 0.0  # the original generate_data never filled the last state
        x = x + noise_std * rng.standard_normal(x.shape)
        return Trajectory(x, u, dt=cfg.dt)

    return {
        "A": A,
        "B": B,
        "train": [trajectory(1, k, cfg.noise_std) for k in range(cfg.n_train)],
        "val": [trajectory(2, k, 0.0) for k in range(cfg.n_val)],
        "sim": [trajectory(3, k, 0.0) for k in range(cfg.n_sim)],
    }


# ------------------------------------------------------------------------------------------------
# data: the two-link robot (paper Sec. "Robot task"; original code section 3)


@dataclass(frozen=True)
class ArmSampling(Sampling):
    """:class:`Sampling` of the paper arm over ``duration`` [s] (``T = duration / dt``)."""

    duration: float = 4.0

    @property
    def T(self) -> int:  # noqa: N802 - the paper's symbol
        return int(round(self.duration / self.dt))


@dataclass(frozen=True)
class RobotData(ArmSampling):
    """Data of the robot experiments (docs/experiments.md, "paper_common": the robot data)."""

    n_train: int = 3


NOMINAL_DT = 0.02


def held_filtered_gaussian(T: int, m: int, rng: np.random.Generator, *, dt: float,
                           scale: float, window: int = 100) -> np.ndarray:
    """The paper's filtered Gaussian input generated on the nominal 0.02 s grid and held
    (zero-order) on a grid of period ``dt``: ``[T, m]``."""
    from mbtsr.excitation import filtered_gaussian

    n_nominal = int(np.ceil(T * dt / NOMINAL_DT - 1e-9)) + 1
    u = filtered_gaussian(n_nominal, m, window=window, scale=scale, seed=rng)
    idx = np.floor(np.arange(T) * dt / NOMINAL_DT + 1e-9).astype(int)
    return u[idx]


def arm_env(cfg: ArmSampling):
    """The paper-preset arm with episodes of one trajectory; Coulomb friction off
    (``frictionloss = (0, 0)``, viscous kept) when the config says ``friction=False``."""
    import envs  # noqa: F401 - registers the envs
    from envs.two_link_arm import TwoLinkArmEnv

    params = None if getattr(cfg, "friction", True) else {"frictionloss": (0.0, 0.0)}
    return TwoLinkArmEnv(preset="paper", episode_steps=cfg.T, dt=cfg.dt, params=params)


def arm_dataset(cfg: ArmSampling, seed: int, n_train: int, *, window: int = 100) -> dict:
    """Train / validation / simulation trajectories of the paper arm for MC run ``seed``
    (docs/experiments.md, "paper_common": the robot data), input window ``window`` taps.

    :return: ``{"env": env, "train": [...], "val": [...], "sim": [...]}``."""
    from envs.collect import collect_trajectories
    from mbtsr.trajectory import Trajectory

    env = arm_env(cfg)
    scale = math.sqrt(window) * env.excitation_std

    def collect(split: int, count: int, noise_std: float) -> list:
        trajs = collect_trajectories(
            env, count, cfg.T, input=held_filtered_gaussian,
            input_kwargs={"dt": cfg.dt, "scale": scale, "window": window},
            seed=child_seed(seed, split), reject_abs_q=0.9 * np.pi)
        rng = seed_sequence(seed, split, 99)
        return [Trajectory(tr.x + noise_std * rng.standard_normal(tr.x.shape), tr.u, dt=tr.dt)
                for tr in trajs]

    return {"env": env, "train": collect(1, n_train, cfg.noise_std),
            "val": collect(2, cfg.n_val, 0.0), "sim": collect(3, cfg.n_sim, 0.0)}


def robot_dataset(cfg: RobotData, seed: int) -> dict:
    """:func:`arm_dataset` of the robot experiments (the paper's 100-tap window, friction on)."""
    return arm_dataset(cfg, seed, cfg.n_train)


# ------------------------------------------------------------------------------------------------
# nominal model and training (paper Sec. "Nominal model")

NOMINAL_ACTIVATIONS = ("elu", "sigmoid", "tanh", "swish")
ALL_ACTIVATIONS = ("elu", "sigmoid", "tanh", "swish", "relu", "leaky_relu")

#: Epochs of the nominal model (paper): 1000 for g, 2000 for f; "the network was trained for
#: half the number of epochs" with sampled Jacobian propagation.
NOMINAL_EPOCHS = {"g": 1000, "f": 2000}


def nominal_epochs(formulation: str, method: str, scale: float = 1.0) -> int:
    """The paper's epoch count for ``formulation`` and ``method``, times ``scale`` (>= 1)."""
    epochs = NOMINAL_EPOCHS[formulation] * (0.5 if method == "sampled" else 1.0)
    return max(1, int(round(epochs * scale)))


def regularization(method: str, *, sigma: float = 0.1, n_copies: int = 1,
                   exact_weight: float = 1.0, smooth_weight: float = 0.01,
                   copies_batch: str = "shared"):
    """The :class:`mbtsr.training.RegularizationConfig` of a method name: ``none``, ``sampled``,
    ``exact`` or ``smooth`` (docs/experiments.md, "paper_common": the methods).

    :param copies_batch: ``"shared"`` (copies in their trajectory's batch) or ``"own"`` (one
        optimizer step per copy, the original code's batching)."""
    from mbtsr.training import RegularizationConfig

    if method == "none":
        return RegularizationConfig()
    if method == "sampled":
        return RegularizationConfig.paper(sigma=sigma, n_copies=n_copies,
                                          copies_batch=copies_batch)
    if method == "exact":
        return RegularizationConfig(exact_weight=exact_weight)
    if method == "smooth":
        return RegularizationConfig(smooth_weight=smooth_weight)
    raise ValueError(f"method must be none, sampled, exact or smooth, got {method!r}")


def build_ensemble(n: int, m: int, *, formulation: str = "g",
                   activations: Sequence[str] = NOMINAL_ACTIVATIONS, width: int = 20,
                   depth: int = 1, dropout: float = 0.0, layer_norm: bool = False,
                   repeat: int = 1, seed: int = 0):
    """The paper's nominal ensemble (4 x 20 units, elu/sigmoid/tanh/swish) or a deviation of it.

    :param repeat: every activation ``repeat`` times (ensemble size x3 deviation: 3)."""
    from mbtsr.ensemble import DynamicsEnsemble, EnsembleConfig, MemberSpec

    members = tuple(MemberSpec(a, width, depth, dropout, layer_norm)
                    for _ in range(repeat) for a in activations)
    return DynamicsEnsemble(EnsembleConfig(n, m, members=members, formulation=formulation,
                                           seed=int(seed)))


def train(model, trajs, *, epochs: int, method: str, seed: int, lr: float = 0.01,
          weight_decay: float = 0.0, optimizer_state=None, reg_kwargs: dict | None = None):
    """:func:`mbtsr.training.train_ensemble` with the experiments' settings (one trajectory per
    step as the original code, coupled L2 weight decay)."""
    from mbtsr.training import TrainConfig, train_ensemble

    cfg = TrainConfig(epochs=int(epochs), lr=lr, weight_decay=weight_decay, seed=int(seed),
                      progress=False)
    return train_ensemble(model, trajs, cfg, regularization(method, **(reg_kwargs or {})),
                          optimizer_state=optimizer_state)


# ------------------------------------------------------------------------------------------------
# the metric bundle (paper Sec. "Evaluation")


def evaluation_points(trajs, stride: int) -> tuple[np.ndarray, np.ndarray]:
    """Every ``stride``-th ``(x_t, u_t)`` of the trajectories: ``([P, n], [P, m])``."""
    X = np.concatenate([tr.x[:-1][::stride] for tr in trajs])
    U = np.concatenate([tr.u[::stride] for tr in trajs])
    return X, U


def eigenvalue_matching_error(ev_hat: np.ndarray, ev_true: np.ndarray) -> float:
    """The original code's eigenvalue error (``eval_jac2``): at each point
    ``sum_i min_j |l_i - l*_j|^2 + sum_j min_i |l_i - l*_j|^2``, then sqrt of the mean over
    points. ``ev_hat: [P, n]``, ``ev_true: [n]`` or ``[P, n]``."""
    ev_true = np.broadcast_to(ev_true, ev_hat.shape)
    d = np.abs(ev_hat[:, :, None] - ev_true[:, None, :]) ** 2  # [P, n, n]
    per_point = d.min(2).sum(1) + d.min(1).sum(1)
    return float(np.sqrt(per_point.mean()))


def evaluate(model, val, sim, X: np.ndarray, U: np.ndarray, A_true: np.ndarray,
             B_true: np.ndarray) -> dict:
    """Prediction, simulation and Jacobian metrics of ``model``.

    :param val: validation trajectories (one-step prediction RMS, all transitions).
    :param sim: trajectories simulated from their ``x_0`` with their inputs (simulation RMS per
        trajectory, averaged as the original's ``simaverage``; divergence counted).
    :param X: ``[P, n]``, ``U: [P, m]`` points where the Jacobians are compared.
    :param A_true: ``[P, n, n]``, ``B_true: [P, n, m]`` true Jacobians there.
    :return: ``pred_rms, sim_rms`` (mean over ``sim``; inf if one blew up), ``sim_rms_finite``
        (mean over the non-diverged ones), ``sim_diverged`` (count), ``jac_err`` (paper eq.
        (jacerr)), ``jac_rms_entry`` (original's per-entry RMS), ``log10`` versions."""
    from mbtsr.metrics import jacobian_error, jacobian_rms_per_entry, prediction_rms, simulation_rms

    pred = prediction_rms(model, val)
    sims = [simulation_rms(model, tr) for tr in sim]
    sim_rms = np.array([s[0] for s in sims], dtype=float)
    diverged = np.array([s[1] > 0 for s in sims])
    A_hat, B_hat = model.member_jacobians(X, U)
    J_true = (A_true, B_true)
    jac = jacobian_error(J_true, (A_hat, B_hat))
    with np.errstate(divide="ignore"):
        return {
            "pred_rms": finite_or_none(pred),
            "log10_pred_rms": finite_or_none(np.log10(pred)),
            "sim_rms": finite_or_none(sim_rms.mean()),
            "log10_sim_rms": finite_or_none(np.log10(sim_rms.mean())),
            "sim_rms_each": [finite_or_none(v) for v in sim_rms],
            "sim_diverged": int(diverged.sum()),
            "n_sim": len(sim),
            "jac_err": finite_or_none(jac),
            "jac_rms_entry": finite_or_none(jacobian_rms_per_entry(J_true, (A_hat, B_hat))),
        }


def eigen_summary(ev_hat: np.ndarray, ev_true: np.ndarray | None, n_store: int) -> dict:
    """Scalar summaries of learned state-Jacobian eigenvalues ``ev_hat: [P, n]`` (complex) and the
    first ``n_store`` points' eigenvalues for the figures."""
    out = {
        "eig_mean_abs": float(np.abs(ev_hat).mean()),
        "eig_mean_dist_to_1": float(np.abs(ev_hat - 1.0).mean()),
        "eig_max_abs": float(np.abs(ev_hat).max()),
        "eig_learned": complex_to_pairs(ev_hat[:n_store]),
    }
    if ev_true is not None:
        out["eig_match_err"] = eigenvalue_matching_error(ev_hat, ev_true)
        out["eig_true"] = complex_to_pairs(ev_true)
        out["eig_true_mean_abs"] = float(np.abs(ev_true).mean())
        out["eig_true_mean_dist_to_1"] = float(np.abs(ev_true - 1.0).mean())
    return out


# ------------------------------------------------------------------------------------------------
# Monte-Carlo run functions (module level, so that the process pool's workers can import them)


def timed(run_fn: Callable[[dict, int], dict]) -> Callable[[dict, int], dict]:
    """``run_fn(config, seed)`` with its wall and CPU time [s] added to the result (``wall``,
    ``cpu_time``)."""

    @functools.wraps(run_fn)
    def run(config: dict, seed: int) -> dict:
        t0, c0 = time.perf_counter(), time.process_time()
        result = run_fn(config, seed)
        return {**result, "wall": time.perf_counter() - t0, "cpu_time": time.process_time() - c0}

    return run


@timed
def run_linear(config: dict, seed: int) -> dict:
    """One Monte-Carlo run on a random stable linear system (``exp_linear``,
    ``exp_weight_decay``); ``config``'s keys: docs/experiments.md, "paper_common"."""
    from mbtsr.metrics import jacobian_eigenvalues, prediction_rms

    cfg = LinearData(**config["data"])
    d = linear_dataset(cfg, seed)
    X, U = evaluation_points(d["val"], cfg.eval_stride)
    A_true = np.broadcast_to(d["A"], (len(X), cfg.n, cfg.n))
    B_true = np.broadcast_to(d["B"], (len(X), cfg.n, cfg.m))
    model = build_ensemble(cfg.n, cfg.m, formulation=config["formulation"],
                           seed=child_seed(seed, 10))
    rounds, state = [], None
    for r in range(config["rounds"]):
        trajs = d["train"][: r + 1] if config["incremental"] else d["train"]
        hist = train(model, trajs, epochs=config["epochs_per_round"], method=config["method"],
                     seed=child_seed(seed, 20, r), lr=config["lr"],
                     weight_decay=config["weight_decay"], optimizer_state=state,
                     reg_kwargs=config["reg"])
        state = hist.optimizer_state
        metrics = evaluate(model, d["val"], d["sim"], X, U, A_true, B_true)
        rounds.append({k: metrics[k] for k in ("jac_rms_entry", "jac_err", "pred_rms",
                                               "sim_rms")}
                      | {"train_loss": finite_or_none(hist.train_loss[-1])})
    return {**metrics, "train_pred_rms": finite_or_none(prediction_rms(model, d["train"])),
            **eigen_summary(jacobian_eigenvalues(model, X, U), np.linalg.eigvals(d["A"]),
                            config["n_eig_store"]),
            "rounds": rounds, "train_loss": rounds[-1]["train_loss"]}


@timed
def run_robot(config: dict, seed: int) -> dict:
    """One Monte-Carlo run on the paper's two-link robot (``exp_robot``, ``exp_deviations``);
    ``config``'s keys: docs/experiments.md, "paper_common"."""
    from mbtsr.metrics import jacobian_eigenvalues, prediction_rms

    cfg = RobotData(**config["data"])
    d = robot_dataset(cfg, seed)
    env = d["env"]
    X, U = evaluation_points(d["val"], cfg.eval_stride)
    A_true, B_true = env.linearize_trajectory(X, U)
    model = build_ensemble(4, 2, formulation=config["formulation"], seed=child_seed(seed, 10),
                           **config.get("model", {}))
    t1 = time.perf_counter()
    hist = train(model, d["train"], epochs=config["epochs"], method=config["method"],
                 seed=child_seed(seed, 20), lr=config["lr"], reg_kwargs=config["reg"])
    train_time = time.perf_counter() - t1
    return {**evaluate(model, d["val"], d["sim"], X, U, A_true, B_true),
            "train_pred_rms": finite_or_none(prediction_rms(model, d["train"])),
            "eig_match_err": eigenvalue_matching_error(jacobian_eigenvalues(model, X, U),
                                                       np.linalg.eigvals(A_true)),
            "train_loss": finite_or_none(hist.train_loss[-1]), "steps": int(hist.steps),
            "train_time": train_time}


@timed
def run_activations(config: dict, seed: int) -> dict:
    """One Monte-Carlo run of the activation-function comparison (paper appendix A): one
    member per activation in one batched ensemble, the prediction RMS of each at the
    ``checkpoints`` (docs/experiments.md, "exp_activations")."""
    cfg = RobotData(**config["data"])
    d = robot_dataset(cfg, seed)
    acts = list(config["activations"])
    model = build_ensemble(4, 2, formulation=config["formulation"], activations=acts,
                           width=config["width"], seed=child_seed(seed, 10))
    Xv, Uv = evaluation_points(d["val"], 1)
    Yv = np.concatenate([tr.x[1:] for tr in d["val"]])
    pred = {a: [] for a in acts}
    done, state = 0, None
    for c in config["checkpoints"]:
        hist = train(model, d["train"], epochs=c - done, method="none",
                     seed=child_seed(seed, 20, c), lr=config["lr"], optimizer_state=state)
        state, done = hist.optimizer_state, c
        P = model.member_predictions(Xv, Uv)  # [K, N, n]
        with np.errstate(over="ignore", invalid="ignore"):
            rms = np.sqrt(np.mean((P - Yv) ** 2, axis=(1, 2)))
        for a, v in zip(acts, rms):
            pred[a].append(finite_or_none(v))
    return {"pred_rms": pred, "checkpoints": list(config["checkpoints"])}


# ------------------------------------------------------------------------------------------------
# regime sweep of the robot Jacobian claim (``exp_regime``)

#: moving-average taps of the excitation windows (at dt 0.02 s; torque std kept in both)
EXCITATION_WINDOWS = {"paper": 100, "short": 10}


@dataclass(frozen=True)
class RegimeData(ArmSampling):
    """Data of one regime-sweep cell family: the robot data with an excitation window, with or
    without Coulomb friction; cells use the first ``n_train`` of ``n_train_max`` trajectories."""

    window: str = "paper"
    friction: bool = True
    n_train_max: int = 10


@functools.lru_cache(maxsize=8)  # the cells of one seed share it (the sweep runs seed by seed)
def regime_dataset(cfg: RegimeData, seed: int) -> dict:
    """Train / validation / simulation trajectories and the true Jacobians (MuJoCo finite
    differences) at the evaluation points and at every training point, for MC run ``seed``.

    :return: ``{"env", "train", "val", "sim", "X", "U", "A", "B", "A_train", "B_train"}`` with
        ``A_train: [n_train_max, T, 4, 4]`` at the measured (noisy) training states."""
    d = arm_dataset(cfg, seed, cfg.n_train_max, window=EXCITATION_WINDOWS[cfg.window])
    env = d["env"]
    d["X"], d["U"] = evaluation_points(d["val"], cfg.eval_stride)
    d["A"], d["B"] = env.linearize_trajectory(d["X"], d["U"])
    jac_train = [env.linearize_trajectory(tr.x[:-1], tr.u) for tr in d["train"]]
    d["A_train"] = np.stack([a for a, _ in jac_train])
    d["B_train"] = np.stack([b for _, b in jac_train])
    return d


def row_group_errors(A_true: np.ndarray, B_true: np.ndarray, A_hat: np.ndarray,
                     B_hat: np.ndarray, mask: np.ndarray | None = None) -> dict:
    """Paper eq. (jacerr) ``sqrt(mean_t ||J_t - Jhat_t||_F^2)`` over all rows and split into the
    arm's position rows (q, rows 0-1) and velocity rows (qdot, rows 2-3), over the points in
    ``mask`` (default all). ``A: [P, 4, 4]``, ``B: [P, 4, 2]``."""
    dJ = np.concatenate([A_true - A_hat, B_true - B_hat], -1)  # [P, 4, 6]
    if mask is not None:
        dJ = dJ[mask]
    if dJ.shape[0] == 0:
        return {"all": None, "pos": None, "vel": None}
    sq = dJ ** 2
    return {"all": float(np.sqrt(sq.sum((1, 2)).mean())),
            "pos": float(np.sqrt(sq[:, :2].sum((1, 2)).mean())),
            "vel": float(np.sqrt(sq[:, 2:].sum((1, 2)).mean()))}


def jacobian_diagnostics(X: np.ndarray, A_true: np.ndarray, B_true: np.ndarray,
                         A_hat: np.ndarray, B_hat: np.ndarray, still_speed: float) -> dict:
    """The Jacobian error split by row group and into "still" points (some joint speed below
    ``still_speed``: stiction) and "moving" ones.

    :return: ``jac_{all,pos,vel}`` and ``jac_{moving,still}_{all,pos,vel}``, ``frac_still``."""
    still = (np.abs(X[:, 2:4]) < still_speed).any(1)
    out = {"frac_still": float(still.mean())}
    for tag, mask in (("", None), ("moving_", ~still), ("still_", still)):
        for k, v in row_group_errors(A_true, B_true, A_hat, B_hat, mask).items():
            out[f"jac_{tag}{k}"] = v
    return out


def label_jacobians(labels: list, trajs: list) -> tuple[np.ndarray, np.ndarray]:
    """The LTV models' ``(A [sum T, n, n], B [sum T, n, m])`` over their trajectories' steps."""
    return tuple(np.concatenate([np.asarray(getattr(lm, k))[:tr.T]
                                 for lm, tr in zip(labels, trajs)]) for k in "AB")


def oracle_ltv_models(trajs, A_train: np.ndarray, B_train: np.ndarray) -> list:
    """"LTV" models of the TRUE Jacobians through the measured states: perturbed copies get the
    labels ``x_{t+1} + A_t dx + B_t du`` (the oracle upper bound of sampled JacProp)."""
    from mbtsr.ltv import LTVModel

    models = []
    for tr, A, B in zip(trajs, A_train, B_train):
        T = tr.T
        A, B = A[:T], B[:T]
        c = tr.x[1:] - np.einsum("tij,tj->ti", A, tr.x[:-1]) - np.einsum("tij,tj->ti", B, tr.u)
        cov = np.broadcast_to(np.eye(tr.n + tr.m + 1), (T, tr.n, tr.n + tr.m + 1,
                                                        tr.n + tr.m + 1))
        models.append(LTVModel(A=A, B=B, c=c, cov=np.array(cov), lam=0.0))
    return models


def fused_ltv_models(ltv_models: list, model, trajs, prior_scale: float = 1.0) -> list:
    """The LTV models fused (:func:`mbtsr.ltv.fuse_prior`) with a prior at the network's
    ensemble-mean Jacobians, of covariance ``prior_scale`` x the LTV posterior's (1: the
    average of the two Jacobians); the original's ``useprior``."""
    from mbtsr.ltv import fuse_prior

    return [fuse_prior(lm, *model.jacobians(tr.x[:-1], tr.u),
                       np.asarray(lm.cov)[:tr.T] * prior_scale)
            for lm, tr in zip(ltv_models, trajs)]


REGIME_METHODS = ("none", "sampled", "exact", "oracle", "prior")


@timed
def run_regime(config: dict, seed: int) -> dict:
    """One Monte-Carlo run of the regime sweep (``exp_regime``); ``config``'s keys and the
    methods: docs/experiments.md, "paper_common". Every method of one cell takes the same
    number of optimizer steps."""
    from mbtsr.metrics import prediction_rms
    from mbtsr.training import RegularizationConfig, TrainConfig, train_ensemble

    method = config["method"]
    if method not in REGIME_METHODS:  # else it would silently train as "sampled"
        raise ValueError(f"config['method'] must be one of {REGIME_METHODS}, got {method!r}")
    cfg = RegimeData(**config["data"])
    d = regime_dataset(cfg, seed)
    n_train, E = int(config["n_train"]), int(config["epochs"])
    trajs = d["train"][:n_train]
    A_tr, B_tr = (np.concatenate(list(d[k][:n_train])) for k in ("A_train", "B_train"))
    X_tr, U_tr = evaluation_points(trajs, 1)
    model = build_ensemble(4, 2, seed=child_seed(seed, 10), **config.get("model", {}))
    batch = sum(tr.T for tr in trajs) if config["batch"] == "full" else "trajectory"
    log_epochs = sorted({max(0, int(round(E * f)) - 1) for f in
                         np.linspace(0, 1, int(config["n_log"]) + 1)[1:]})
    log = {"epoch": [], "pos": [], "vel": []}

    def callback(epoch: int, m) -> None:
        if epoch + offset[0] in log_epochs:
            e = row_group_errors(A_tr, B_tr, *m.jacobians(X_tr, U_tr))
            log["epoch"].append(epoch + offset[0] + 1)
            log["pos"].append(e["pos"])
            log["vel"].append(e["vel"])

    offset = [0]
    oracle = method == "oracle"
    ltv_models = oracle_ltv_models(trajs, d["A_train"], d["B_train"]) if oracle else None
    reg = {"none": RegularizationConfig(), "exact": RegularizationConfig(
        exact_weight=config["exact_weight"])}.get(method, RegularizationConfig.paper())
    t1 = time.perf_counter()
    phases = [E] if method != "prior" else [E // 2, E - E // 2]
    state, label_models, steps, plain = None, ltv_models, 0, None
    for p, epochs in enumerate(phases):
        tc = TrainConfig(epochs=epochs, lr=config["lr"], batch=batch, seed=child_seed(seed, 20, p),
                         progress=False)
        if p == 1:
            label_models = fused_ltv_models(label_models, model, trajs, config["prior_scale"])
        hist = train_ensemble(model, trajs, tc, reg, ltv_models=label_models,
                              optimizer_state=state, callback=callback)
        state, offset[0], steps = hist.optimizer_state, offset[0] + epochs, steps + hist.steps
        if p == 0:
            label_models = plain = hist.ltv_models
    train_time = time.perf_counter() - t1
    result = evaluate(model, d["val"], d["sim"], d["X"], d["U"], d["A"], d["B"])
    A_hat, B_hat = model.jacobians(d["X"], d["U"])
    result.update(jacobian_diagnostics(d["X"], d["A"], d["B"], A_hat, B_hat,
                                       config["still_speed"]))
    result["train_pred_rms"] = finite_or_none(prediction_rms(model, trajs))
    result["net_train_jac"] = log
    # the labels' Jacobian error at the training points (ltv: prior's plain first-half labels)
    for tag, labels in (("label", label_models), ("ltv", plain if method == "prior" else None)):
        if labels is not None:
            e = row_group_errors(A_tr, B_tr, *label_jacobians(labels, trajs))
            result.update({f"{tag}_jac_pos": e["pos"], f"{tag}_jac_vel": e["vel"]})
    result["steps"] = steps
    result["train_time"] = train_time
    return result


def robot_truth_diagnostics(cfg: RobotData, seed: int, still_speed: float = 0.05) -> dict:
    """What caps the robot's Jacobian error, for MC run ``seed`` of ``exp_robot`` (no training):
    ``const_train`` / ``const_eval``, ``twin`` (``_moving``, ``_still``), ``ltv_{pos,vel}``,
    ``frac_still`` (docs/experiments.md, "exp_robot")."""
    from mbtsr.ltv import fit_ltv
    from mbtsr.training import ORIGINAL_LTV_LAMBDA

    d = robot_dataset(cfg, seed)
    env, trajs = d["env"], d["train"]
    X, U = evaluation_points(d["val"], cfg.eval_stride)
    A, B = env.linearize_trajectory(X, U)
    J = np.concatenate([A, B], -1)
    A_tr, B_tr = (np.concatenate(j) for j in zip(*[env.linearize_trajectory(tr.x[:-1], tr.u)
                                                   for tr in trajs]))

    def err(dJ: np.ndarray) -> float:
        return float(np.sqrt((dJ ** 2).sum((-1, -2)).mean()))

    twin = jacobian_diagnostics(X, A, B, *env.analytic_model().jacobians(X, U), still_speed)
    labels = [fit_ltv(tr, ORIGINAL_LTV_LAMBDA) for tr in trajs]
    ltv = row_group_errors(A_tr, B_tr, *label_jacobians(labels, trajs))
    return {"const_train": err(J - np.concatenate([A_tr, B_tr], -1).mean(0)),
            "const_eval": err(J - J.mean(0)), "twin": twin["jac_all"],
            "twin_moving": twin["jac_moving_all"], "twin_still": twin["jac_still_all"],
            "frac_still": twin["frac_still"], "ltv_pos": ltv["pos"], "ltv_vel": ltv["vel"]}
