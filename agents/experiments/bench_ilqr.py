"""Benchmark iLQR and MPC on the two-link arm reach task, against IPOPT and crocoddyl.

What it measures and how to run it: docs/experiments.md, section ``bench_ilqr``.
"""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass

import gymnasium as gym
import numpy as np
import torch

import envs  # noqa: F401  (registers mbtsr/TwoLinkArm-v0)
from agents.cli import main as command
from agents.config import PlannerConfig
from agents.experiments.paper_common import machine_info, write_result
from envs.mujoco_model import HybridDynamics, MujocoDynamics
from mbtsr.costs import quadratic_cost
from mbtsr.episode import run_episode
from mbtsr.ilqr import ILQROptions, ilqr
from mbtsr.ipopt_reference import solve_ipopt
from mbtsr.mpc import MPC, MPCOptions


@dataclass(frozen=True)
class Args:
    """Benchmark of iLQR and MPC on the arm, against IPOPT and crocoddyl."""

    out: str | None = None
    """write the results to this JSON file"""
    smoke: bool = False
    """tiny CI size: the options not given take SMOKE's values"""
    preset: str = "default"
    """arm preset"""
    horizons: str = "100,200"
    """comma-separated iLQR horizons"""
    timing_iterations: int = 15
    """iLQR iterations per timing run (tolerances off)"""
    repeats: int = 3
    """timing runs; the best (least disturbed by other processes) is reported"""
    n_problems: int = 3
    """start/target pairs for the IPOPT comparison"""
    mpc_horizon: int = PlannerConfig().for_task(None, None).horizon
    """MPC horizon (the agent's on a task without termination)"""
    mpc_steps: int = 100
    """control steps per MPC episode"""
    mpc_iterations: int = PlannerConfig().ilqr_iterations
    """iLQR iterations per MPC step (warm-started; the agent's)"""
    mpc_first_iterations: int = PlannerConfig().first_plan_iterations
    """iLQR iterations of the first MPC step (the agent's)"""
    peers: bool = True
    """run crocoddyl side by side (skipped when not installed)"""
    ensemble: str = ""
    """path of a saved ensemble (mbtsr.ensemble.save_model); empty: random 4-member ensemble"""
    seed: int = 0
    """seed of the start/target pairs and of the random ensemble"""
    threads: int = 1
    """torch threads"""
    true_model_only: bool = False
    """run only section 6 (the true-model MPC of every benchmark-suite task)"""
    true_model_steps: int = 20
    """warm-started MPC steps per task and planner in section 6 (after the cold start)"""
    true_model_tasks: tuple[str, ...] = ()
    """section 6's tasks (empty: every task of scripts/bench_suite.py)"""
    true_model_planners: tuple[str, ...] = ("cem-ilqr", "ilqr")
    """section 6's planners"""
    true_model_variants: str = ""
    """section 6: more planner variants, a JSON object of labels to dotted planner settings on
    top of the task's (e.g. '{"h15": {"planner.horizon": 15}}'); their returns are measured too"""
    true_model_returns: tuple[str, ...] = ()
    """section 6: the planners whose return on the suite's evaluation episodes is measured too
    (a whole oracle evaluation per task; the default planner's is in
    docs/results/bench_suite_baselines.json)"""


#: --smoke: the tiny CI size (options given on the command line win)
SMOKE = {"smoke": True, "horizons": "20", "timing_iterations": 2, "repeats": 1, "n_problems": 1,
         "mpc_steps": 5, "peers": False, "true_model_steps": 1, "true_model_tasks": ("arm-far",),
         "true_model_planners": ("ilqr",)}


def main(argv: list[str] | None = None) -> dict:
    """The command line (``--help``: the options)."""
    return command(Args, run, args=argv, outputs=("out",), presets={"--smoke": SMOKE})


