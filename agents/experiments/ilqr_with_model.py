"""Plug a dynamics model into iLQR: plan a reach on the two-link arm and run it in the env.

What it measures and how to run it: docs/experiments.md, section ``ilqr_with_model``.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import gymnasium as gym
import numpy as np

import envs  # noqa: F401  (registers mbtsr/TwoLinkArm-v0)
from agents.cli import main as command
from agents.experiments.paper_common import pyplot, save_figure
from mbtsr.costs import quadratic_cost
from mbtsr.episode import run_episode
from mbtsr.ilqr import ILQROptions, ilqr
from mbtsr.io import write_json_atomic
from mbtsr.mpc import MPC, MPCOptions

plt = pyplot()


@dataclass(frozen=True)
class Args:
    """Plan a reach of the two-link arm with iLQR on a chosen model and replay it (open loop and
    MPC) in the real env."""

    out: str = "runs/ilqr_with_model"
    """output directory"""
    smoke: bool = False
    """tiny CI size: the options not given take SMOKE's values"""
    model: str = "true"
    """true | analytic | ltv | PATH of a saved ensemble"""
    seed: int = 0
    """reset seed (start state and, without --target, the target)"""
    target: str = ""
    """target joint angles "q1,q2" [rad]; empty: drawn by the env"""
    preset: Literal["default", "paper"] = "default"
    """arm preset"""
    T: int = 100
    """planning horizon and episode length [steps]"""
    max_iter: int = 100
    """iLQR iterations of the open-loop plan"""
    mpc_horizon: int = 50
    """MPC horizon [steps]"""
    mpc_iterations: int = 2
    """iLQR iterations per MPC step"""
    ltv_trajectories: int = 20
    """excitation rollouts for --model ltv"""
    ltv_lam: float = 10.0
    """LTV smoothness weight lambda for --model ltv"""


#: --smoke: the tiny CI size (options given on the command line win)
SMOKE = {"smoke": True, "T": 20, "max_iter": 5, "mpc_horizon": 10, "mpc_iterations": 1,
         "ltv_trajectories": 3, "out": "runs/smoke/ilqr_with_model"}


def main(argv: list[str] | None = None) -> dict:
    """The command line (``--help``: the options)."""
    return command(Args, run, args=argv, folders=("out",), presets={"--smoke": SMOKE})


def episode_cost(X: np.ndarray, U: np.ndarray, goal, Q, R) -> np.ndarray:
    """Per-step env cost ``(x_{t+1} - g)^T Q (x_{t+1} - g) + u_t^T R u_t`` -> ``[T]``."""
    E = X[1:] - goal
    return np.einsum("ti,ij,tj->t", E, Q, E) + np.einsum("ti,ij,tj->t", U, R, U)


def build_model(args: Args, arm: Any, options: dict) -> tuple[Any, str]:
    """The planning model ``--model`` names, and its name: the arm's true or analytic model,
    an LTV fit on excitation rollouts of this episode, or a saved ensemble."""
    if args.model == "true":
        return arm.dynamics_model(), "true"
    if args.model == "analytic":
        return arm.analytic_model(), "analytic"
    if args.model == "ltv":
        from envs.collect import collect_trajectories
        from mbtsr.ltv import fit_ltv

        steps = args.T + args.mpc_horizon
        data_env = gym.make("mbtsr/TwoLinkArm-v0", preset=args.preset, episode_steps=steps)
        trajs = collect_trajectories(data_env, args.ltv_trajectories, steps, seed=args.seed,
                                     reset_options=options)
        return fit_ltv(trajs, args.ltv_lam), "ltv"
    from mbtsr.ensemble import load_model

    if not Path(args.model).is_file():
        raise ValueError(f"--model must be true, analytic, ltv or the path of a saved "
                         f"ensemble; there is no file at {args.model}")
    return load_model(args.model).freeze(), Path(args.model).stem


def plot_runs(runs: dict[str, tuple], t: np.ndarray, target: np.ndarray, title: str,
              png: Path) -> None:
    """Planned vs executed: angles, velocities, the first action and the cumulative cost of
    each ``label -> (X [T+1, 4], U [T, 2], cost [T])`` over times ``t [T+1]``."""
    fig, axes = plt.subplots(2, 3, figsize=(14, 7), sharex=True)
    for label, (X, U, c) in runs.items():
        style = "--" if label.startswith("planned") else "-"
        for i in range(2):
            axes[0, i].plot(t, X[:, i], style, label=label)
            axes[1, i].plot(t, X[:, 2 + i], style, label=label)
        axes[0, 2].step(t[:-1], U[:, 0], style, where="post", label=label)
        axes[1, 2].plot(t[1:], np.cumsum(c), style, label=label)
    for i in range(2):
        axes[0, i].axhline(target[i], color="k", lw=0.8, ls=":")
        axes[0, i].set_ylabel(f"q{i + 1} [rad]")
        axes[1, i].set_ylabel(f"q{i + 1} dot [rad/s]")
    axes[0, 2].set_ylabel("a1 (normalized)")
    axes[1, 2].set_ylabel("cumulative cost")
    for ax in axes[1]:
        ax.set_xlabel("time [s]")
    axes[0, 0].legend(fontsize=8)
    fig.suptitle(title)
    save_figure(fig, png, dpi=100)


