"""Train the Algorithm-1 agent (JacProp model learning + iLQR MPC) on the two-link arm.

What it measures and how to run it: docs/experiments.md, section ``train_agent``.
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import tyro

from agents import cli
from agents.config import AgentConfig, EvaluationConfig, PlannerConfig
from agents.experiments.paper_common import pyplot, save_figure, write_result
from mbtsr.ensemble import ModelConfig
from mbtsr.training import RegularizationConfig

os.environ.setdefault("MUJOCO_GL", "egl")  # headless rendering, before mujoco is imported


@dataclass(frozen=True)
class Args:
    """Train the Algorithm-1 agent (JacProp model learning + MPC) on a Gymnasium env. The
    defaults are the paper's setup on its arm (a 4 x 1 x 20 ensemble, sampled JacProp, iLQR);
    the library's (AgentConfig()) are --model.hidden-width None --model.hidden-layers None
    --model.activations swish --regularization none --planner.kind cem-ilqr."""

    config: str = ""
    """start from this file, the flags given with it on top: a run's config.json (its agent and
    script settings; the rerun gets its own folder: --run-dir, else the default) or a YAML/JSON
    file of AgentConfig fields written by hand (changes to these defaults, e.g. 'training: {lr:
    1e-3}')"""
    env_id: str = "mbtsr/TwoLinkArm-v0"
    """Gymnasium env id"""
    episodes: int = 10
    """total training episodes of the run (a resumed run counts the done ones)"""
    resume: bool = False
    """continue from <run-dir>/checkpoint.pt with the configuration saved there"""
    out: str = ""
    """write the benchmark JSON here (the run folder is --run-dir)"""
    smoke: bool = False
    """tiny CI run (2 short episodes, a tiny model and planner): the options not given take
    SMOKE's values"""
    plots: bool = True
    """learning curve and final-reach PNGs"""
    summary_table: bool = True
    """print the rich summary table"""
    regularization: Literal["weights", "sampled", "exact", "smooth", "none"] = "weights"
    """the regularizer by name: only its weight stays on (the one given with its flag, e.g.
    --regularization.exact-weight, else its default: sampled 1, exact/smooth 0.01); none: all
    weights 0; weights: as the weight flags say"""
    agent: Annotated[AgentConfig, tyro.conf.arg(name="")] = field(
        default_factory=lambda: AgentConfig(
            model=ModelConfig.paper(), planner=PlannerConfig(kind="ilqr"),
            regularization="sampled",
            evaluation=EvaluationConfig(oracle_cache_dir="runs/oracle_cache")))
    """the agent (its flags carry no agent. prefix; the defaults: above). --run-dir defaults
    to runs/train_agent/<env>_<regularization>_<formulation>_seed<seed> (a fresh run that finds
    a finished one there adds _1, _2, ...); --evaluation.oracle-cache-dir none disables the
    shared cache of the (deterministic) oracle costs"""

    def __post_init__(self) -> None:
        if self.episodes < 1:
            raise ValueError(f"--episodes must be >= 1, got {self.episodes}")
        agent = self.agent
        if str(agent.evaluation.oracle_cache_dir).lower() in ("", "none"):
            agent = agent.replace({"evaluation.oracle_cache_dir": None})
        if self.regularization != "weights":
            agent = agent.replace(regularization=_named(self.regularization, agent.regularization))
        object.__setattr__(self, "agent", agent)


#: --smoke: the tiny CI size (given options win; the agent's: changes on top of --config's)
SMOKE = {"smoke": True, "episodes": 2, "plots": False, "summary_table": False,
         "agent": {
             "collection.episode_steps": 25, "collection.n_excitation_episodes": 1,
             "training.steps": 20, "training.batch": 32, "model.ensemble_size": 2,
             "model.hidden_width": 12, "planner.horizon": 6,
             "planner.first_plan_iterations": 4, "evaluation.every": 1,
             "evaluation.episodes": 1, "evaluation.oracle_cache_dir": None, "progress": False,
             "tensorboard": False, "torch_threads": 1}}


