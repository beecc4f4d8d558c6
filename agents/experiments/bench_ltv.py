"""Benchmark of LTV identification (issue 3).

What it measures and how to run it: docs/experiments.md, section ``bench_ltv``.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")  # one core, like the generic solver
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")

import dataclasses  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
import scipy  # noqa: E402
import scipy.sparse as sp  # noqa: E402
import scipy.sparse.linalg as spl  # noqa: E402

from agents.cli import main as command  # noqa: E402
from agents.experiments.paper_common import machine_info, write_result  # noqa: E402
from mbtsr.ltv import fit_ltv, fit_ltv_tv, select_lambda  # noqa: E402


@dataclasses.dataclass
class Args:
    """Benchmark of LTV identification: fit_ltv vs a generic sparse solve, TV solver, lambda."""

    out: str | None = None
    """write the results to this JSON file"""
    smoke: bool = False
    """tiny CI size: the options not given take SMOKE's values"""
    sizes: str = "4x2,10x10"
    """(n, m) pairs, comma separated"""
    horizons: str = "200,1000,5000"
    """values of T, comma separated"""
    lam: float = 10.0
    """L2 regularization weight"""
    repeats: int = 7
    """timed loops of the fit and of the generic solve, alternating (each about 50 ms of
    calls); the speed-up is the median of the paired ratios"""
    generic_max_unknowns: int = 2_000_000
    """skip the generic solve above this many unknowns T n (n+m)"""
    noise: float = 0.05
    """measurement noise of the test data"""
    tv_T: int = 1000
    """horizon of the TV benchmark"""
    seed: int = 0
    """seed of the test systems and data"""


#: --smoke: the tiny CI size (options given on the command line win)
SMOKE = {"smoke": True, "sizes": "4x2", "horizons": "100,200", "repeats": 1, "tv_T": 100}


def main(argv: list[str] | None = None) -> dict:
    """The command line (``--help``: the options)."""
    return command(Args, run, args=argv, outputs=("out",), presets={"--smoke": SMOKE})


