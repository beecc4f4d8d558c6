"""Benchmark the Algorithm-1 agent against Stable-Baselines3 SAC, TD3 and PPO (issue 7).

Sample efficiency (env steps to solve) and wall time to solve on the same task: the same env id
and preset, 100-step episodes, reward = minus the agent's cost, the same fixed evaluation
targets and reset seeds, the same "solved" threshold (``solved_ratio`` x the mean cost of MPC
with the TRUE model on those targets, :func:`agents.evaluation.oracle_cost`). Methods:

- ``jacprop``: the agent with sampled tangent-space regularization (Jacobian propagation);
- ``none``: the same agent without regularization;
- ``sac``, ``td3``, ``ppo``: :func:`agents.sb3_baselines.train_sb3` (hyperparameters in
  :func:`agents.sb3_baselines.default_hyperparams`).

Every method x seed is one run of :func:`mbtsr.runner.run_sweep` (one JSON file per finished
run under ``--out-dir``; an interrupted benchmark resumes where it stopped). A run stops at its
first solved evaluation. A run that does not solve within its budget has steps-to-solve
``>= budget``: it is reported as that lower bound, never as a number, and so is every median or
ratio it enters. Wall seconds exclude evaluation time.

Outputs: ``--json PATH`` (everything, including the learning curves), a learning-curve figure
(log-scale env steps) and the markdown report ``--docs`` (default ``docs/benchmark_sb3.md``, the
figure next to it as ``<stem>_curves.png``).

Usage::

    python scripts/benchmark_sb3.py --json docs/benchmark.json                # full benchmark
    python scripts/benchmark_sb3.py --json /tmp/q.json --quick --docs /tmp/q.md  # CI smoke test
    python scripts/benchmark_sb3.py --json b.json --backend ray               # on a Ray cluster

Default budgets (2 cores shared with other jobs, one torch thread per worker, 2 workers): SAC
and TD3 50k env steps each (measured 20-60 env steps/s single-threaded here: up to ~40 min per
unsolved run), PPO 500k env steps (~700-1000 steps/s: ~10 min), the agent 30 episodes (3000 env
steps; it stops at its first solved evaluation). With 3 seeds the worst case (nothing solves) is
about 2-2.5 hours: a long job outside CI, resumable. Larger budgets are flags
(``--budget-sac 200000``); runs already finished with other settings are refused (use a new
``--out-dir``).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import platform
import shlex
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from agents.experiments.paper_common import SweepArgs
from mbtsr.io import atomic_write_text
from mbtsr.report import markdown_table

REPO = Path(__file__).resolve().parents[2]
os.environ.setdefault("MUJOCO_GL", "egl")

SB3_METHODS = ("sac", "td3", "ppo")
AGENT_METHODS = {"jacprop": "sampled", "none": "none"}
LABELS = {
    "jacprop": "agent, sampled JacProp",
    "none": "agent, no regularization",
    "sac": "SB3 SAC",
    "td3": "SB3 TD3",
    "ppo": "SB3 PPO",
}


@dataclass
class Args(SweepArgs):
    """Benchmark the Algorithm-1 agent against Stable-Baselines3 SAC, TD3 and PPO (issue 7)."""

    json: str = "docs/benchmark.json"
    """the benchmark JSON (--quick: runs/benchmark_sb3_quick/benchmark.json)"""
    out_dir: str = ""
    """per-run JSON + TensorBoard; default runs/benchmark_sb3[_quick]"""
    docs: str = "docs/benchmark_sb3.md"
    """markdown report; the figure goes next to it (--quick: under runs/benchmark_sb3_quick)"""
    seeds: int = 3
    """seeds per method"""
    first_seed: int = 0
    """seeds are first_seed .. first_seed + seeds - 1"""
    methods: str = "jacprop,none,sac,ppo,td3"
    """comma list of jacprop, none, sac, td3, ppo"""
    env_id: str = "mbtsr/TwoLinkArm-v0"
    """Gymnasium env id"""
    preset: str = "default"
    """arm preset (env kwarg)"""
    eval_episodes: int = 10
    """evaluation targets (the agent's eval_episodes)"""
    eval_seed: int = 1000
    """evaluation targets and resets (the agent's eval_seed)"""
    solved_ratio: float = 1.2
    """solved = mean evaluation cost <= solved_ratio x the oracle's"""
    budget_agent: int = 30
    """agent budget, episodes"""
    budget_sac: int = 50_000
    """SAC budget, env steps"""
    budget_td3: int = 50_000
    """TD3 budget, env steps"""
    budget_ppo: int = 500_000
    """PPO budget, env steps"""
    eval_every_sac: int = 500
    """env steps between SAC evaluations"""
    eval_every_td3: int = 500
    """env steps between TD3 evaluations"""
    eval_every_ppo: int = 4096
    """env steps between PPO evaluations (a multiple of PPO's n_steps, 2048)"""
    config: str = ""
    """an AgentConfig file (YAML/JSON written by hand, or a run's config.json) as the base of the
    agent runs; --quick, --agent-config, the method's regularizer and what the benchmark sets per
    run (seed, evaluation, run_dir, ...; printed) apply on top"""
    agent_config: str = "{}"
    """JSON of AgentConfig overrides by dotted field, e.g. '{"training.steps": 200}'"""
    sb3_hyperparams: str = "{}"
    """JSON {algo: {kwarg: value}} replacing the defaults of an algo"""
    sb3_progress_bar: bool = False
    """SB3's own progress bars (garbled with several workers)"""
    tensorboard: bool = True
    """TensorBoard logs of every run under --out-dir"""

    def __post_init__(self) -> None:
        _validate(self)


#: what --quick changes (tiny budgets; nothing is expected to solve); options given on the
#: command line win (``mbtsr.cli.parse(presets=...)``)
QUICK = {
    "quick": True,
    "seeds": 1,
    "eval_episodes": 2,
    "budget_agent": 2,
    "budget_sac": 200,
    "budget_td3": 200,
    "budget_ppo": 128,
    "eval_every_sac": 100,
    "eval_every_td3": 100,
    "eval_every_ppo": 64,
    "json": "runs/benchmark_sb3_quick/benchmark.json",  # never over the real report by default
    "docs": "runs/benchmark_sb3_quick/benchmark.md",
}
QUICK_AGENT = {"training.steps": 10, "planner.horizon": 10, "planner.first_plan_iterations": 5,
               "model.ensemble_size": 2}
QUICK_LTV = {"regularization.ltv_lambda": 1.0}  # --quick, for the regularizers that fit LTV models
QUICK_SB3 = {
    "sac": {"learning_starts": 50, "batch_size": 32},
    "td3": {"learning_starts": 50, "batch_size": 32, "action_noise_std": 0.1},
    "ppo": {"n_steps": 64, "batch_size": 32, "n_epochs": 2, "normalize": True},
}


def _validate(args: Args) -> None:
    for name in ("workers", "seeds", "eval_episodes", "budget_agent", "budget_sac", "budget_td3",
                 "budget_ppo", "eval_every_sac", "eval_every_td3", "eval_every_ppo"):
        if getattr(args, name) < 1:
            raise ValueError(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    if args.first_seed < 0 or args.eval_seed < 0:
        raise ValueError("--first-seed and --eval-seed must be >= 0")
    if not (math.isfinite(args.solved_ratio) and args.solved_ratio >= 1):
        raise ValueError(f"--solved-ratio must be a finite number >= 1, got {args.solved_ratio}")
    unknown = set(methods_of(args)) - set(LABELS)
    if unknown or not methods_of(args):
        raise ValueError(f"--methods must be a comma list of {sorted(LABELS)}, got {args.methods}")
    for name in ("agent_config", "sb3_hyperparams"):
        try:
            value = json.loads(getattr(args, name))
        except json.JSONDecodeError as err:
            raise ValueError(f"--{name.replace('_', '-')} is not valid JSON: {err}") from None
        if not isinstance(value, dict):
            raise ValueError(f"--{name.replace('_', '-')} must be a JSON object")


def methods_of(args: Args) -> list[str]:
    return [m.strip() for m in args.methods.split(",") if m.strip()]


# ------------------------------------------------------------------------------------------
# Run functions (module level: the runner's worker processes import them)
# ------------------------------------------------------------------------------------------


def agent_fields(config: dict, seed: int, env) -> dict:
    """The AgentConfig fields (dotted) of an agent run (and of the oracle probe, which shares
    them)."""
    fields = dict(config["agent_config"])
    if env is not None and fields.get("collection.episode_steps") is None and getattr(
            env.spec, "max_episode_steps", None) is None:
        fields["collection.episode_steps"] = int(env.unwrapped.episode_steps)
    fields.update({
        "seed": seed, "evaluation.every": 1, "evaluation.episodes": config["eval_episodes"],
        "evaluation.seed": config["eval_seed"], "evaluation.solved_ratio": config["solved_ratio"],
        "evaluation.stop_when_solved": True, "evaluation.early_exit": False, "progress": False,
        "checkpoint": False, "evaluation.oracle_cache_dir": config.get("oracle_cache_dir"),
        "run_dir": config.get("run_dir") and f"{config['run_dir']}/seed{seed}",
        "tensorboard": bool(config.get("run_dir"))})
    return fields


def compute_oracle(config: dict) -> dict:
    """The evaluation targets and the true-model MPC oracle's costs on them, computed by an agent
    with the benchmark's settings through its own cache (``oracle_cache_dir``), so the
    benchmark and every agent run share one cached oracle."""
    import gymnasium as gym
    import numpy as np

    import envs  # noqa: F401  (registers the ids)
    from agents.config import AgentConfig
    from agents.jacprop_agent import JacPropAgent

    env = gym.make(config["env_id"], **config["env_kwargs"])
    fields = {**agent_fields(config, 0, env), "run_dir": None, "tensorboard": False}
    probe = JacPropAgent(env, AgentConfig.default(fields))
    t0 = time.perf_counter()
    cost = probe.compute_oracle()
    seconds = time.perf_counter() - t0
    env.close()
    return {"targets": np.asarray(probe.eval_targets).tolist(), "oracle_cost": cost,
            "oracle_seconds": seconds}


def run_case(config: dict, seed: int) -> dict:
    """One method x seed: an SB3 baseline or the agent, to the first solved evaluation."""
    import envs  # noqa: F401  (registers the ids)

    if config["method"] in SB3_METHODS:
        from agents.sb3_baselines import train_sb3

        return train_sb3(
            config["method"], config["env_id"], config["budget_steps"], seed,
            config["eval_every"], config["targets"], config["threshold"],
            hyperparams=config["hyperparams"], tensorboard_log=config.get("tensorboard_log"),
            progress_bar=config.get("progress_bar", False), env_kwargs=config["env_kwargs"],
            eval_seed=config["eval_seed"], tb_log_name=f"{config['method']}_seed{seed}",
        )
    return run_agent(config, seed)


def run_agent(config: dict, seed: int) -> dict:
    """The Algorithm-1 agent for up to ``budget_episodes`` episodes, evaluated after every
    episode (after the excitation phase) on the benchmark's targets; stops when solved."""
    import gymnasium as gym

    from agents.config import AgentConfig
    from agents.jacprop_agent import JacPropAgent

    t_start = time.perf_counter()
    env = gym.make(config["env_id"], **config["env_kwargs"])
    agent = JacPropAgent(env, AgentConfig.default(agent_fields(config, seed, env)))
    curve, train_wall, eval_seconds = [], [], [0.0]
    solve: dict[str, Any] = {}

    def after_episode(info: dict) -> bool:
        row = info["row"]
        now = time.perf_counter() - t_start
        eval_seconds[0] += row["time_eval"]
        if row.get("eval_cost") is not None:
            curve.append([int(row["env_steps"]), float(row["eval_cost"])])
            train_wall.append(now - eval_seconds[0])
        if row.get("solved") and not solve:
            solve.update(steps=int(row["env_steps"]), wall=now - eval_seconds[0],
                         wall_incl=now, episodes=int(row["episode"]) + 1)
        return True

    agent.learn(config["budget_episodes"], callback=after_episode, progress_bar=False)
    total = time.perf_counter() - t_start
    env.close()
    return {
        "method": config["method"],
        "regularization": agent.config.regularization.kind,
        "seed": seed,
        "budget_episodes": config["budget_episodes"],
        "budget_steps": config["budget_episodes"] * agent.spec.episode_steps,
        "threshold": config["threshold"],
        "agent_oracle_cost": agent.oracle_mean,
        "curve": curve,
        "curve_train_wall": train_wall,
        "solved": bool(solve),
        "steps_to_solve": solve.get("steps"),
        "episodes_to_solve": solve.get("episodes"),
        "wall_seconds_to_solve": solve.get("wall"),
        "wall_seconds_to_solve_incl_eval": solve.get("wall_incl"),
        "env_steps": int(agent.env_steps),
        "train_wall_seconds": total - eval_seconds[0],
        "eval_wall_seconds": eval_seconds[0],
        "total_wall_seconds": total,
        "agent_config": agent.config.to_dict(),
        "wall_time_note": "wall_seconds_to_solve excludes evaluation time",
    }


# ------------------------------------------------------------------------------------------
# Summaries: censored medians, the best SB3 method, ratios
# ------------------------------------------------------------------------------------------


def bound(value: float, lower: bool, fmt: str = "{:.0f}") -> dict:
    """A number that may be a lower bound, with its display string (``">= 100000"``)."""
    return {"value": value, "lower_bound": lower,
            "display": (">= " if lower else "") + fmt.format(value)}


def run_entry(rec: dict) -> dict:
    """Per-seed numbers of one finished run; unsolved runs get lower bounds."""
    r = rec["result"]
    solved = bool(r["solved"])
    steps = r["steps_to_solve"] if solved else r["env_steps"]
    wall = r["wall_seconds_to_solve"] if solved else r["train_wall_seconds"]
    curve = r["curve"]
    return {
        "seed": rec["seed"],
        "solved": solved,
        "steps_to_solve": bound(float(steps), not solved),
        "wall_seconds_to_solve": bound(float(wall), not solved, "{:.1f}"),
        "wall_seconds_to_solve_incl_eval": bound(
            float(r["wall_seconds_to_solve_incl_eval"] if solved else r["total_wall_seconds"]),
            not solved, "{:.1f}"),
        "final_eval_cost": curve[-1][1] if curve else None,
        "env_steps": r["env_steps"],
        "train_wall_seconds": r["train_wall_seconds"],
        "eval_wall_seconds": r["eval_wall_seconds"],
        "env_steps_per_second": r["env_steps"] / max(r["train_wall_seconds"], 1e-9),
        "curve": curve,
        "curve_train_wall": r["curve_train_wall"],
        **({"agent_oracle_cost": r["agent_oracle_cost"]} if "agent_oracle_cost" in r else {}),
    }


def summarize_method(name: str, records: list[dict], config: dict, n_seeds: int,
                     oracle: float) -> dict:
    from agents.sb3_baselines import censored_median

    runs = [run_entry(rec) for rec in records]
    budget = config.get("budget_steps")
    if budget is None:  # the agent: episodes x the env's episode length
        budget = records[0]["result"]["budget_steps"] if records else None
    out: dict[str, Any] = {
        "label": LABELS[name],
        "budget_steps": budget,
        "n_runs": len(runs),
        "n_failed": n_seeds - len(runs),
        "n_solved": sum(r["solved"] for r in runs),
        "runs": runs,
    }
    if name in SB3_METHODS:
        out["hyperparams"] = config["hyperparams"]
        out["eval_every"] = config["eval_every"]
    else:
        out["agent_config_overrides"] = config["agent_config"]
        out["budget_episodes"] = config["budget_episodes"]
        out["agent_config"] = records[0]["result"]["agent_config"] if records else None
    if runs:
        for key, fmt in (("steps_to_solve", "{:.0f}"), ("wall_seconds_to_solve", "{:.1f}"),
                         ("wall_seconds_to_solve_incl_eval", "{:.1f}")):
            med, lower = censored_median([r[key]["value"] for r in runs],
                                         [r[key]["lower_bound"] for r in runs])
            out[f"median_{key}"] = bound(med, lower, fmt)
        finals = [r["final_eval_cost"] / oracle for r in runs if r["final_eval_cost"] is not None]
        out["median_final_cost_ratio"] = float(sorted(finals)[len(finals) // 2]) if finals \
            else None
    return out


def ratio(num: dict, den: dict) -> dict:
    """``num / den`` for numbers that may be lower bounds: exact / exact is exact,
    lower / exact a lower bound, exact / lower an upper bound, lower / lower undetermined."""
    value = num["value"] / den["value"] if den["value"] > 0 else math.inf
    kind = {(False, False): "exact", (True, False): "lower", (False, True): "upper",
            (True, True): "undetermined"}[(num["lower_bound"], den["lower_bound"])]
    prefix = {"exact": "", "lower": ">= ", "upper": "<= ", "undetermined": "? "}[kind]
    return {"value": value, "kind": kind, "display": f"{prefix}{value:.3g}"}


def target_met(r: dict, target: float, strict: bool = False) -> bool | None:
    """Is ``ratio >= target`` (``> target`` if strict)? ``None`` when the bounds can't tell."""
    meets = r["value"] > target if strict else r["value"] >= target
    if r["kind"] == "exact":
        return bool(meets)
    if r["kind"] == "lower":
        return True if meets else None
    if r["kind"] == "upper":
        return False if not meets else None
    return None


def compare(summary: dict) -> dict:
    """Best SB3 method (median steps and median wall time) and the agents' ratios to it."""
    from agents.sb3_baselines import best_of

    sb3 = {m: s for m, s in summary.items() if m in SB3_METHODS and s["n_runs"]}
    out: dict[str, Any] = {"target_steps_ratio": 20.0, "target_wall_ratio": 1.0}
    if not sb3:
        return out
    for key in ("steps_to_solve", "wall_seconds_to_solve"):
        m, v, lower = best_of({n: (s[f"median_{key}"]["value"], s[f"median_{key}"]["lower_bound"])
                               for n, s in sb3.items()})
        out[f"best_sb3_{key}"] = {"method": m, **bound(v, lower,
                                                        "{:.0f}" if "steps" in key else "{:.1f}")}
    for agent in AGENT_METHODS:
        if agent not in summary or not summary[agent]["n_runs"]:
            continue
        s = summary[agent]
        steps = ratio(out["best_sb3_steps_to_solve"], s["median_steps_to_solve"])
        wall = ratio(out["best_sb3_wall_seconds_to_solve"], s["median_wall_seconds_to_solve"])
        out[agent] = {
            "steps_ratio": steps,
            "steps_target_met": target_met(steps, 20.0),
            "wall_ratio": wall,
            "wall_target_met": target_met(wall, 1.0, strict=True),
        }
    return out


# ------------------------------------------------------------------------------------------
# Figure and markdown
# ------------------------------------------------------------------------------------------

COLORS = {"jacprop": "tab:blue", "none": "tab:cyan", "sac": "tab:red", "td3": "tab:orange",
          "ppo": "tab:green"}


def plot_curves(summary: dict, oracle: float, solved_ratio: float, path: Path) -> None:
    """Evaluation cost / oracle cost vs env steps (log-log), one thin line per seed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4.5))
    for name, s in summary.items():
        for i, run in enumerate(s["runs"]):
            pts = [(st, c / oracle) for st, c in run["curve"] if st > 0]
            if not pts:
                continue
            x, y = zip(*pts)
            ax.plot(x, y, "-", color=COLORS[name], lw=1.2, alpha=0.8, marker="." if
                    len(pts) < 40 else None, label=s["label"] if i == 0 else None)
            if run["solved"]:  # the agents' stars overlap: draw the first one larger
                ax.plot(x[-1], y[-1], "*", color=COLORS[name], mec="k", mew=0.5,
                        ms=16 if name == "jacprop" else 10, zorder=3)
    ax.axhline(solved_ratio, color="k", ls="--", lw=1, label=f"solved ({solved_ratio} x oracle)")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("env steps (log scale)")
    ax.set_ylabel("evaluation cost / oracle cost")
    ax.set_title("Learning curves on the same targets (star: first solved evaluation)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, loc="upper right")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def write_markdown(report: dict, path: Path, figure: Path) -> None:
    s, cmp, a = report["methods"], report["comparison"], report["args"]
    lines = [
        "# Benchmark: Algorithm-1 agent vs Stable-Baselines3 (SAC, TD3, PPO)",
        "",
        "Generated by `scripts/benchmark_sb3.py` (issue 7)"
        + (" in **--quick mode (smoke test, budgets far too small to solve; the numbers mean "
           "nothing)**" if report["quick"] else "")
        + (" as an INTERIM report of the runs finished so far (`--report-only`)"
           if a["report_only"] else "") + ". Reproduce with:",
        "",
        "```bash",
        report["command"],
        "```",
        "",
        f"Task: `{a['env_id']}` preset `{a['preset']}`, 100-step episodes, reward = minus the "
        "agent's cost. Solved = mean evaluation cost of the deterministic policy over "
        f"{a['eval_episodes']} fixed random targets (reset seeds {a['eval_seed']}+i) "
        f"<= {a['solved_ratio']} x the true-model MPC oracle's cost on the same targets "
        f"(oracle {report['oracle_cost']:.4g}, threshold {report['threshold']:.4g}). "
        f"Seeds: {report['seeds']}. Each run stops at its first solved evaluation.",
        "",
    ]
    rows = []
    for m in s.values():
        if not m["n_runs"]:
            missing = f"no finished run ({m['n_failed']} failed or unfinished)"
            rows.append([m["label"], m["budget_steps"], missing, "-", "-", "-", "-"])
            continue
        per_steps = ", ".join(r["steps_to_solve"]["display"] for r in m["runs"])
        per_wall = ", ".join(r["wall_seconds_to_solve"]["display"] for r in m["runs"])
        fail = f" ({m['n_failed']} missing: failed or unfinished)" if m["n_failed"] else ""
        rows.append([m["label"], m["budget_steps"], f"{m['n_solved']}/{m['n_runs']}{fail}",
                     f"**{m['median_steps_to_solve']['display']}** ({per_steps})",
                     f"**{m['median_wall_seconds_to_solve']['display']}** ({per_wall})",
                     m["median_wall_seconds_to_solve_incl_eval"]["display"],
                     m["median_final_cost_ratio"]])
    lines.append(markdown_table(
        ["method", "budget (env steps)", "solved runs", "env steps to solve: median (per seed)",
         "wall s to solve, excl. eval: median (per seed)", "wall s incl. eval: median",
         "final cost / oracle (median)"], rows))
    lines += ["", "`>= B`: not solved within the budget; the budget (or the time spent on it) is "
              "a lower bound, and so is any median or ratio it enters.", ""]
    for name in AGENT_METHODS:
        runs = s.get(name, {}).get("runs", [])
        if runs and all(r["solved"] and r["curve"] and len(r["curve"]) == 1 for r in runs):
            lines += [f"Note: {LABELS[name]} solved at its FIRST evaluation in every run, so "
                      f"{runs[0]['curve'][0][0]} env steps is also the smallest number this "
                      "configuration can report (evaluations start after the excitation "
                      "episodes); its true need may be lower, and its ratios below are then "
                      "conservative.", ""]
    if "best_sb3_steps_to_solve" in cmp:
        b, w = cmp["best_sb3_steps_to_solve"], cmp["best_sb3_wall_seconds_to_solve"]
        lines += [
            "## Ratios (best SB3 method / agent, medians over seeds)",
            "",
            f"Best SB3 by env steps: {LABELS[b['method']]} ({b['display']}); by wall time: "
            f"{LABELS[w['method']]} ({w['display']} s).",
            "",
            markdown_table(
                ["agent", "env steps: best SB3 / agent (target >= 20)", "met?",
                 "wall time: best SB3 / agent (target > 1)", "met?"],
                [[LABELS[agent], cmp[agent]["steps_ratio"]["display"],
                  _yes(cmp[agent]["steps_target_met"]), cmp[agent]["wall_ratio"]["display"],
                  _yes(cmp[agent]["wall_target_met"])] for agent in AGENT_METHODS
                 if agent in cmp]),
        ]
        lines += ["", "`>= r`: a lower bound (the SB3 median is censored by its budget); `<= r` "
                  "an upper bound (the agent did not solve); `?`: undetermined.", ""]
    lines += [
        f"![learning curves]({os.path.relpath(figure, path.parent)})",
        "",
        "Evaluation cost relative to the oracle vs env steps (log-log; the step-0 evaluation of "
        "the untrained SB3 policies is not drawn on the log axis). One line per seed.",
        "",
        "## Setup",
        "",
        f"- Machine: {report['machine']['cpu_count']} CPU cores, {report['machine']['platform']}; "
        f"{a['workers']} workers ({a['backend']} backend), one torch thread each; report "
        f"generated at git {report['machine']['git']}. Other jobs shared the machine, so wall "
        "times are noisy.",
        "- Wall time to solve EXCLUDES evaluation time (model construction, data collection, "
        "gradient steps / model fitting and planning count; the evaluation episodes and the "
        "agent's oracle computation do not). Times including evaluation are in the JSON. The "
        "first run in each worker process also pays the process cold start (first torch/SB3 "
        "calls: up to ~10 s under load), which shows in the agent's seconds-scale times.",
        "- Steps to solve are resolved to the evaluation period: the agent after every "
        f"episode ({_agent_excitation(s)}), SAC/TD3 every {a['eval_every_sac']}/"
        f"{a['eval_every_td3']} steps, PPO every {a['eval_every_ppo']} steps.",
        "- SB3 hyperparameters: SB3 defaults with the rl-baselines3-zoo MuJoCo changes that "
        "are not about the budget (TD3: Gaussian action noise std 0.1; PPO: VecNormalize of "
        "observations and rewards); the zoo's `learning_starts=10000` is not used, because it "
        "would put a 10k-step floor under steps-to-solve. Per method: "
        + "; ".join(f"{n}: `{json.dumps(m['hyperparams'])}`" for n, m in s.items()
                    if "hyperparams" in m) + ".",
        "- Agent: `AgentConfig` defaults with overrides "
        f"`{json.dumps(_agent_summary(s).get('agent_config_overrides', {}))}`; `none` differs "
        "only in `regularization`.",
        f"- Compute: the runs took {report['run_seconds_total'] / 3600:.2f} h of wall time in "
        f"total (sum over runs, {a['workers']} in parallel), the oracle "
        f"{report['oracle_seconds']:.0f} s; runs finished between {report['runs_finished'][0]} "
        f"and {report['runs_finished'][1]}. This invocation took "
        f"{report['benchmark_wall_seconds'] / 60:.1f} min (finished runs are loaded, not rerun).",
        "",
        "Raw numbers, learning curves and per-run records: the JSON written by `--json` and "
        "the per-run files under `--out-dir`.",
        "",
    ]
    atomic_write_text(path, "\n".join(lines))


def _finish_times(sweep_dir: Path, records: list[dict]) -> list[str]:
    """First and last finish time (UTC, from the per-run files) of ``records``."""
    from datetime import datetime, timezone

    stamps = sorted(os.path.getmtime(sweep_dir / "runs" / f"{r['run_id']}.json") for r in records)
    if not stamps:
        return ["-", "-"]
    fmt = "%Y-%m-%d %H:%M UTC"
    return [datetime.fromtimestamp(t, timezone.utc).strftime(fmt) for t in (stamps[0], stamps[-1])]


def _git_revision() -> str:
    import subprocess

    try:
        rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, text=True,
                             capture_output=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"],
                               cwd=REPO, text=True, capture_output=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return rev + (" (uncommitted changes)" if dirty else "")


def _agent_summary(s: dict) -> dict:
    return s.get("jacprop") or s.get("none") or {}


def _agent_excitation(s: dict) -> str:
    from agents.config import AgentConfig

    saved = _agent_summary(s).get("agent_config")
    cfg = AgentConfig.from_dict(saved).collection if saved else None  # old flat JSON too
    k = cfg and cfg.n_excitation_episodes
    steps = cfg and cfg.episode_steps
    return "evaluations start after the excitation phase" if k is None else (
        f"{steps} steps each; the first evaluation after the {k} excitation episodes")


def _yes(v: bool | None) -> str:
    return {True: "yes", False: "**no**", None: "undetermined"}[v]


# ------------------------------------------------------------------------------------------
# Main: oracle -> sweep -> summaries -> JSON, figure, markdown
# ------------------------------------------------------------------------------------------


def _agent_config(overrides: dict, method: str, quick: bool) -> dict:
    """The AgentConfig fields (dotted) of agent method ``method``."""
    kind = AGENT_METHODS[method]
    ltv = QUICK_LTV if quick and kind in ("sampled", "exact") else {}
    return {**ltv, **overrides, "regularization": kind}


def run(args: Args) -> dict:
    """Oracle, sweep (resumable), summaries; writes the JSON, the figure and the markdown."""
    import torch

    from agents.config import AgentConfig, file_changes
    from agents.sb3_baselines import default_hyperparams
    from mbtsr.io import write_json_atomic
    from mbtsr.runner import load_results, run_sweep

    t_start = time.perf_counter()
    git_revision = _git_revision()
    torch.set_num_threads(1)
    out_dir = Path(args.out_dir or ("runs/benchmark_sb3_quick" if args.quick
                                    else "runs/benchmark_sb3"))
    docs = Path(args.docs)
    figure = docs.with_name(docs.stem + "_curves.png")
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    methods = methods_of(args)
    env_kwargs = {"preset": args.preset}
    command = "python scripts/benchmark_sb3.py " + shlex.join(sys.argv[1:])

    # 1. evaluation targets and the oracle: an agent's, through the cache the runs share ------
    from_file = {}
    if args.config:
        per_run = {*agent_fields({"agent_config": {}, "eval_episodes": 1, "eval_seed": 0,
                                  "solved_ratio": 1.2}, 0, None),
                   *(f"regularization.{k}_weight" for k in ("sampled", "exact", "smooth"))}
        from_file, fixed = file_changes(args.config, per_run)
        if fixed:
            print(f"--config {args.config}: the benchmark sets {', '.join(fixed)} per run")
    agent_overrides = {**from_file, **(QUICK_AGENT if args.quick else {}),
                       **json.loads(args.agent_config)}
    agent_base = {"env_id": args.env_id, "env_kwargs": env_kwargs, "eval_seed": args.eval_seed,
                  "eval_episodes": args.eval_episodes, "solved_ratio": args.solved_ratio,
                  "oracle_cache_dir": str(out_dir / "oracle_cache")}
    for m in sorted(set(methods) & set(AGENT_METHODS)):  # every agent config valid, before runs
        try:
            AgentConfig.default(agent_fields({**agent_base, "agent_config": _agent_config(
                agent_overrides, m, args.quick)}, 0, None))
        except ValueError as err:
            raise ValueError(f"method {m!r}: {err}") from None
    oracle_rec = compute_oracle({**agent_base, "agent_config": agent_overrides})
    oracle = oracle_rec["oracle_cost"]
    threshold = args.solved_ratio * oracle
    targets = oracle_rec["targets"]
    print(f"oracle cost {oracle:.4g} on {len(targets)} targets "
          f"({oracle_rec['oracle_seconds']:.1f} s); solved threshold {threshold:.4g}")

    # 3. one config per method ------------------------------------------------------------------
    sb3_override = json.loads(args.sb3_hyperparams)
    configs: dict[str, dict] = {}
    for m in methods:
        base = {"method": m, "env_id": args.env_id, "env_kwargs": env_kwargs,
                "eval_seed": args.eval_seed, "threshold": threshold}
        if m in SB3_METHODS:
            hp = sb3_override.get(m, QUICK_SB3[m] if args.quick else default_hyperparams(m))
            configs[m] = {**base, "budget_steps": getattr(args, f"budget_{m}"),
                          "eval_every": getattr(args, f"eval_every_{m}"), "targets": targets,
                          "hyperparams": hp, "progress_bar": args.sb3_progress_bar,
                          "tensorboard_log": str(out_dir / "tb") if args.tensorboard else None}
        else:
            configs[m] = {**base, **agent_base, "budget_episodes": args.budget_agent,
                          "agent_config": _agent_config(agent_overrides, m, args.quick),
                          "run_dir": str(out_dir / "agent" / m) if args.tensorboard else None}

    # 4. the sweep (per-run JSON, resumable) ----------------------------------------------------
    if args.report_only:  # finished runs of exactly these configs and seeds
        records = [r for r in load_results(out_dir / "sweep") if r["name"] in configs
                   and r["seed"] in seeds and r["config"] == configs[r["name"]]]
    else:
        records = run_sweep(run_case, configs, seeds, out_dir / "sweep", backend=args.backend,
                            workers=args.workers, progress=True, address=args.address or None)

    # 5. summaries, ratios, outputs --------------------------------------------------------------
    summary = {m: summarize_method(m, [r for r in records if r["name"] == m], configs[m],
                                   len(seeds), oracle) for m in methods}
    for m in AGENT_METHODS:  # the agent computed its own oracle: it must be the same number
        for run in summary.get(m, {}).get("runs", []):
            own = run.get("agent_oracle_cost")
            if own is not None and not math.isclose(own, oracle, rel_tol=1e-9):
                print(f"WARNING: {m} seed {run['seed']} oracle {own} != benchmark oracle {oracle}")
    report = {
        "command": command,
        "quick": args.quick,
        "args": dataclasses.asdict(args),
        "seeds": seeds,
        "oracle_cost": oracle,
        "threshold": threshold,
        "eval_targets": targets,
        "machine": {"cpu_count": os.cpu_count(), "platform": platform.platform(),
                    "python": platform.python_version(), "torch": torch.__version__,
                    "git": git_revision},
        "wall_time_note": "wall seconds to solve exclude evaluation time",
        "methods": summary,
        "comparison": compare(summary),
        "n_failed_runs": sum(s["n_failed"] for s in summary.values()),
        "oracle_seconds": oracle_rec["oracle_seconds"],
        "run_seconds_total": sum(r["wall_time"] for r in records),
        "runs_finished": _finish_times(out_dir / "sweep", records),
        "benchmark_wall_seconds": time.perf_counter() - t_start,
    }
    write_json_atomic(args.json, report)
    plot_curves(summary, oracle, args.solved_ratio, figure)
    write_markdown(report, docs, figure)
    print(f"wrote {args.json}, {figure}, {docs}")
    for m, s in summary.items():
        if s["n_runs"]:
            print(f"{m:8s} steps to solve {s['median_steps_to_solve']['display']:>12s}   "
                  f"wall {s['median_wall_seconds_to_solve']['display']:>10s} s   "
                  f"solved {s['n_solved']}/{s['n_runs']}")
    if report["n_failed_runs"] and args.report_only:
        print(f"{report['n_failed_runs']} run(s) not finished (or failed) yet")
    elif report["n_failed_runs"]:
        print(f"{report['n_failed_runs']} run(s) FAILED: see {out_dir / 'sweep' / 'errors'}")
        if args.quick:
            raise SystemExit(1)
    return report