def _named(kind: str, reg: RegularizationConfig) -> RegularizationConfig:
    """``--regularization KIND``: ``reg`` with only KIND's weight on (its given weight, or the
    default when that is 0)."""
    rest = {k: v for k, v in dataclasses.asdict(reg).items() if not k.endswith("_weight")}
    weight = getattr(reg, f"{kind}_weight", 0.0)
    return RegularizationConfig.named(kind, weight if weight > 0 else None, **rest)


def default_run_dir(args: Args) -> Path:
    cfg = args.agent
    return Path("runs") / "train_agent" / (
        f"{args.env_id.replace('/', '_')}_{cfg.regularization.kind}_{cfg.model.formulation}"
        f"_seed{cfg.seed}")


#: the script settings a run's config.json gives to a rerun (not: its outputs, --resume, the
#: regularizer's name, which its agent section already resolves)
_RERUN = ("env_id", "episodes", "plots", "summary_table")


def _flag(argv: list[str], name: str) -> str | None:
    """The value of the last ``name VALUE`` / ``name=VALUE`` in ``argv`` (None: not given)."""
    value = None
    for i, a in enumerate(argv):
        if a == name and i + 1 < len(argv):
            value = argv[i + 1]
        elif a.startswith(name + "="):
            value = a.split("=", 1)[1]
    return value


def from_file(path: str) -> Args:
    """The :class:`Args` defaults that ``--config PATH`` gives (see :class:`Args`.config).

    :raises ValueError: naming the file and the problem.
    """
    from agents.config import in_file, read_config_file, split_run_config

    base = Args()
    try:
        agent, run = split_run_config(read_config_file(path))
        cfg = AgentConfig.from_dict(agent, base=base.agent)
        script = run.get("script", {})
        names = {f.name for f in dataclasses.fields(Args)} - {"agent"}
        known = names | {"json"}  # json: --out's former name, in the records of older runs
        if not isinstance(script, dict) or set(script) - known:
            bad = sorted(set(script) - known) if isinstance(script, dict) else script
            raise ValueError(f"unknown script setting(s) {bad} (this script has "
                             f"{sorted(names)})")
        if run:  # a run's record: its folder holds that run
            cfg = cfg.replace(run_dir=None)
        try:
            return dataclasses.replace(base, config=str(path), agent=cfg,
                                       **{k: script[k] for k in _RERUN if k in script})
        except TypeError as err:  # e.g. episodes "3" < 1
            raise ValueError(f"script: {err}") from None
    except ValueError as err:
        raise in_file(path, err) from None


def parse(argv: list[str] | None = None) -> Args:
    """The command line; ``--config PATH`` supplies the defaults (:func:`from_file`); with
    ``--resume`` the checkpoint's saved AgentConfig supplies them, and a flag that contradicts it
    is an error (exit code 2, one line)."""
    from agents.checkpoint import CheckpointError, load_checkpoint

    argv = list(sys.argv[1:] if argv is None else argv)
    path, default = _flag(argv, "--config"), None
    if path:
        try:
            default = from_file(path)
        except ValueError as err:
            cli.fail(f"--config {err}")
    args = cli.parse(Args, args=argv, outputs=("out",), default=default,
                     presets={"--smoke": SMOKE})
    if args.config and args.resume:
        cli.fail("--config starts a new run and --resume continues one with the configuration "
                 "saved in its checkpoint: give one of them")
    if args.regularization != "weights":  # a name and a weight of another regularizer
        for kind in ("sampled", "exact", "smooth"):
            flag = f"--regularization.{kind}-weight"
            if kind != args.regularization and any(
                    a.replace("_", "-").split("=")[0] == flag for a in argv):
                cli.fail(f"--regularization {args.regularization} turns "
                         f"regularization.{kind}_weight off: give {flag} or --regularization "
                         f"{args.regularization}, not both")
    if args.agent.run_dir:
        try:
            cli.check_output_path(args.agent.run_dir, name="--run-dir", folder=True)
        except ValueError as err:
            cli.fail(str(err))
    if not args.resume:
        return args
    run_dir = Path(args.agent.run_dir) if args.agent.run_dir else default_run_dir(args)
    checkpoint = run_dir / "checkpoint.pt"
    if not checkpoint.is_file():
        cli.fail(f"--resume: no checkpoint at {checkpoint}")
    try:
        saved = AgentConfig.from_dict(json.loads(load_checkpoint(checkpoint)["agent_config"]))
    except (CheckpointError, ValueError) as err:
        cli.fail(f"--resume: {err}")
    saved = saved.replace(run_dir=str(run_dir))
    args = cli.parse(Args, args=argv, default=dataclasses.replace(args, agent=saved))
    if args.agent.run_dir:  # the same folder spelled differently ("runs/x/") is no change
        args = dataclasses.replace(args, agent=args.agent.replace(run_dir=str(run_dir)))
    given, kept = args.agent.dotted(), saved.dotted()
    changed = [name for name in given if given[name] != kept[name]]
    if changed:
        name = changed[0]
        cli.fail(f"--resume: --{name.replace('_', '-')} {given[name]!r} differs "
                 f"from the saved run's {kept[name]!r} ({checkpoint})")
    return args


