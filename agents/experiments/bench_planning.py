"""Planning at the control rate (issue 45): the default planner on the default learned model.

What it measures and how to run it: docs/experiments.md, section ``bench_planning``.
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from dataclasses import dataclass

import numpy as np
from threadpoolctl import threadpool_limits

from agents.cli import main as command
from agents.experiments.paper_common import machine_info, pyplot, save_figure, write_result


@dataclass(frozen=True)
class Args:
    """Planning at the control rate: ms per MPC step of the default planner per suite task."""

    out: str | None = None
    """write the results to this JSON file"""
    smoke: bool = False
    """tiny CI size: tiny model and planner (the suite's smoke settings) on Reacher, few steps;
    checks the bench runs, times nothing"""
    tasks: tuple[str, ...] = ()
    """suite tasks (empty: every task of scripts/bench_suite.py)"""
    steps: int = 60
    """warm MPC steps per task (an episode's first, cold step is reported apart; an episode that
    ends is followed by the next seed's)"""
    seed: int = 0
    """seed of the env reset, the excitation data and the model's weights"""
    repeats: int = 5
    """timings of each kernel and of the matmul peak; the best is reported"""
    overrides: str = ""
    """agent settings on top of each task's, a JSON object of dotted fields (e.g.
    '{"planner.proposal.samples": 32}'): a planner variant, timed the same way"""
    figure: str | None = None
    """write the ms-per-step figure (PNG) here"""


#: --smoke: the tiny CI size (options given on the command line win)
SMOKE = {"smoke": True, "tasks": ("reacher",), "steps": 3, "repeats": 1}


def main(argv: list[str] | None = None) -> dict:
    """The command line (``--help``: the options)."""
    return command(Args, run, args=argv, outputs=("out", "figure"), presets={"--smoke": SMOKE})


def matmul_peak(dtype: type, size: int = 1024, repeats: int = 5) -> float:
    """GFLOP/s of one ``[size, size] @ [size, size]`` product on one thread (best of
    ``repeats``)."""
    a = np.random.default_rng(0).standard_normal((size, size)).astype(dtype)
    out = np.empty_like(a)
    with threadpool_limits(1):
        np.matmul(a, a, out=out)
        best = min(_seconds(lambda: np.matmul(a, a, out=out)) for _ in range(repeats))
    return 2.0 * size**3 / best / 1e9


def _seconds(f) -> float:
    tic = time.process_time()
    f()
    return time.process_time() - tic


def kernel_rates(frozen, samples: int, horizon: int, repeats: int) -> dict:
    """Time CEM's batched rollout (``samples`` sequences, ``horizon`` steps) and iLQR's
    Jacobians along ``horizon`` steps on ``frozen`` (a folded plan), in its precision.

    FLOPs are the multiply-adds of the products (2 per multiply-add): per row and step
    ``2 K (p W + (L-1) W^2 + W n)`` for ``K`` members of ``L`` layers of ``W`` units, ``p = n+m``
    inputs; the Jacobians add ``2 K n ((L-1) W^2 + W p)`` per step (reverse mode, ``n`` rows)."""
    plan, n, m = frozen._plan, frozen.state_dim, frozen.action_dim
    K, W, L, p = plan.K, plan.W, plan.Wh.shape[0] + 1, n + m
    step_flops = 2.0 * K * (p * W + (L - 1) * W * W + W * n)
    samples = max(samples, frozen.kernel_rows + 1)  # fewer rows run the compiled row kernel
    rng = np.random.default_rng(0)
    x0 = rng.standard_normal(n)
    U = rng.uniform(-1.0, 1.0, (samples, horizon, m))
    X, _ = frozen._rollout_open_loop(x0, U, np.inf)
    jobs = {
        "cem_rollout": (lambda: frozen._rollout_open_loop(x0, U, np.inf),
                        step_flops * samples * horizon),
        "jacobians": (lambda: frozen.jacobians(X[0, :-1], U[0]),
                      (step_flops + 2.0 * K * n * ((L - 1) * W * W + W * p)) * horizon),
    }
    out = {}
    with threadpool_limits(1):
        for name, (f, flops) in jobs.items():
            f()
            best = min(_seconds(f) for _ in range(repeats))
            out[name] = {"gflop": flops / 1e9, "ms": 1e3 * best, "gflops": flops / best / 1e9,
                         "rows": samples if name == "cem_rollout" else horizon}
    return out


def bench_task(name: str, args: Args, peaks: dict[str, float]) -> dict:
    """ms per MPC step, return and kernel rates of the default planner on task ``name``."""
    from agents.experiments import bench_suite

    overrides = {"seed": args.seed, **(json.loads(args.overrides) if args.overrides else {})}
    agent = bench_suite.make_agent(name, overrides, smoke=args.smoke)
    env, cfg = agent.env, agent.config
    agent.model.set_normalization([  # the agent's own excitation: 5 episodes of 50 steps
        agent.collector.rollout(None, episode=i, reset_seed=args.seed + i,
                                signal_seed=args.seed + i, max_steps=50)[1] for i in range(5)])
    agent.freeze()
    frozen = agent.planning_model
    if frozen._plan is None:  # layer norm or mixed depths: no folded planning kernels
        raise ValueError(f"task {name!r}: the model has no folded planning kernels (layer norm "
                         "or mixed depths); bench_planning times the folded ones")
    obs, _ = env.reset(seed=args.seed)
    plan, wall, cpu, cold, returns, start = None, [], [], [], [0.0], True
    while len(wall) < args.steps:  # warm steps; an episode that ends starts a cold one
        tic, cpu_tic = time.perf_counter(), time.process_time()
        action, plan = agent.predict(obs, plan, episode_start=start)
        (cold if start else wall).append(time.perf_counter() - tic)
        if not start:
            cpu.append(time.process_time() - cpu_tic)
        obs, reward, terminated, truncated, _ = env.step(action)
        returns[-1] += float(reward)
        start = terminated or truncated
        if start:
            obs, _ = env.reset(seed=args.seed + len(returns))
            returns.append(0.0)
    period = 1e3 * float(env.unwrapped.dt)
    warm_wall, warm_cpu = 1e3 * np.array(wall), 1e3 * np.array(cpu)
    row = {
        "env_id": env.spec.id if env.spec is not None else None,
        "control_period_ms": period, "model": f"{frozen.n_members}x{frozen._plan.Wh.shape[0] + 1}"
        f"x{frozen._plan.W}", "precision": frozen.precision, "planner": cfg.planner.kind,
        "horizon": cfg.planner.horizon, "replan_every": cfg.planner.replan_every,
        "steps": len(wall), "cold_starts": len(cold), "cold_start_s": float(np.median(cold)),
        "ms_per_step_median": float(np.median(warm_wall)),
        "ms_per_step_p95": float(np.percentile(warm_wall, 95)),
        "cpu_ms_per_step_median": float(np.median(warm_cpu)),
        "cpu_ms_per_step_p95": float(np.percentile(warm_cpu, 95)),
        "returns": returns[:-1] if start else returns,  # not the episode just reset
    }
    row["fraction_of_period"] = row["ms_per_step_median"] / period
    row["cpu_fraction_of_period"] = row["cpu_ms_per_step_median"] / period
    samples = cfg.planner.proposal.samples if cfg.planner.kind == "cem-ilqr" else \
        cfg.planner.cem.samples
    kernels = kernel_rates(frozen, samples, cfg.planner.horizon, args.repeats)
    for k in kernels.values():
        k["fraction_of_peak"] = k["gflops"] / peaks[frozen.precision]
    row["kernels"] = kernels
    env.close()
    row["targets"] = {"median_within_period": row["ms_per_step_median"] <= period,
                      "p95_within_2x_period": row["ms_per_step_p95"] <= 2 * period,
                      "cpu_median_within_period": row["cpu_ms_per_step_median"] <= period,
                      "cpu_p95_within_2x_period": row["cpu_ms_per_step_p95"] <= 2 * period}
    print(f"{name:26s} {row['model']:9s} median {row['ms_per_step_median']:6.1f} ms "
          f"(CPU {row['cpu_ms_per_step_median']:5.1f}), p95 {row['ms_per_step_p95']:6.1f} "
          f"(CPU {row['cpu_ms_per_step_p95']:5.1f}), period {period:.0f} ms; rollout "
          f"{kernels['cem_rollout']['gflops']:.1f} GFLOP/s, Jacobians "
          f"{kernels['jacobians']['gflops']:.1f}; returns {np.round(row['returns'], 2)}",
          flush=True)
    return row


def figure(result: dict, path: str) -> None:
    """Median (bar) and p95 (whisker) CPU ms per MPC step per task, against the control period."""
    plt = pyplot()
    rows = result["tasks"]
    names = list(rows)
    x = np.arange(len(names))
    fig, ax = plt.subplots(figsize=(1.3 * len(names) + 2, 3.6))
    for key, label, shift in (("", "wall", -0.2), ("cpu_", "CPU", 0.2)):
        med = np.array([rows[k][f"{key}ms_per_step_median"] for k in names])
        p95 = np.array([rows[k][f"{key}ms_per_step_p95"] for k in names])
        ax.bar(x + shift, med, 0.38, yerr=[np.zeros_like(med), p95 - med], capsize=3,
               label=f"{label} median (whisker: p95)")
    period = np.array([rows[k]["control_period_ms"] for k in names])
    ax.scatter(x, period, marker="_", s=900, color="k", zorder=3, label="control period")
    ax.set_xticks(x, names, rotation=20, ha="right")
    ax.set_ylabel("ms per MPC step")
    load = result["machine"].get("load_average_end", [None])[0]
    ax.set_title(f"default planner, default model, one thread (load average {load:.1f})"
                 if load is not None else "default planner, default model, one thread")
    ax.legend(fontsize=8)
    save_figure(fig, path)
    print(f"wrote {path}")


def run(args: Args) -> dict:
    """The whole bench; writes ``args.out`` / ``args.figure`` if set and returns the result."""
    import torch

    from agents.experiments import bench_suite

    if args.steps < 1:
        raise ValueError(f"--steps must be >= 1, got {args.steps}")
    if args.overrides and not isinstance(json.loads(args.overrides), dict):
        raise ValueError(f"--overrides must be a JSON object of dotted agent settings, got "
                         f"{args.overrides!r}")
    unknown = sorted(set(args.tasks) - set(bench_suite.TASKS))
    if unknown:
        raise ValueError(f"unknown tasks {unknown}; known: {sorted(bench_suite.TASKS)}")
    torch.set_num_threads(1)
    # one core: numpy's BLAS too (the targets are per core; without this the larger
    # models' products ran on both cores, CPU time twice the wall time)
    threadpool_limits(1, user_api="blas")
    load = os.getloadavg()
    peaks = {name: matmul_peak(dtype, repeats=args.repeats)
             for name, dtype in (("float32", np.float32), ("float64", np.float64))}
    print(f"matmul peak, one thread: float32 {peaks['float32']:.1f} GFLOP/s, float64 "
          f"{peaks['float64']:.1f}", flush=True)
    result = {"args": dataclasses.asdict(args), "matmul_peak_gflops": peaks,
              "tasks": {name: bench_task(name, args, peaks)
                        for name in args.tasks or tuple(bench_suite.TASKS)}}
    result["machine"] = machine_info(load)
    write_result(args.out, result)
    if args.figure:
        figure(result, args.figure)
    return result


if __name__ == "__main__":
    main()