def load_ensemble(path: str, seed: int):
    """The ensemble under test and a note on where it came from; without a path the paper's
    4-member ensemble with random weights, normalized on 4 excitation rollouts of the arm (an
    unnormalized random net diverges over 200 steps): its timing is representative, not its
    accuracy."""
    from envs.collect import collect_trajectories
    from mbtsr.ensemble import DynamicsEnsemble, EnsembleConfig, load_model

    if path:
        return load_model(path), f"loaded from {path}"
    model = DynamicsEnsemble(EnsembleConfig(4, 2, seed=seed))
    data_env = gym.make("mbtsr/TwoLinkArm-v0", episode_steps=100)
    model.set_normalization(collect_trajectories(data_env, 4, 100, seed=seed))
    return model, "random weights, 4 members (paper), normalization from 4 excitation rollouts"


def per_iteration(res, wall: float, cpu: float) -> dict:
    """Iterations, status and ms per iteration (wall, CPU and per phase) of an iLQR result."""
    its = max(res.iterations, 1)
    phases = {k: v / its * 1e3 for k, v in res.timings.items() if k != "total"}
    return {"iterations": res.iterations, "status": res.status,
            "ms_per_iteration": wall / its * 1e3, "cpu_ms_per_iteration": cpu / its * 1e3,
            "ms_per_phase_per_iteration": phases}


def time_ilqr(cost, model, x0, T, iterations, repeats):
    """Best-of-``repeats`` ms per iteration with tolerances off (fixed iteration count)."""
    opts = ILQROptions(max_iter=iterations, tol_fun=0.0, tol_grad=0.0)
    solve_ilqr_timed(cost, model, x0, T, opts)  # warm-up
    res, _, cpu = min((solve_ilqr_timed(cost, model, x0, T, opts) for _ in range(repeats)),
                      key=lambda r: r[0].timings["total"] / max(r[0].iterations, 1))
    if res.iterations == 0:
        return {"error": res.message}
    n_jac = 1 + sum(tr["accepted"] for tr in res.trace[:-1])
    return {**per_iteration(res, res.timings["total"], cpu),
            "accepted": int(sum(tr["accepted"] for tr in res.trace)),
            "ms_per_jacobian_call": res.timings["jacobians"] / n_jac * 1e3}


def solve_ilqr_timed(cost, model, x0, T, options, u_min=-1.0, u_max=1.0):
    """``(result, wall seconds, CPU seconds)`` of one iLQR solve from zero controls."""
    tic, cpu = time.perf_counter(), time.process_time()
    res = ilqr(cost, model, x0, np.zeros((T, 2)), u_min=u_min, u_max=u_max, options=options)
    return res, time.perf_counter() - tic, time.process_time() - cpu


def time_to_within(res, wall, threshold):
    """Seconds until the iLQR trace first reaches ``cost <= threshold`` (None if never)."""
    elapsed = wall - sum(tr["time"] for tr in res.trace)  # the setup before the iterations
    for tr in res.trace:
        elapsed += tr["time"]
        if tr["cost"] <= threshold:
            return elapsed
    return None


