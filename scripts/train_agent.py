"""Train the Algorithm-1 agent (JacProp model learning + iLQR MPC) on the two-link arm.

The project's main job (Bagge Carlson et al., "Tangent-Space Regularization for Neural-Network
Models of Dynamical Systems", arXiv:1806.09919, Algorithm 1 in an episodic loop)::

    python scripts/train_agent.py                       # embedded defaults, mbtsr/TwoLinkArm-v0
    python scripts/train_agent.py --seed 3 --regularization exact --json bench.json
    python scripts/train_agent.py --run-dir runs/x --resume   # continue a killed run exactly

Every field of :class:`agents.config.AgentConfig` is a flag (``--epochs-per-episode 100``,
``--formulation f``, ``--no-tensorboard`` ...). The run folder receives ``config.json``,
``episodes.csv``, ``checkpoint.pt`` (resume), ``model.pt`` (the learned ensemble,
:func:`mbtsr.ensemble.load_model`), ``data.npz`` (all trajectories), ``tb/`` (TensorBoard),
``learning_curve.png``, ``final_reach.png`` and ``summary.json``. ``--json PATH`` writes the
benchmark numbers: episodes_to_solve, env_steps_to_solve, the final cost ratio to the oracle and
the wall seconds per phase.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # run from anywhere; the repo holds envs/ and agents/
    sys.path.insert(0, str(REPO))
os.environ.setdefault("MUJOCO_GL", "egl")  # headless rendering, before mujoco is imported


@dataclass(frozen=True)
class Args:
    """Script-level arguments (the agent's own settings are the AgentConfig flags)."""

    env_id: str = "mbtsr/TwoLinkArm-v0"
    episodes: int = 10  # total training episodes of the run (a resumed run counts the done ones)
    run_dir: str = ""  # default: runs/train_agent/<env>_<regularization>_<formulation>_seed<seed>
    # (a fresh default run that finds a finished one there adds a suffix _1, _2, ...)
    resume: bool = False  # continue from <run_dir>/checkpoint.pt
    json: str = ""  # write the benchmark JSON here
    plots: bool = True  # learning curve and final-reach PNGs
    summary_table: bool = True  # print the rich summary table


#: AgentConfig values this script uses unless a flag says otherwise: the main job shares the
#: (deterministic) oracle costs between runs
SCRIPT_AGENT_DEFAULTS = {
    "oracle_cache_dir": str(REPO / "runs" / "oracle_cache"),
}


def build_parser() -> argparse.ArgumentParser:
    from agents.config import AgentConfig

    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    agent_fields = {f.name for f in dataclasses.fields(AgentConfig)}
    defaults = AgentConfig()
    for owner, fields in (("script", dataclasses.fields(Args)),
                          ("agent", dataclasses.fields(AgentConfig))):
        group = parser.add_argument_group(owner)
        for f in fields:
            if owner == "agent" and f.name == "run_dir":
                continue  # the script's --run-dir
            if owner == "script" and f.name in agent_fields and f.name != "run_dir":
                continue
            flag = "--" + f.name.replace("_", "-")
            default = (f.default if owner == "script"
                       else SCRIPT_AGENT_DEFAULTS.get(f.name, getattr(defaults, f.name)))
            if isinstance(default, bool):
                group.add_argument(flag, action=argparse.BooleanOptionalAction, default=None,
                                   help=f"(default {default})")
            elif isinstance(default, tuple):
                group.add_argument(flag, nargs="+", default=None, help=f"(default {default})")
            elif f.name == "ltv_lambda":
                group.add_argument(flag, type=_float_or_auto, default=None,
                                   help=f"a number or 'auto' (default {default})")
            elif f.name == "episode_steps":
                group.add_argument(flag, type=int, default=None, help="(default: the env's)")
            elif default is None or f.name == "oracle_cache_dir":
                group.add_argument(flag, type=str, default=None,
                                   help=f"('none' for None; default {default})")
            else:
                group.add_argument(flag, type=type(default), default=None,
                                   help=f"(default {default})")
    return parser


def _float_or_auto(text: str) -> float | str:
    return text if text == "auto" else float(text)


def parse(argv: list[str] | None = None):
    """``(args, agent_overrides)``: the script's Args and the AgentConfig fields the user set."""
    from agents.config import AgentConfig

    parser = build_parser()
    ns = {k: v for k, v in vars(parser.parse_args(argv)).items() if v is not None}
    script = {f.name for f in dataclasses.fields(Args)}
    args = Args(**{k: v for k, v in ns.items() if k in script})
    overrides = {**SCRIPT_AGENT_DEFAULTS,
                 **{k: v for k, v in ns.items() if k not in script}}
    for k in ("oracle_cache_dir",):
        if str(overrides.get(k)).lower() in ("", "none"):
            overrides[k] = None
    if "activations" in overrides:
        overrides["activations"] = tuple(overrides["activations"])
    try:
        AgentConfig(**overrides)  # fail fast with the config's own message on a bad flag
    except (TypeError, ValueError) as err:
        parser.error(str(err))
    if args.episodes < 1:
        parser.error(f"--episodes must be >= 1, got {args.episodes}")
    return args, overrides


def main(argv: list[str] | None = None) -> dict:
    import numpy as np

    from agents.checkpoint import CheckpointError, atomic_write_text, check_same
    from agents.config import AgentConfig
    from agents.evaluation import make_env
    from agents.jacprop_agent import JacPropAgent

    # 1. arguments --------------------------------------------------------------------------
    args, overrides = parse(argv)
    cfg_preview = AgentConfig(**overrides)
    run_dir = Path(args.run_dir or (
        REPO / "runs" / "train_agent" /
        f"{args.env_id.replace('/', '_')}_{cfg_preview.regularization}_"
        f"{cfg_preview.formulation}_seed{cfg_preview.seed}"))
    if not args.run_dir and not args.resume:  # a fresh default run never clobbers an old one
        base, k = run_dir, 1
        while (run_dir / "checkpoint.pt").exists():
            run_dir, k = base.with_name(f"{base.name}_{k}"), k + 1
    checkpoint = run_dir / "checkpoint.pt"
    if args.resume and not checkpoint.is_file():
        raise SystemExit(f"--resume: no checkpoint at {checkpoint}")
    if not args.resume and checkpoint.exists():
        raise SystemExit(
            f"{checkpoint} exists: pass --resume to continue it or choose another --run-dir"
        )

    # 2. the env and the agent (fresh, or restored from the checkpoint) ----------------------
    env, _ = make_env(args.env_id, render_mode="rgb_array") if cfg_preview.video else \
        make_env(args.env_id)
    if args.resume:
        try:  # a damaged checkpoint, another env (dt, preset, ...) or a changed flag: one line
            agent = JacPropAgent.load(checkpoint, env=env, run_dir=str(run_dir))
            saved = agent.config.to_dict()
            changed = {k: v for k, v in overrides.items()
                       if k in saved and SCRIPT_AGENT_DEFAULTS.get(k, saved[k]) != v}
            check_same(json.loads(json.dumps({k: saved[k] for k in changed}, default=str)),
                       json.loads(json.dumps(changed, default=str)), what="config",
                       path=checkpoint)
        except CheckpointError as err:
            raise SystemExit(f"--resume: {err}") from None
        print(f"resuming {run_dir} after episode {agent.episodes_done}")
    else:
        agent = JacPropAgent(env, AgentConfig(**{**overrides, "run_dir": str(run_dir)}))
    atomic_write_text(run_dir / "config.json", json.dumps(
        {"script": dataclasses.asdict(args), "command": " ".join(sys.argv),
         **agent.resolved_config()}, indent=2, default=str))

    # 3. Algorithm 1: episodes of rollout -> LTV fit -> regularised model update -> planning --
    remaining = max(0, args.episodes - agent.episodes_done)
    t0 = time.perf_counter()
    agent.learn(remaining, progress_bar=agent.config.progress)
    wall = time.perf_counter() - t0

    # 4. results: summary, benchmark JSON, figures --------------------------------------------
    summary = agent.summary()
    summary["wall_seconds_this_process"] = wall
    summary["run_dir"] = str(run_dir)
    atomic_write_text(run_dir / "summary.json", json.dumps(summary, indent=2))
    if args.json:
        atomic_write_text(args.json, json.dumps(summary, indent=2))
    if args.plots:
        plot_learning_curve(agent, run_dir / "learning_curve.png")
        plot_final_reach(agent, env, run_dir / "final_reach.png")
    if args.summary_table:
        print_summary(agent, summary)
    env.close()
    _ = np  # numpy is imported for the plotting helpers' side
    return summary


def plot_learning_curve(agent, path: Path) -> None:
    """Episode cost (training rollouts) and evaluation cost vs episodes, with the oracle."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    rows = agent.logger_rows
    ep = np.array([r["episode"] for r in rows]) + 1
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    ax = axes[0]
    ax.semilogy(ep, [r["episode_cost"] for r in rows], "o-", label="training rollout")
    ev = np.array([np.nan if r.get("eval_cost") is None else r["eval_cost"] for r in rows])
    if np.any(np.isfinite(ev)):
        ax.semilogy(ep, ev, "s-", label="evaluation (mean of targets)")
    oracle = agent.oracle_mean
    if oracle is not None:
        ax.axhline(oracle, color="k", ls="--", label="oracle (true-model MPC)")
        ax.axhline(agent.config.solved_ratio * oracle, color="g", ls=":", label="solved")
    ax.set_xlabel("episode")
    ax.set_ylabel("episode cost")
    ax.legend(fontsize=8)
    ax = axes[1]
    for key, label in (("one_step_rms", "one-step RMS (new data)"),
                       ("jacobian_error", "Jacobian error (new data)")):
        v = np.array([np.nan if r.get(key) is None else r[key] for r in rows], dtype=float)
        if np.any(np.isfinite(v)):
            ax.semilogy(ep, v, "o-", label=label)
    ax.set_xlabel("episode")
    ax.set_title("model error before the update")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_final_reach(agent, env, path: Path) -> None:
    """One evaluation reach of the final agent (and of the oracle) against its target."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from agents.evaluation import oracle_policy, run_episode

    target, seed = agent.evaluation_problem(0)
    options = None if target is None else {"target": target}
    rec = agent.rollout_policy(env, seed=seed, options=options)
    curves = [("agent", rec)]
    if hasattr(env.unwrapped, "dynamics_model") and target is not None:
        oracle = oracle_policy(env, agent.config.horizon, iterations=agent.config.ilqr_iterations,
                               first_plan_iterations=agent.config.first_plan_iterations,
                               terminal_weight=agent.config.terminal_weight)
        state = {"U": None}

        def act(obs, t):
            a, state["U"] = oracle.predict(obs, state["U"], episode_start=t == 0)
            return a

        curves.append(("oracle", run_episode(env, act, seed=seed, options=options)))
    dt = agent.spec.dt or 1.0
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    for name, r in curves:
        t = np.arange(r.obs.shape[0]) * dt
        x = agent.state_map.state(r.obs)
        k = min(2, x.shape[1])
        for i in range(k):
            axes[0].plot(t, x[:, i], ls="-" if name == "agent" else "--",
                         label=f"{name}: state {i} (cost {r.cost:.3g})" if i == 0 else
                         f"{name}: state {i}")
        ta = np.arange(r.actions.shape[0]) * dt
        for i in range(r.actions.shape[1]):
            axes[1].plot(ta, r.actions[:, i], ls="-" if name == "agent" else "--",
                         label=f"{name}: action {i}")
    if target is not None:
        for i, v in enumerate(np.atleast_1d(target)):
            axes[0].axhline(v, color="k", lw=0.8, ls=":", label="target" if i == 0 else None)
    axes[0].set_xlabel("time [s]" if agent.spec.dt else "step")
    axes[0].set_title("final reach vs target")
    axes[0].legend(fontsize=7)
    axes[1].set_xlabel("time [s]" if agent.spec.dt else "step")
    axes[1].set_title("actions")
    axes[1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def print_summary(agent, summary: dict) -> None:
    from rich.console import Console
    from rich.table import Table

    table = Table(title=f"JacProp agent on {agent.env_id}")
    for col in ("episode", "phase", "env steps", "episode cost", "eval cost", "ratio",
                "1-step RMS", "Jac err", "s/episode"):
        table.add_column(col, justify="right")
    for r in agent.logger_rows:
        table.add_row(
            str(r["episode"] + 1), r["phase"], str(r["env_steps"]), _num(r["episode_cost"]),
            _num(r.get("eval_cost")), _num(r.get("cost_ratio")), _num(r.get("one_step_rms")),
            _num(r.get("jacobian_error")), _num(r.get("time_total")),
        )
    console = Console(width=max(120, Console().width))
    console.print(table)
    keys = ("episodes_to_solve", "env_steps_to_solve", "final_cost_ratio", "oracle_cost",
            "wall_seconds_per_phase")
    console.print({k: summary.get(k) for k in keys})


def _num(v) -> str:
    if v is None:
        return "-"
    try:
        f = float(v)
    except (TypeError, ValueError):
        return str(v)
    return "-" if f != f else f"{f:.4g}"


if __name__ == "__main__":
    main()