def main(argv: list[str] | None = None) -> dict:
    """The command line (``python -m agents.experiments.train_agent``, ``mbtsr-train``):
    :func:`parse`, then :func:`run` (errors: one line, exit code 2)."""
    return cli.call(run, parse(argv))


def console() -> None:
    """The console script ``mbtsr-train``: :func:`main`, exit code 0 (errors: 2)."""
    main()


def run(args: Args) -> dict:
    """Train (or resume) one run; write its folder, the JSON, the figures; return the summary."""
    from agents.checkpoint import CheckpointError, atomic_write_text
    from agents.evaluation import make_env
    from agents.jacprop_agent import JacPropAgent
    from mbtsr.io import write_json_atomic

    # 1. the run folder -----------------------------------------------------------------------
    cfg = args.agent
    run_dir = Path(cfg.run_dir) if cfg.run_dir else default_run_dir(args)
    if not cfg.run_dir and not args.resume:  # a fresh default run never clobbers an old one
        base, k = run_dir, 1
        while (run_dir / "checkpoint.pt").exists():
            run_dir, k = base.with_name(f"{base.name}_{k}"), k + 1
        if args.config:
            print(f"--config {args.config}: this run goes to {run_dir}")
    checkpoint = run_dir / "checkpoint.pt"
    if args.resume and not checkpoint.is_file():
        raise ValueError(f"--resume: no checkpoint at {checkpoint}")
    if not args.resume and checkpoint.exists():
        raise ValueError(
            f"{checkpoint} exists: pass --resume to continue it or choose another --run-dir")

    # 2. the env and the agent (fresh, or restored from the checkpoint) ----------------------
    env, _ = make_env(args.env_id, **({"render_mode": "rgb_array"} if cfg.video else {}))
    if args.resume:
        try:  # a damaged checkpoint or another env (dt, preset, ...): one line
            agent = JacPropAgent.load(checkpoint, env=env, run_dir=str(run_dir))
        except CheckpointError as err:
            raise ValueError(f"--resume: {err}") from None
        print(f"resuming {run_dir} after episode {agent.episodes_done}")
    else:
        agent = JacPropAgent(env, cfg.replace(run_dir=str(run_dir)))
    atomic_write_text(run_dir / "config.json", json.dumps(
        {"script": {k: v for k, v in dataclasses.asdict(args).items() if k != "agent"},
         "command": " ".join(sys.argv),
         **agent.resolved_config()}, indent=2, default=str))

    # 3. Algorithm 1: episodes of rollout -> LTV fit -> regularised model update -> planning --
    remaining = max(0, args.episodes - agent.episodes_done)
    t0 = time.perf_counter()
    agent.learn(episodes=remaining, progress_bar=agent.config.progress)
    wall = time.perf_counter() - t0

    # 4. results: summary, benchmark JSON, figures --------------------------------------------
    summary = agent.summary()
    summary["wall_seconds_this_process"] = wall
    summary["run_dir"] = str(run_dir)
    write_json_atomic(run_dir / "summary.json", summary, indent=2)
    write_result(args.out, summary, indent=2)
    if args.plots:
        plot_learning_curve(agent, run_dir / "learning_curve.png")
        plot_final_reach(agent, env, run_dir / "final_reach.png")
    if args.summary_table:
        print_summary(agent, summary)
    env.close()
    return summary