def peer_comparison(args, problems) -> dict:
    """mbtsr iLQR and crocoddyl BoxFDDP on the same problems, timed in alternating pairs
    (``max(args.repeats, 9)`` pairs, the order flipped every pair, so that both solvers see the
    same machine load): the ratios are medians over the pairs, the solver figures those of the
    least disturbed run (least wall time)."""
    from agents.experiments import peers_crocoddyl as peers_mod

    if not peers_mod.HAVE_CROCODDYL:
        print("crocoddyl: skipped (not installed)")
        return {"skipped": "crocoddyl not installed"}
    x0, target = problems[0]
    out = {}
    for prob in (peers_mod.box_lq_problem(), peers_mod.arm_reach_problem(x0, target)):
        if prob.params is not None:
            out["pinocchio_vs_twin_max_accel_error"] = peers_mod.check_pinocchio_matches_twin(
                prob.params
            )

        def ours(prob=prob):
            return solve_ilqr_timed(prob.cost, prob.model, prob.x0, prob.T, ILQROptions(),
                                    prob.u_min, prob.u_max)

        ours()  # warm-up: builds the cost's mapped functions, loads numba's cache
        peers_mod.solve_crocoddyl(prob)
        pairs = []
        for i in range(max(args.repeats, 9)):
            if i % 2:
                croc, mine = peers_mod.solve_crocoddyl(prob), ours()
            else:
                mine, croc = ours(), peers_mod.solve_crocoddyl(prob)
            pairs.append((mine, croc))
        res, wall, cpu = min((mine for mine, _ in pairs), key=lambda r: r[1])
        croc = min((c for _, c in pairs), key=lambda c: c["wall_time_s"])
        stats = per_iteration(res, wall, cpu)

        def median_ratio(mine_of, croc_of, pairs=pairs):
            return float(np.median([mine_of(m) / croc_of(c) for m, c in pairs]))

        out[prob.name] = {
            "mbtsr": {"cost": res.cost, "wall_time_s": wall, "cpu_time_s": cpu, **stats},
            "crocoddyl": croc,
            "pairs": len(pairs),
            "per_iteration_ratio": median_ratio(
                lambda m: m[1] / max(m[0].iterations, 1), lambda c: c["ms_per_iteration"] / 1e3),
            "time_to_converge_ratio": median_ratio(lambda m: m[1], lambda c: c["wall_time_s"]),
            "per_iteration_ratio_cpu": median_ratio(
                lambda m: m[2] / max(m[0].iterations, 1),
                lambda c: c["cpu_ms_per_iteration"] / 1e3),
            "time_to_converge_ratio_cpu": median_ratio(lambda m: m[2], lambda c: c["cpu_time_s"]),
            "final_cost_rel_diff": abs(res.cost - croc["cost"]) / abs(croc["cost"]),
        }
        r = out[prob.name]
        print(
            f"{prob.name}: mbtsr {stats['ms_per_iteration']:.3f} ms/it x {res.iterations} it, "
            f"cost {res.cost:.10g}; "
            f"crocoddyl {croc['ms_per_iteration']:.3f} ms/it x {croc['iterations']} it, cost "
            f"{croc['cost']:.10g}; median of {len(pairs)} alternating pairs: per-iteration "
            f"ratio {r['per_iteration_ratio']:.2f}, time-to-converge ratio "
            f"{r['time_to_converge_ratio']:.2f} (CPU time: {r['per_iteration_ratio_cpu']:.2f}, "
            f"{r['time_to_converge_ratio_cpu']:.2f}), cost rel diff "
            f"{r['final_cost_rel_diff']:.2e}"
        )
    return out