def stable_system(n: int, m: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A random stable pair (A, B): orthogonal times 0.9, unit-scale B."""
    Q, _ = np.linalg.qr(rng.normal(size=(n, n)))
    return 0.9 * Q, rng.normal(size=(n, m)) / np.sqrt(m)


def simulate(A, B, T, noise, rng):
    """x: [T+1, n], u: [T, m] from x_{t+1} = A_t x_t + B_t u_t + e (A, B [T, ...] or fixed)."""
    A = np.broadcast_to(A, (T, *A.shape[-2:]))
    B = np.broadcast_to(B, (T, *B.shape[-2:]))
    u = rng.normal(size=(T, B.shape[2]))
    x = np.zeros((T + 1, A.shape[1]))
    for t in range(T):
        x[t + 1] = A[t] @ x[t] + B[t] @ u[t] + noise * rng.normal(size=A.shape[1])
    return x, u


def jacobian_rms(fit, A: np.ndarray, B: np.ndarray) -> float:
    """RMS over time of the Frobenius error of a fit's ``[A_t B_t]`` against ``A, B [T, ...]``."""
    err = np.concatenate([fit.A - A, fit.B - B], axis=2)
    return float(np.sqrt(np.mean(np.sum(err**2, axis=(1, 2)))))


def generic_normal_equations(x: np.ndarray, u: np.ndarray, lam: float):
    """The same problem assembled generically: the sparse normal equations ``(N, r)`` of
    ``[I kron phi_t^T ; lam D kron I] k = [x_{t+1} ; 0]`` in ``k = vec([A_t B_t]^T)``."""
    T, n = u.shape[0], x.shape[1]
    phi = np.concatenate([x[:-1], u], axis=1)
    p = phi.shape[1]
    # measurement rows: block t is I_n kron phi_t^T  (n rows, n p columns)
    C = sp.block_diag([sp.kron(sp.eye(n), phi[t][None, :]) for t in range(T)], format="csr")
    D = sp.diags([-np.ones(T - 1), np.ones(T - 1)], [0, 1], shape=(T - 1, T))
    A_ls = sp.vstack([C, lam * sp.kron(D, sp.eye(n * p))]).tocsc()
    b = np.concatenate([x[1:].reshape(-1), np.zeros((T - 1) * n * p)])
    return (A_ls.T @ A_ls).tocsc(), A_ls.T @ b


def _per_call(fn, calls: int) -> float:
    fn()  # untimed: the first call after another function's pays for its memory and caches
    t0 = time.perf_counter()
    for _ in range(calls):
        fn()
    return (time.perf_counter() - t0) / calls


def timings(*fns, repeats: int, min_seconds: float = 0.05) -> np.ndarray:
    """``[len(fns), repeats]`` seconds per call of each ``fn()``, each from a loop of as many
    calls as fill ``min_seconds`` (as ``timeit``: one call of a 1 ms function is at the mercy of
    the clock and of other processes); the functions' loops alternate (a, b, a, b, ...), so that
    each ratio ``b_i / a_i`` compares them at the same machine speed (a shared machine's speed
    drifts by tens of percent between seconds)."""
    calls = [max(1, int(np.ceil(min_seconds / max(_per_call(fn, 1), 1e-9)))) for fn in fns]
    return np.array([[_per_call(fn, c) for fn, c in zip(fns, calls)]
                     for _ in range(repeats)]).T


def run(args: Args) -> dict:
    """Run the benchmark; print and return the results (and write ``args.out``)."""
    rng = np.random.default_rng(args.seed)
    sizes = [tuple(int(v) for v in s.split("x")) for s in args.sizes.split(",")]
    horizons = [int(v) for v in args.horizons.split(",")]
    results: dict = {
        "config": dataclasses.asdict(args),
        "machine": machine_info(numpy=np.__version__, scipy=scipy.__version__,
                                threads=os.environ.get("OMP_NUM_THREADS")),
        "l2": [],
    }
    l2_fits(args, sizes, horizons, rng, results)
    tv_fit(args, rng, results)
    automatic_lambda(args, rng, results)
    targets(results)
    write_result(args.out, results, indent=2)
    return results


def l2_fits(args: Args, sizes: list[tuple[int, int]], horizons: list[int],
            rng: np.random.Generator, results: dict) -> None:
    """``results["l2"]``: the L2 fit vs a generic sparse solve per size and horizon;
    ``results["exponent"]``: the scaling exponent in T (least-squares slope of log time vs
    log T)."""
    for n, m in sizes:
        A, B = stable_system(n, m, rng)
        for T in horizons:
            x, u = simulate(A, B, T, args.noise, rng)
            fit = lambda x=x, u=u: fit_ltv((x, u), args.lam)  # noqa: E731
            row = {"n": n, "m": m, "T": T}
            unknowns = T * n * (n + m)
            if unknowns > args.generic_max_unknowns:
                (t_fit,) = timings(fit, repeats=args.repeats)
                row["generic_solve_s"] = None
            else:
                normal, rhs = generic_normal_equations(x, u, args.lam)
                t_fit, t_solve = timings(
                    fit, lambda a=normal, b=rhs: spl.spsolve(a, b), repeats=args.repeats)
                t_asm = float(np.median(timings(
                    lambda x=x, u=u: generic_normal_equations(x, u, args.lam), repeats=3)))
                k_ref = spl.spsolve(normal, rhs).reshape(T, n, n + m)
                k_fast = fit_ltv((x, u), args.lam).params
                row.update({
                    "generic_solve_s": float(np.median(t_solve)),
                    "generic_assembly_s": t_asm,
                    "speedup_vs_solve": float(np.median(t_solve / t_fit)),
                    "speedup_vs_solve_range": [float(np.min(t_solve / t_fit)),
                                               float(np.max(t_solve / t_fit))],
                    "speedup_vs_assembly_plus_solve": float(np.median((t_solve + t_asm) / t_fit)),
                    "rel_diff": float(np.linalg.norm(k_fast - k_ref) / np.linalg.norm(k_ref)),
                })
            row.update(fit_s=float(np.median(t_fit)), fit_min_s=float(np.min(t_fit)))
            results["l2"].append(row)
            print(json.dumps(row))

    results["exponent"] = {}
    for n, m in sizes:
        rows = [r for r in results["l2"] if (r["n"], r["m"]) == (n, m)]
        slope = np.polyfit(np.log([r["T"] for r in rows]), np.log([r["fit_s"] for r in rows]), 1)
        results["exponent"][f"{n}x{m}"] = float(slope[0])


def tv_fit(args: Args, rng: np.random.Generator, results: dict) -> None:
    """``results["tv"]``, ``["tv_admm_only"]``: the TV fit at T = tv_T on a system with one
    jump, with and without the polish."""
    n, m, T = 4, 2, args.tv_T
    A1, B1 = stable_system(n, m, rng)
    A2, B2 = stable_system(n, m, rng)
    t_jump = T // 2
    before = (np.arange(T) < t_jump)[:, None, None]
    A_tv, B_tv = np.where(before, A1, A2), np.where(before, B1, B2)
    x, u = simulate(A_tv, B_tv, T, args.noise, rng)
    # noise-level choice: lam ~ 2 sigma sqrt(T s^2 p n), s^2 the regressor power per entry
    phi = np.concatenate([x[:-1], u], axis=1)
    lam_tv = 2.0 * args.noise * np.sqrt(T * np.mean(phi**2) * (n + m) * n)
    t0 = time.perf_counter()
    tv = fit_ltv_tv((x, u), lam_tv)
    t_tv = time.perf_counter() - t0
    results["tv"] = {
        "n": n, "m": m, "T": T, "lam": float(lam_tv), "time_s": t_tv,
        "iterations": tv.info["iterations"], "converged": tv.info["converged"],
        "polished": tv.info["polished"], "kkt_ratio": tv.info["kkt_ratio"],
        "true_change_point": t_jump, "change_points": tv.info["change_points"],
        "jacobian_rms_error": jacobian_rms(tv, A_tv, B_tv),
    }
    t0 = time.perf_counter()
    tv_nopolish = fit_ltv_tv((x, u), lam_tv, polish=False, max_iter=20000)
    results["tv_admm_only"] = {
        "time_s": time.perf_counter() - t0,
        "iterations": tv_nopolish.info["iterations"],
        "converged": tv_nopolish.info["converged"],
        "n_change_points": len(tv_nopolish.info["change_points"]),
        "max_abs_diff_to_polished": float(np.abs(tv_nopolish.params - tv.params).max()),
    }
    print(json.dumps(results["tv"]))
    print(json.dumps(results["tv_admm_only"]))


def automatic_lambda(args: Args, rng: np.random.Generator, results: dict) -> None:
    """``results["select_lambda_<method>"]``: the automatic lambda at T = 1000 on a smoothly
    varying system, against the best lambda of its grid."""
    (A1, B1), (A2, B2) = stable_system(4, 2, rng), stable_system(4, 2, rng)
    w = (0.5 - 0.5 * np.cos(2 * np.pi * np.arange(1000) / 1000))[:, None, None]
    A_s, B_s = (1 - w) * A1 + w * A2, (1 - w) * B1 + w * B2  # norms stay <= 0.9: stable
    x, u = simulate(A_s, B_s, 1000, args.noise, rng)
    for method in ("marginal_likelihood", "gcv"):
        t0 = time.perf_counter()
        lam_sel, curve = select_lambda((x, u), method=method)
        elapsed = time.perf_counter() - t0
        grid_err = [jacobian_rms(fit_ltv((x, u), g), A_s, B_s) for g in curve["lambdas"]]
        results[f"select_lambda_{method}"] = {
            "T": 1000, "n": 4, "m": 2, "time_s": elapsed, "lam": lam_sel,
            "grid_points": len(curve["lambdas"]), "at_boundary": curve["at_boundary"],
            "jacobian_rms_error": jacobian_rms(fit_ltv((x, u), lam_sel), A_s, B_s),
            "error_optimal_grid_lam": float(curve["lambdas"][int(np.argmin(grid_err))]),
            "error_optimal_grid_error": float(min(grid_err)),
        }
        print(json.dumps(results[f"select_lambda_{method}"]))


def targets(results: dict) -> None:
    """``results["targets"]``: the scaling exponent, the speed-up and the 10 ms target."""
    speedups = [r["speedup_vs_solve"] for r in results["l2"] if "speedup_vs_solve" in r]
    results["targets"] = {
        "exponent_max": {"value": max(results["exponent"].values()), "target": "<= 1.15",
                         "met": max(results["exponent"].values()) <= 1.15},
    }
    if speedups:
        results["targets"]["speedup_min"] = {"value": min(speedups), "target": ">= 5",
                                             "met": min(speedups) >= 5}
    ref = next((r for r in results["l2"] if (r["n"], r["m"], r["T"]) == (4, 2, 1000)), None)
    if ref is not None:  # the 10 ms target is at T = 1000, n = 4, m = 2
        results["targets"]["fit_4x2_T1000_ms"] = {
            "value": 1e3 * ref["fit_s"], "min": 1e3 * ref["fit_min_s"], "target": "<= 10",
            "met": ref["fit_s"] <= 0.010}
    print(json.dumps(results["exponent"]))
    print(json.dumps(results["targets"]))


if __name__ == "__main__":
    main()