def plot_learning_curve(agent, path: Path) -> None:
    """Episode cost (training rollouts) and evaluation cost vs episodes, with the oracle."""
    plt = pyplot()
    rows = agent.logger_rows
    ep = np.array([r["episode"] for r in rows]) + 1
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    ax = axes[0]
    short = agent.config.collection.rollout_steps
    handed_on = ", episodes continued" if agent.config.collection.continue_rollouts else ""
    ax.semilogy(ep, [r["episode_cost"] for r in rows], "o-", label="training rollout" + (
        f" (at most {short} steps{handed_on}; evaluation {agent.spec.episode_steps})"
        if short else ""))
    ev = np.array([r.get("eval_cost") for r in rows], dtype=float)  # None: nan
    if np.any(np.isfinite(ev)):
        ax.semilogy(ep, ev, "s-", label="evaluation (mean of targets)")
    oracle = agent.oracle_mean
    if oracle is not None:
        ax.axhline(oracle, color="k", ls="--", label="oracle (true-model MPC)")
        ax.axhline(agent.config.evaluation.solved_ratio * oracle, color="g", ls=":", label="solved")
    ax.set_xlabel("episode")
    ax.set_ylabel("episode cost")
    ax.legend(fontsize=8)
    ax = axes[1]
    for key, label in (("one_step_rms", "one-step RMS (new data)"),
                       ("jacobian_error", "Jacobian error (new data)")):
        v = np.array([r.get(key) for r in rows], dtype=float)  # None: nan
        if np.any(np.isfinite(v)):
            ax.semilogy(ep, v, "o-", label=label)
    ax.set_xlabel("episode")
    ax.set_title("model error before the update")
    ax.legend(fontsize=8)
    save_figure(fig, path, dpi=120)


def plot_final_reach(agent, env, path: Path) -> None:
    """One evaluation reach of the final agent (and of the oracle) against its target."""
    from agents.evaluation import run_episode

    plt = pyplot()
    target, seed = agent.evaluator.problem(0)
    options = None if target is None else {"target": target}
    rec = agent.rollout_policy(env, seed=seed, options=options)
    curves = [("agent", rec)]
    if hasattr(env.unwrapped, "dynamics_model") and target is not None:
        oracle = agent.evaluator.oracle_policy(env)  # the agent's planner on the true model
        curves.append(("oracle", run_episode(env, oracle, seed=seed, options=options)))
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
    for ax, title in zip(axes, ("final reach vs target", "actions")):
        ax.set_xlabel("time [s]" if agent.spec.dt else "step")
        ax.set_title(title)
        ax.legend(fontsize=7)
    save_figure(fig, path, dpi=120)


def print_summary(agent, summary: dict) -> None:
    from rich.console import Console
    from rich.table import Table

    table = Table(title=f"JacProp agent on {agent.env_id}")
    for col in ("episode", "phase", "env steps", "episode cost", "eval cost", "ratio",
                "1-step RMS", "Jac err", "s/episode"):
        table.add_column(col, justify="right")
    for r in agent.logger_rows:
        table.add_row(
            str(r["episode"]), r["phase"], str(r["env_steps"]), _num(r["episode_cost"]),
            _num(r.get("eval_cost")), _num(r.get("cost_ratio")), _num(r.get("one_step_rms")),
            _num(r.get("jacobian_error")), _num(r.get("time_total")),
        )
    console = Console(width=max(120, Console().width))
    console.print(table)
    keys = ("episodes_to_solve", "env_steps_to_solve", "final_cost_ratio", "oracle_cost",
            "wall_seconds_per_phase")
    console.print({k: summary.get(k) for k in keys})
    steps = summary.get("env_steps_to_solve")
    if steps is not None:
        verdict = f"solved at {steps} env steps"
    elif summary.get("solved_criterion") is None:
        verdict = "no solved criterion (no oracle and no evaluation.solved_return)"
    elif not summary.get("eval_curve"):
        verdict = "not evaluated"
    else:
        verdict = "not solved within the budget"
    console.print(verdict, f"; run folder: {agent.config.run_dir}"
                  if agent.config.run_dir else "", sep="")


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