def cold_compile_seconds() -> float:
    """Seconds for the first-ever call of the numba backward pass (fresh process, empty cache)."""
    code = (
        "import time, numpy as np; t = time.perf_counter();"
        "from mbtsr import _lqr_kernels as k; z = np.zeros;"
        "k.backward_pass(z((3, 2, 2)) + np.eye(2), z((3, 2, 1)) + 1, z((4, 2)), z((3, 1)),"
        " z((4, 2, 2)) + np.eye(2), z((3, 1, 1)) + 1, z((3, 1, 2)), z((3, 1)) - 1,"
        " z((3, 1)) + 1, 0.1, 1, True, k.BOXQP_DEFAULTS); print(time.perf_counter() - t)"
    )
    with tempfile.TemporaryDirectory() as cache:
        env = {**os.environ, "NUMBA_CACHE_DIR": cache}
        out = subprocess.run(
            [sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True
        )
    return float(out.stdout.strip().splitlines()[-1])


def _true_model_variants(args: Args) -> dict[str, dict]:
    """Section 6's planner variants by label: each of ``true_model_planners`` (its kind) and
    each entry of ``true_model_variants`` (a JSON object of labels to dotted planner settings)."""
    variants = {kind: {"planner.kind": kind} for kind in args.true_model_planners}
    if args.true_model_variants:
        extra = json.loads(args.true_model_variants)
        if not isinstance(extra, dict) or not all(isinstance(v, dict) for v in extra.values()):
            raise ValueError("--true-model-variants must be a JSON object of labels to objects of "
                             "planner settings, e.g. '{\"h15\": {\"planner.horizon\": 15}}', "
                             f"got {args.true_model_variants!r}")
        bad = [k for v in extra.values() for k in v if not k.startswith("planner.")]
        if bad:
            raise ValueError(f"--true-model-variants sets only planner.* settings, got {bad}")
        taken = sorted(set(extra) & set(variants))
        if taken:
            raise ValueError(f"--true-model-variants labels {taken} are planner kinds of "
                             "--true-model-planners: choose other labels")
        variants.update(extra)
    unknown = sorted(set(args.true_model_returns) - set(variants))
    if unknown:
        raise ValueError(f"--true-model-returns names {unknown}, which are neither planners nor "
                         f"variants; known: {sorted(variants)}")
    return variants


def check_true_model_variants(args: Args) -> None:
    """Refuse, before any measurement, a variant whose settings the agent's config refuses on
    one of section 6's tasks (an unknown field, a bad value, a setting without effect)."""
    from agents.config import AgentConfig
    from agents.experiments import bench_suite

    variants = _true_model_variants(args)
    for name in args.true_model_tasks or tuple(bench_suite.TASKS):
        if name not in bench_suite.TASKS:
            raise ValueError(f"unknown task {name!r}; known: {sorted(bench_suite.TASKS)}")
        for label, overrides in variants.items():
            try:
                AgentConfig.default({**bench_suite.TASKS[name]["overrides"], **overrides})
            except (ValueError, TypeError) as e:
                raise ValueError(f"true-model variant {label!r} on task {name!r}: {e}") from e


def true_model_planning(args: Args) -> dict:
    """Section 6 (docs/experiments.md, ``bench_ilqr``): ms per MPC step of the scored oracle
    (``agent.evaluator.oracle_policy``) on every suite task per planner variant, cold and warm
    (the timed episode resets with seed 1000), and the return where asked for."""
    from agents.experiments import bench_suite
    from mbtsr.episode import as_policy

    variants = _true_model_variants(args)
    out: dict = {}
    for name in args.true_model_tasks or tuple(bench_suite.TASKS):
        out[name] = {}
        for label, overrides in variants.items():
            agent = bench_suite.make_agent(name, overrides)  # the scored oracle's own planner
            planner, env = agent.config.planner, agent.env
            policy = as_policy(agent.evaluator.oracle_policy(env))
            obs, _ = env.reset(seed=1000)
            times, cpu = [], []  # wall, and this process's CPU time (load-independent work)
            for t in range(args.true_model_steps + 1):
                tic, cpu_tic = time.perf_counter(), time.process_time()
                action = policy(obs, t)
                times.append(time.perf_counter() - tic)
                cpu.append(time.process_time() - cpu_tic)
                obs, _, terminated, truncated, _ = env.step(action)
                if terminated or truncated:
                    break
            env.close()
            row = out[name][label] = {
                "overrides": overrides, "cold_start_s": times[0],
                "ms_per_step_median": 1000 * float(np.median(times[1:])),
                "ms_per_step_max": 1000 * float(np.max(times[1:])),
                "cpu_ms_per_step_median": 1000 * float(np.median(cpu[1:])),
                "cpu_ms_per_step_mean": 1000 * float(np.mean(cpu[1:])),
                "steps": len(times) - 1, "horizon": planner.horizon,
                "replan_every": planner.replan_every}
            if label in args.true_model_returns or label not in args.true_model_planners:
                oracle = bench_suite.task_baselines(name, overrides=overrides)
                row.update({k: oracle[k] for k in (
                    "oracle_return", "oracle_returns", "oracle_seconds", "oracle_cpu_seconds")})
                row["oracle_cpu_ms_per_step_bound"] = 1000 * oracle["oracle_cpu_seconds"] / (
                    agent.spec.episode_steps * len(oracle["oracle_returns"]))
            print(f"true model {name} {label}: cold {times[0]:.2f} s, "
                  f"{row['ms_per_step_median']:.0f} ms/step "
                  f"({row['cpu_ms_per_step_median']:.0f} ms CPU), return "
                  f"{row.get('oracle_return', '-')}", flush=True)
    return out


def vs_ipopt(args: Args, horizons: list[int], problems: list, models: dict, make_cost) -> dict:
    """Section 2: iLQR (default tolerances, ``tol_fun_rel`` 1e-4 and 1e-3) against IPOPT on the
    analytic model per horizon and problem, and iLQR on the true model; medians per setting."""
    labels = {"ilqr_default": ILQROptions(), "ilqr_rel_1e-4": ILQROptions(tol_fun_rel=1e-4),
              "ilqr_rel_1e-3": ILQROptions(tol_fun_rel=1e-3)}
    comparison = {}
    for T in horizons:
        rows = []
        for i, (x0, target) in enumerate(problems):
            cost = make_cost(target)
            ref = solve_ipopt(models["analytic_casadi"].casadi_step, cost, x0, T, -1.0, 1.0)
            row = {"problem": i, "x0": x0.tolist(), "target": target.tolist(),
                   "ipopt": {"cost": ref.cost, "wall_time_s": ref.wall_time,
                             "build_time_s": ref.build_time, "iterations": ref.iterations,
                             "status": ref.status}}
            for label, opts in labels.items():
                res, wall, _ = min((solve_ilqr_timed(cost, models["analytic_casadi_jit"], x0, T,
                                                     opts) for _ in range(args.repeats)),
                                   key=lambda rw: rw[1])
                t1 = time_to_within(res, wall, 1.01 * ref.cost)
                row[label] = {
                    "cost": res.cost, "cost_over_ipopt": res.cost / ref.cost, "wall_time_s": wall,
                    "wall_over_ipopt": wall / ref.wall_time, "iterations": res.iterations,
                    "status": res.status, "time_to_1pct_of_ipopt_s": t1,
                    "time_to_1pct_over_ipopt": None if t1 is None else t1 / ref.wall_time,
                    "all_controls_within_limits": bool(np.all(np.abs(res.U) <= 1.0))}
            res, wall, _ = solve_ilqr_timed(cost, models["true_mujoco"], x0, T,
                                            labels["ilqr_rel_1e-4"])
            row["ilqr_rel_1e-4_true_mujoco"] = {
                "cost_under_mujoco": res.cost, "cost_over_ipopt_analytic": res.cost / ref.cost,
                "wall_time_s": wall, "iterations": res.iterations, "status": res.status}
            rows.append(row)
            print(f"T={T} problem {i}: ipopt {ref.cost:.4f} ({ref.wall_time:.3f} s), " + "; ".join(
                f"{label} {row[label]['cost_over_ipopt']:.5f} x cost, "
                f"{row[label]['wall_over_ipopt']:.2f} x time" for label in labels))

        def median(key, field, rows=rows):
            vals = [r[key][field] for r in rows if r[key][field] is not None]
            return float(np.median(vals)) if vals else None

        fields = ("cost_over_ipopt", "wall_over_ipopt", "iterations", "time_to_1pct_over_ipopt")
        comparison[f"T={T}"] = {"problems": rows, "median": {
            label: {f: median(label, f) for f in fields} for label in labels}}
    return comparison


def mpc_rates(args: Args, env, mpc_models: dict, x0: np.ndarray, target: np.ndarray,
              make_cost) -> dict:
    """Section 4: the MPC real-time factor (control period / compute time per step) and the
    final reach error per model, best of ``args.repeats`` episodes."""
    arm = env.unwrapped
    results = {}
    for name, model in mpc_models.items():
        mpc = MPC(ilqr, make_cost(target), model, horizon=args.mpc_horizon, u_min=-1.0,
                  u_max=1.0, options=MPCOptions(
                      iterations_per_step=args.mpc_iterations,
                      first_step_iterations=args.mpc_first_iterations,
                      optimizer_options=ILQROptions(tol_fun_rel=1e-6)))  # the documented runs'

        def episode(mpc=mpc):
            cpu = time.process_time()
            out = run_episode(env, mpc, seed=args.seed, options={"target": target, "state": x0},
                              observe=lambda obs, info: info["state"])
            return out, np.asarray(mpc.compute_times), time.process_time() - cpu  # incl. env

        best, ct, best_cpu = min((episode() for _ in range(args.repeats)),
                                 key=lambda r: r[1][1:].mean())
        err = best.states[-1] - np.r_[target, 0.0, 0.0]
        results[name] = {
            "real_time_factor_mean": arm.dt / float(ct[1:].mean()),
            "real_time_factor_median": arm.dt / float(np.median(ct[1:])),
            "real_time_factor_incl_first_step": arm.dt / float(ct.mean()),
            "real_time_factor_cpu_time_incl_first_step_and_env": arm.dt * len(ct) / best_cpu,
            "ms_per_step_mean": float(ct[1:].mean() * 1e3), "ms_first_step": float(ct[0] * 1e3),
            "final_angle_error_rad": float(np.abs(err[:2]).max()),
            "final_speed_rad_s": float(np.abs(err[2:]).max()), "episode_cost": best.cost}
        print(f"MPC {name}: RTF {results[name]['real_time_factor_mean']:.2f} (CPU-time RTF "
              f"{results[name]['real_time_factor_cpu_time_incl_first_step_and_env']:.2f}) "
              f"(horizon {args.mpc_horizon}, {args.mpc_iterations} iterations/step)")
    return results


def targets(timing: dict, comparison: dict, peers: dict, mpc_results: dict) -> dict:
    """The issue-13 targets: ``{name: {"value", "target", "met"}}`` (``met`` None without a
    value), printed."""
    ens200 = timing.get("ensemble", {}).get("T=200", {})
    ana200 = timing["analytic_casadi_jit"].get("T=200", {})
    med200 = comparison.get("T=200", {}).get("median", {}).get("ilqr_rel_1e-4", {})
    lq = peers.get("box_lq", {}) if isinstance(peers, dict) else {}

    def rtf(name: str) -> float | None:
        return mpc_results.get(name, {}).get("real_time_factor_mean")

    checks = {
        "ensemble_ms_per_iteration_T200": (ens200.get("ms_per_iteration"), "<=", 5.0),
        "analytic_ms_per_iteration_T200": (ana200.get("ms_per_iteration"), "<=", 5.0),
        "box_lq_per_iteration_over_crocoddyl": (lq.get("per_iteration_ratio"), "<=", 1.5),
        "box_lq_time_to_converge_over_crocoddyl": (lq.get("time_to_converge_ratio"), "<=", 2.0),
        "box_lq_final_cost_rel_diff": (lq.get("final_cost_rel_diff"), "<=", 1e-6),
        "cost_over_ipopt_rel_1e-4_T200": (med200.get("cost_over_ipopt"), "<=", 1.01),
        "wall_over_ipopt_rel_1e-4_T200": (med200.get("wall_over_ipopt"), "<=", 0.2),
        "mpc_rtf_ensemble": (rtf("ensemble"), ">=", 5),
        "mpc_rtf_analytic": (rtf("analytic_casadi_jit"), ">=", 5.0),
        "mpc_rtf_true_mujoco": (rtf("true_mujoco_analytic_jacobians"), ">=", 1.0),
    }
    out = {k: {"value": v, "target": f"{op} {bound}",
               "met": None if v is None else bool(v <= bound if op == "<=" else v >= bound)}
           for k, (v, op, bound) in checks.items()}
    print("targets:")
    for k, t in out.items():
        v = "n/a" if t["value"] is None else f"{t['value']:.4g}"
        print(f"  {k:42s} {v:>10s}  target {t['target']:>8s}  met: {t['met']}")
    return out


def run(args: Args) -> dict:
    """The whole benchmark; writes ``args.out`` if set and returns the results."""
    torch.set_num_threads(args.threads)
    check_true_model_variants(args)  # before sections 1-6, not after them
    if args.true_model_only:
        results = {"args": dataclasses.asdict(args),
                   "true_model_planning": true_model_planning(args), "machine": machine_info()}
        write_result(args.out, results, indent=2)
        return results
    horizons = [int(h) for h in args.horizons.split(",")]
    load_start = os.getloadavg()
    t_start = time.perf_counter()

    # ---- the task: the arm env's own reach cost, a few start/target pairs
    env = gym.make("mbtsr/TwoLinkArm-v0", preset=args.preset, episode_steps=args.mpc_steps)
    arm = env.unwrapped
    rng = np.random.default_rng(args.seed)
    problems = [(np.r_[rng.uniform(-0.3, 0.3, 2), 0.0, 0.0], rng.uniform(-1.3, 1.3, 2))
                for _ in range(args.n_problems)]
    ensemble, ensemble_note = load_ensemble(args.ensemble, args.seed)
    models = {
        "true_mujoco": MujocoDynamics(env),
        "analytic_casadi": arm.analytic_model(),
        "analytic_casadi_jit": arm.analytic_model(jit=True),
        "ensemble": ensemble.freeze(),  # train -> freeze -> plan
    }

    def make_cost(target):
        return quadratic_cost(arm.cost_Q, arm.cost_R, np.r_[target, 0.0, 0.0])

    # ---- 1. ms per iteration
    timing = {}
    x0, target = problems[0]
    for name, model in models.items():
        timing[name] = {}
        for T in horizons:
            row = timing[name][f"T={T}"] = time_ilqr(
                make_cost(target), model, x0, T, args.timing_iterations, args.repeats)
            print(f"{name:20s} T={T}: {row.get('ms_per_iteration', float('nan')):.2f} ms/iter "
                  f"(CPU {row.get('cpu_ms_per_iteration', float('nan')):.2f})")
    # ---- 2. convergence and cost vs IPOPT (analytic model; true model for iterations)
    comparison = vs_ipopt(args, horizons, problems, models, make_cost)
    # ---- 3. peers: crocoddyl BoxFDDP side by side
    peers = peer_comparison(args, problems) if args.peers else {"skipped": "--peers false"}
    # ---- 4. MPC real-time factor at the agent's default horizon
    mpc_results = mpc_rates(args, env, {
        "ensemble": models["ensemble"],
        "analytic_casadi": models["analytic_casadi"],
        "analytic_casadi_jit": models["analytic_casadi_jit"],
        "true_mujoco_analytic_jacobians": HybridDynamics(models["true_mujoco"],
                                                         models["analytic_casadi_jit"]),
        "true_mujoco_fd_jacobians": models["true_mujoco"],
    }, x0, target, make_cost)
    # ---- 5. numba: the first-ever compile of the backward pass (fresh process, empty cache)
    compile_s = cold_compile_seconds()
    print(f"numba backward pass: cold compile {compile_s:.1f} s")

    results = {
        "args": dataclasses.asdict(args),
        "ensemble": ensemble_note,
        "control_period_s": arm.dt,
        "ms_per_iteration": timing,
        "vs_ipopt_analytic_model": comparison,
        "peers": peers,
        "mpc": mpc_results,
        "mpc_true_mujoco_uses": "MuJoCo steps with the analytic twin's exact (JIT-compiled) "
        "Jacobians (HybridDynamics); true_mujoco_fd_jacobians: MuJoCo's chained mjd_transitionFD",
        "analytic_model_in_targets": "analytic_casadi_jit (TwoLinkArmCasadi(jit=True)); "
        "analytic_casadi is the uncompiled CasADi VM, for reference",
        "numba_cold_compile_s": compile_s,
        # ---- 6. the true-model MPC of the suite's tasks
        "true_model_planning": true_model_planning(args),
        "targets": targets(timing, comparison, peers, mpc_results),
        "machine": machine_info(load_start),
    }
    results["total_time_s"] = time.perf_counter() - t_start
    write_result(args.out, results, indent=2)
    return results

if __name__ == "__main__":
    main()
