"""Collect excitation data from the two-link arm and plot it.

What it measures and how to run it: docs/experiments.md, section ``collect_excitation``.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import gymnasium as gym
import numpy as np

import envs  # noqa: F401  (registers the envs; sets MUJOCO_GL=egl before mujoco is loaded)
from agents.cli import main as command
from agents.experiments.paper_common import pyplot, save_figure
from envs.collect import collect_trajectories, default_input_kwargs
from envs.rendering import render_episode, save_png_strip
from mbtsr.io import write_json_atomic
from mbtsr.trajectory import save_trajectories

plt = pyplot()


@dataclass(frozen=True)
class Args:
    """Collect excitation trajectories of the two-link arm (the paper's robot data)."""

    out: str = "runs/excitation"
    """output directory"""
    smoke: bool = False
    """tiny CI size: the options not given take SMOKE's values"""
    seed: int = 0
    """master seed (same seed, same data)"""
    n_traj: int = 5
    """number of trajectories"""
    T: int = 200  # noqa: N815 - the paper's symbol
    """steps per trajectory (4 s at dt 0.02, the paper's N)"""
    preset: Literal["default", "paper"] = "default"
    """arm preset: default or paper"""
    input: Literal["filtered_gaussian", "multisine"] = "filtered_gaussian"
    """filtered_gaussian or multisine"""
    reject_abs_q: float = 0.9 * math.pi
    """redraw trajectories reaching |q| >= this (<= 0: keep all)"""
    render: bool = True
    """render a PNG strip of the first trajectory"""


#: --smoke: the tiny CI size (options given on the command line win)
SMOKE = {"smoke": True, "n_traj": 2, "T": 50, "render": False,
         "out": "runs/smoke/excitation"}


def main(argv: list[str] | None = None) -> dict:
    """The command line (``--help``: the options)."""
    return command(Args, run, args=argv, folders=("out",), presets={"--smoke": SMOKE})


def run(args: Args) -> dict:
    """Collect, save, plot and render; return the configuration written to config.json."""
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()

    # 1. collect
    env = gym.make("mbtsr/TwoLinkArm-v0", preset=args.preset, episode_steps=args.T)
    trajs = collect_trajectories(
        env,
        args.n_traj,
        args.T,
        input=args.input,
        seed=args.seed,
        reject_abs_q=args.reject_abs_q if args.reject_abs_q > 0 else None,
    )
    attempts = trajs[-1].meta["attempt"] + 1

    # 2. save data and the resolved configuration
    save_trajectories(out / "trajectories.npz", trajs)
    config = {
        "args": dataclasses.asdict(args),
        "env_id": "mbtsr/TwoLinkArm-v0",
        "arm_params": env.unwrapped.params.to_dict(),
        "input_kwargs": default_input_kwargs(env, args.input),
        "attempts": attempts,
        "trajectories": [t.meta for t in trajs],
    }
    write_json_atomic(out / "config.json", config, indent=2)

    # 3. plot states and inputs
    time_axis = np.arange(args.T + 1) * trajs[0].dt
    fig, axes = plt.subplots(3, 2, figsize=(10, 7), sharex=True)
    labels = [("q1 [rad]", "q2 [rad]"), ("q1dot [rad/s]", "q2dot [rad/s]"), ("u1", "u2")]
    for traj in trajs:
        series = (traj.x[:, :2], traj.x[:, 2:], traj.u)
        for row, data in enumerate(series):
            for j in range(2):
                t = time_axis if row < 2 else time_axis[:-1]
                axes[row, j].plot(t, data[:, j], lw=0.9)
    for row in range(3):
        for j in range(2):
            axes[row, j].set_ylabel(labels[row][j])
            axes[row, j].grid(alpha=0.3)
    for j in range(2):
        axes[2, j].set_xlabel("time [s]")
        axes[0, j].axhline(args.reject_abs_q, color="k", ls=":", lw=0.8)
        axes[0, j].axhline(-args.reject_abs_q, color="k", ls=":", lw=0.8)
    fig.suptitle(
        f"{args.n_traj} excitation trajectories ({args.input}, preset {args.preset}; "
        f"u = normalized torque, {attempts - args.n_traj} rejected)"
    )
    save_figure(fig, out / "excitation.png")

    # 4. render a few frames of the first trajectory (replayed from its recorded seed and inputs)
    if args.render:
        render_env = gym.make(
            "mbtsr/TwoLinkArm-v0",
            preset=args.preset,
            episode_steps=args.T,
            render_mode="rgb_array",
            width=240,
            height=180,
        )
        frames = render_episode(render_env, trajs[0].u, seed=trajs[0].meta["reset_seed"])
        save_png_strip(frames, out / "arm.png")  # 6 evenly spaced frames
        render_env.close()

    print(
        f"{args.n_traj} trajectories x {args.T} steps ({attempts} rollouts) -> {out}/ "
        f"[trajectories.npz, config.json, excitation.png{', arm.png' if args.render else ''}] "
        f"in {time.perf_counter() - start:.1f} s"
    )
    return config


if __name__ == "__main__":
    main()