def run(args: Args) -> dict:
    """Plan with the chosen model, replay in the real arm; write the figure and the JSON."""
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    env = gym.make("mbtsr/TwoLinkArm-v0", preset=args.preset, episode_steps=args.T)
    arm = env.unwrapped

    # ---- the episode: start state and target
    options = {}
    if args.target:
        options["target"] = [float(v) for v in args.target.split(",")]
    _, info = env.reset(seed=args.seed, options=options or None)
    x0, target = info["state"], info["target"]
    options = {"target": target, "state": x0}  # replay exactly this episode below
    goal = np.r_[target, 0.0, 0.0]
    Q, R = arm.cost_Q, arm.cost_R
    cost = quadratic_cost(Q, R)  # the goal is a parameter: params=cost.reference(goal)
    print(f"start {np.round(x0, 3).tolist()}, target {np.round(target, 3).tolist()}")

    tic = time.perf_counter()
    model, model_name = build_model(args, arm, options)
    print(f"model: {model_name} ({time.perf_counter() - tic:.2f} s to build)")

    # ---- 1. plan with iLQR on the model
    res = ilqr(cost, model, x0, np.zeros((args.T, 2)), u_min=-1.0, u_max=1.0,
               params=cost.reference(goal),
               options=ILQROptions(max_iter=args.max_iter, tol_fun_rel=1e-6))
    print(f"iLQR: {res.status} after {res.iterations} iterations ({res.message}), "
          f"{res.timings['total']:.2f} s, planned cost {res.cost:.4f}")

    # ---- 2./3. execute the plan in the env: open loop, and with the plan's feedback gains;
    # ---- 4. MPC on the model in the env
    mpc = MPC(ilqr, cost, model, horizon=args.mpc_horizon, u_min=-1.0, u_max=1.0,
              options=MPCOptions(iterations_per_step=args.mpc_iterations, first_step_iterations=30,
                                 optimizer_options=ILQROptions(tol_fun_rel=1e-6)),  # as documented
              params=cost.reference(goal))
    policies = {"open_loop": lambda x, t: res.U[t],
                "plan_with_feedback": lambda x, t: res.U[t] + res.K[t] @ (x - res.X[t]),
                "mpc": mpc}
    # ---- summary: (states, actions, per-step cost) of the plan and of the three executions
    runs = {"planned": (res.X, res.U, episode_cost(res.X, res.U, goal, Q, R))}
    for name, policy in policies.items():
        rec = run_episode(env, policy, seed=args.seed, options=options, max_steps=args.T,
                          observe=lambda obs, info: info["state"])
        runs[name] = (rec.states, rec.actions, -rec.rewards)
    compute_times = np.asarray(mpc.compute_times)
    summary = {
        "args": dataclasses.asdict(args),
        "x0": x0.tolist(),
        "target": target.tolist(),
        "ilqr": {
            "status": res.status,
            "iterations": res.iterations,
            "wall_time_s": res.timings["total"],
        },
        "episode_cost": {("planned_under_model" if k == "planned" else k): float(c.sum())
                         for k, (_, _, c) in runs.items()},
        "final_angle_error_rad": {k: float(np.abs(X[-1, :2] - target).max())
                                  for k, (X, _, _) in runs.items()},
        "mpc_ms_per_step": float(compute_times[1:].mean() * 1e3),
        "mpc_real_time_factor": float(arm.dt / compute_times[1:].mean()),
    }
    for key in ("episode_cost", "final_angle_error_rad"):
        print(key + ": " + ", ".join(f"{k} {v:.4f}" for k, v in summary[key].items()))
    ms, rtf = summary["mpc_ms_per_step"], summary["mpc_real_time_factor"]
    print(f"MPC: {ms:.1f} ms/step, real-time factor {rtf:.2f}")

    png = out_dir / f"ilqr_with_model_{model_name}.png"
    labels = {"planned": "planned (model)", "open_loop": "open loop (env)",
              "plan_with_feedback": "plan + feedback (env)", "mpc": "MPC (env)"}
    plot_runs({labels[k]: v for k, v in runs.items()}, np.arange(args.T + 1) * arm.dt, target,
              f"iLQR with model '{model_name}': target {np.round(target, 2).tolist()}", png)
    write_json_atomic(out_dir / f"ilqr_with_model_{model_name}.json", summary, indent=2)
    print(f"wrote {png}")
    return summary


if __name__ == "__main__":
    main()
