"""Benchmark the two-link arm env: wrapper overhead and Jacobian cost.

What it measures and how to run it: docs/experiments.md, section ``bench_env``.
"""

from __future__ import annotations

import dataclasses
import json
import time
from dataclasses import dataclass
from typing import Literal

import gymnasium as gym
import mujoco
import numpy as np

import envs  # noqa: F401  (registers the envs, selects MUJOCO_GL before mujoco loads)
from agents.cli import main as command
from agents.experiments.paper_common import machine_info, write_result


@dataclass(frozen=True)
class Args:
    """Benchmark the two-link arm env: wrapper overhead and Jacobian cost."""

    out: str | None = None
    """write the results to this JSON file"""
    smoke: bool = False
    """tiny CI size: the options not given take SMOKE's values"""
    preset: Literal["default", "paper"] = "default"
    """arm preset (envs.two_link_arm_model.PRESETS)"""
    n_steps: int = 20000
    """control steps per timing run"""
    n_linearize: int = 300
    """linearize calls per timing run"""
    repeats: int = 5
    """timing runs; the best (least disturbed by other processes) is reported"""
    seed: int = 0
    """seed of the random actions"""


#: --smoke: the tiny CI size (options given on the command line win)
SMOKE = {"smoke": True, "n_steps": 500, "n_linearize": 10, "repeats": 1}


def main(argv: list[str] | None = None) -> dict:
    """The command line (``--help``: the options)."""
    return command(Args, run, args=argv, outputs=("out",), presets={"--smoke": SMOKE})


def best_rate(fn, count: int, repeats: int) -> float:
    """Operations per second of ``fn()`` (which does ``count`` operations), best of ``repeats``."""
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return count / best


def run(args: Args) -> dict:
    """Run the benchmark; print and return the results (and write ``args.out``)."""
    rng = np.random.default_rng(args.seed)
    actions = rng.uniform(-1, 1, size=(args.n_steps, 2)).astype(np.float32)

    # 1. the env through gymnasium.make; episodes of n_steps so that no reset is timed
    env = gym.make("mbtsr/TwoLinkArm-v0", preset=args.preset, episode_steps=args.n_steps + 1)
    base = env.unwrapped
    frame_skip = base.frame_skip

    def run_env() -> None:
        env.reset(seed=args.seed)
        for a in actions:
            env.step(a)

    env_steps_per_s = best_rate(run_env, args.n_steps, args.repeats)

    # 2. raw mj_step on the same compiled model, separate MjData
    model = base.model
    data = mujoco.MjData(model)
    ctrl = actions.astype(np.float64)

    def run_raw(calls: int) -> None:
        """The episode's frame_skip substeps per control step in ``calls`` mj_step calls."""
        mujoco.mj_resetData(model, data)
        for a in ctrl:
            data.ctrl[:] = a
            for _ in range(calls):
                mujoco.mj_step(model, data, nstep=frame_skip // calls)

    raw_control_steps_per_s = best_rate(lambda: run_raw(1), args.n_steps, args.repeats)
    raw_single_control_steps_per_s = best_rate(lambda: run_raw(frame_skip), args.n_steps,
                                               args.repeats)

    # 3. Jacobians
    env.reset(seed=args.seed)
    xs = np.column_stack(
        [rng.uniform(-2, 2, (args.n_linearize, 2)), rng.uniform(-3, 3, (args.n_linearize, 2))]
    )
    us = rng.uniform(-1, 1, (args.n_linearize, 2))

    def run_linearize() -> None:
        for x, u in zip(xs, us):
            base.linearize(x, u)

    linearize_per_s = best_rate(run_linearize, args.n_linearize, args.repeats)
    traj_x, traj_u = xs[:100], us[:100]
    linearize_traj_100_per_s = best_rate(
        lambda: base.linearize_trajectory(traj_x, traj_u), 1, args.repeats
    )
    analytic = base.analytic_model()
    analytic.jacobians(traj_x, traj_u)  # build the mapped function once
    analytic_jac_100_per_s = best_rate(lambda: analytic.jacobians(traj_x, traj_u), 1, args.repeats)
    scratch = mujoco.MjData(model)
    fd_a, fd_b = np.zeros((4, 4)), np.zeros((4, 2))

    def run_fd() -> None:
        for _ in range(1000):
            mujoco.mjd_transitionFD(model, scratch, 1e-6, True, fd_a, fd_b, None, None)

    fd_calls_per_s = best_rate(run_fd, 1000, args.repeats)

    results = {
        "preset": args.preset,
        "frame_skip": frame_skip,
        "dt": base.dt,
        "env_steps_per_s_gymnasium_make": env_steps_per_s,
        "raw_mj_step_control_steps_per_s": raw_control_steps_per_s,
        "raw_mj_step_single_calls_control_steps_per_s": raw_single_control_steps_per_s,
        "raw_mj_step_substeps_per_s": raw_control_steps_per_s * frame_skip,
        "ratio_env_vs_raw_per_control_step": raw_control_steps_per_s / env_steps_per_s,
        "ratio_target": 3.0,
        "ratio_ok": bool(raw_control_steps_per_s / env_steps_per_s <= 3.0),
        "linearize_calls_per_s": linearize_per_s,
        "linearize_trajectory_T100_per_s": linearize_traj_100_per_s,
        "analytic_casadi_jacobians_T100_per_s": analytic_jac_100_per_s,
        "mjd_transitionFD_centered_calls_per_s": fd_calls_per_s,
        "config": dataclasses.asdict(args),
        "machine": machine_info(mujoco=mujoco.__version__, gymnasium=gym.__version__,
                                note="best of repeats; 2 shared cores, timings noisy"),
    }
    env.close()
    print(json.dumps(results, indent=2))
    write_result(args.out, results, indent=2)
    return results


if __name__ == "__main__":
    main()
