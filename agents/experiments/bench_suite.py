"""Benchmark suite: the agent on standard MuJoCo tasks and the project's arm, measured against
doing nothing, the true-model oracle, SB3 SAC and PETS, at equal env steps.

What it measures and how to run it: docs/experiments.md, section ``bench_suite``.
"""

from __future__ import annotations

import json
import math
import os
import platform
import sys
import time
import warnings
from collections import Counter
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from itertools import product
from pathlib import Path
from typing import Any, Literal

REPO = Path(__file__).resolve().parents[2]
os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np  # noqa: E402

from agents import cli  # noqa: E402
from agents.config import PLANNERS, PlannerConfig  # noqa: E402
from agents.experiments.paper_common import (  # noqa: E402
    cpu_model,
    finite_or_none,
    library_version,
    pyplot,
    save_figure,
)
from agents.tasks import SUITE  # noqa: E402
from mbtsr.io import atomic_write_text, write_json_atomic  # noqa: E402

REGULARIZATIONS = ("none", "sampled", "exact", "smooth")
#: a run within this fraction of the oracle's return (below it) counts as solved
ORACLE_MARGIN = 0.05
#: the evaluation protocol of every method
EVAL_EPISODES, EVAL_SEED = 3, 1000
#: the zero-action and oracle returns per task (``--baselines``), read by every report
BASELINES_JSON = REPO / "docs" / "results" / "bench_suite_baselines.json"


#: the suite's tasks (:data:`agents.tasks.SUITE` holds them: env, cost, budget, evaluation
#: period, task-specific agent settings), as this module reads them
TASKS: dict[str, dict[str, Any]] = {
    name: {"task": t, "budget": t.budget, "eval_every": t.eval_every, "overrides": t.settings}
    for name, t in SUITE.items()}

#: tiny budgets of the smoke mode (CI); planner settings only reach the planner they act in
SMOKE_OVERRIDES = {
    "training.steps": 3, "planner.horizon": 5, "planner.first_plan_iterations": 2,
    "planner.ilqr_iterations": 1, "planner.cem.samples": 16, "planner.cem.elites": 4,
    "planner.cem.iterations": 1, "planner.proposal.samples": 8, "planner.proposal.elites": 2,
    "planner.proposal.iterations": 1, "model.ensemble_size": 2, "model.hidden_width": 8,
}
SMOKE_BUDGET = 200


def _planner_applies(key: str, kind: str) -> bool:
    """Whether the dotted setting ``key`` acts under planner ``kind`` (the config refuses
    settings without effect)."""
    if key.startswith("planner.cem."):
        return kind == "cem"
    if key.startswith("planner.proposal."):
        return kind == "cem-ilqr"
    return key != "planner.ilqr_iterations" or kind != "cem"


def agent_config(name: str, overrides: dict[str, Any] | None = None, *, smoke: bool = False
                 ) -> Any:
    """The :class:`~agents.config.AgentConfig` of task ``name``: the task's settings, the
    suite's evaluation protocol, ``overrides`` (dotted ``AgentConfig`` fields) and, with
    ``smoke``, the tiny budgets (``overrides`` win over them; a re-plan period longer than
    the smoke horizon lengthens the horizon to it).

    :raises ValueError: a setting the config refuses, naming it; regularizer weights in
        ``overrides`` that turn its ``regularization`` name into another regularizer."""
    from agents.config import AgentConfig

    entry = TASKS[name]
    settings = {"evaluation.episodes": EVAL_EPISODES, "evaluation.seed": EVAL_SEED,
                "evaluation.every": 0,
                "evaluation.every_steps": SMOKE_BUDGET // 2 if smoke else entry["eval_every"],
                "progress": False, "tensorboard": False, "checkpoint": False,
                "torch_threads": 1, "jacobian_error": False,
                **entry["overrides"], **(overrides or {})}
    if smoke:
        kind = settings.get("planner.kind", PlannerConfig().kind)
        settings.update({k: v for k, v in SMOKE_OVERRIDES.items() if _planner_applies(k, kind)})
        if "planner.replan_every" in settings:
            settings["planner.replan_every"] = 2
        settings.update(overrides or {})  # the caller's settings win over the smoke budgets
        if "planner.horizon" not in (overrides or {}):
            settings["planner.horizon"] = max(settings["planner.horizon"],
                                              int(settings.get("planner.replan_every", 1)))
    cfg = AgentConfig.default(settings)
    reg = (overrides or {}).get("regularization")
    if isinstance(reg, str) and cfg.regularization.kind != reg:
        raise ValueError(f"the regularizer weights make the {reg!r} runs "
                         f"{cfg.regularization.kind!r}; set only the weights of the "
                         f"--regularizations they run")
    return cfg


#: ``--form``: how the agent is given the task (its oracle plans on the written cost):
#: ``written`` the task's functions; ``learned`` no cost (a reward learned from the env's
#: rewards), the rest of the task kept
FORMS: dict[str, Callable[[dict[str, Any]], dict[str, Any]]] = {
    "written": lambda kw: kw,
    "learned": lambda kw: {**kw, "cost_fn": "learned", "terminal_cost_fn": None},
}


def make_agent(name: str, overrides: dict[str, Any] | None = None, *, smoke: bool = False,
               form: str = "written") -> Any:
    """The agent of task ``name`` on a new env, configured by :func:`agent_config`, given the
    task in ``form`` (:data:`FORMS`)."""
    from agents.jacprop_agent import JacPropAgent

    task = TASKS[name]["task"]
    return JacPropAgent(task.make_env(), agent_config(name, overrides, smoke=smoke),
                        **FORMS[form](task.agent_kwargs()))


# ---------------------------------------------------------------------------------------------
# baselines: doing nothing and the true-model oracle
# ---------------------------------------------------------------------------------------------

def task_baselines(name: str, *, smoke: bool = False,
                   overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """Zero action and the true-model oracle (the agent's own MPC on the TRUE dynamics,
    :meth:`agents.jacprop_agent.JacPropAgent.compute_oracle`) on task ``name``'s evaluation
    episodes, with the oracle's planning time per MPC step (an upper bound).

    :param overrides: other planner settings (dotted ``AgentConfig`` fields such as
        ``"planner.kind"`` or ``"planner.horizon"``), on top of the task's own."""
    import torch

    from agents.evaluation import evaluate_policy_costs

    torch.set_num_threads(1)
    agent = make_agent(name, overrides, smoke=smoke)
    env, kwargs = agent.evaluator.setup()
    m = agent.spec.act_dim
    zero = -evaluate_policy_costs(lambda obs: np.zeros(m), env, agent.eval_targets,
                                  EVAL_SEED, **kwargs)
    tic, cpu = time.perf_counter(), time.process_time()
    agent.compute_oracle()
    wall, cpu = time.perf_counter() - tic, time.process_time() - cpu
    oracle = -np.asarray(agent.oracle_costs, dtype=float)
    steps = agent.spec.episode_steps * len(oracle)  # an upper bound where episodes end early
    cfg = agent.config.planner
    agent.env.close()
    return {
        "task": name, "zero_returns": zero.tolist(), "zero_return": float(np.mean(zero)),
        "oracle_returns": oracle.tolist(), "oracle_return": float(np.mean(oracle)),
        "oracle_seconds": wall, "oracle_cpu_seconds": cpu,
        "oracle_ms_per_step_bound": 1000.0 * wall / steps,
        "planner": _planner_settings(cfg), "git": _git(),
    }


def _planner_settings(cfg: Any) -> dict[str, Any]:
    """The planner settings a stored oracle was computed with (a :class:`PlannerConfig`)."""
    return {"kind": cfg.kind, "horizon": cfg.horizon, "terminal_weight": cfg.terminal_weight,
            "ilqr_iterations": cfg.ilqr_iterations,
            "first_plan_iterations": cfg.first_plan_iterations,
            "warm_samples": cfg.warm_samples,
            **{part: {k: getattr(getattr(cfg, part), k) for k in ("samples", "elites",
                                                                 "iterations")}
               for part in ("proposal", "cem")}}


def _settings_sentence() -> str:
    """The report's sentences on the horizon rule and the task settings beyond the defaults."""
    parts = [f"{name} " + ", ".join(f"{k}={v}" for k, v in entry["overrides"].items())
             for name, entry in TASKS.items() if entry["overrides"]]
    ends = [name for name, entry in TASKS.items() if PlannerConfig().for_task(
        entry["task"].cost_fn, entry["task"].termination_fn).horizon == 15]
    return (f" {', '.join(ends)}: horizon 15, terminal weight 100 (the horizon rule: a written "
            "cost with a termination function). Task settings beyond the agent's defaults (the "
            "agent and its oracle use them): " + "; ".join(parts) + ".")


def _check_baseline_settings(name: str, baseline: dict[str, Any], planner_cfg: Any) -> None:
    """Refuse a stored oracle computed with other planner settings (horizon, terminal weight,
    iterations) than the task's now: its return and the solved threshold would not apply.

    :raises ValueError: naming the task, both settings and the command that recomputes it."""
    # a baseline stored before warm_samples existed sampled cem.samples when warm (None)
    stored = {"warm_samples": None,
              **{k: v for k, v in baseline.get("planner", {}).items() if k != "kind"}}
    now = {k: v for k, v in _planner_settings(planner_cfg).items()
           if k != "kind" and k in stored}
    if stored != now:
        raise ValueError(
            f"the stored baseline of task {name!r} was computed with planner settings "
            f"{stored}, the task now plans with {now}: recompute it with "
            f"`python scripts/bench_suite.py --baselines --tasks {name} --seeds` (an empty "
            f"--seeds: the baselines only)")


def solved_return(oracle_return: float) -> float:
    """The return a run must reach to count as solved: within :data:`ORACLE_MARGIN` of the
    oracle's (``R - 0.05 |R|``: 200 -> 190, -3.92 -> -4.12)."""
    return oracle_return - ORACLE_MARGIN * abs(oracle_return)


def normalized(score: float | None, baseline: dict[str, Any] | None) -> float | None:
    """``(R - R_zero) / (R_oracle - R_zero)``: 0 for doing nothing, 1 for the oracle."""
    if score is None or baseline is None:
        return None
    span = baseline["oracle_return"] - baseline["zero_return"]
    return None if span == 0 else (score - baseline["zero_return"]) / span


def load_baselines(path: Path = BASELINES_JSON) -> dict[str, dict[str, Any]]:
    """The stored baselines per task (``{}`` if none)."""
    return json.loads(path.read_text()).get("tasks", {}) if path.is_file() else {}


# ---------------------------------------------------------------------------------------------
# agent runs
# ---------------------------------------------------------------------------------------------

def run_one(name: str, planner: str, reg: str, seed: int, *, smoke: bool,
            oracle_cache: str, baseline: dict[str, Any] | None,
            checkpoint_dir: Path | None = None, stop_after: int | None = None,
            agent_settings: dict[str, Any] | None = None, form: str = "written"
            ) -> dict[str, Any] | None:
    """One agent run of task ``name`` for its budget; returns its record (curve of mean
    evaluation returns, env steps to solve against the baseline's threshold, wall per phase).

    :param checkpoint_dir: this run's folder: the agent checkpoints there after every episode
        and a run found there continues from its checkpoint (bit-identical to an uninterrupted
        run, as ``train_agent.py --resume``), so a killed run loses at most one episode.
        ``None``: no checkpoint (a killed run is lost).
    :param stop_after: pause after the episode that completes this many new env steps (needs
        ``checkpoint_dir``); returns ``None`` (unfinished, to be continued from
        ``checkpoint_dir``) if the budget is not reached.
    :param agent_settings: dotted ``AgentConfig`` fields on top of the task's
        (:func:`check_agent_settings`); recorded in the run.
    :param form: how the agent is given the task (:data:`FORMS`); recorded in the run.
    :raises ValueError: ``stop_after`` without ``checkpoint_dir``; a checkpoint of other
        settings (:class:`~mbtsr.fileformat.CheckpointError`, naming the first)."""
    import torch

    from agents.checkpoint import check_same
    from agents.jacprop_agent import JacPropAgent

    if stop_after is not None and checkpoint_dir is None:
        raise ValueError("stop_after needs checkpoint_dir: a paused run continues from its "
                         "checkpoint")
    torch.set_num_threads(1)
    overrides: dict[str, Any] = {
        **check_agent_settings(agent_settings or {}),
        "seed": seed, "planner.kind": planner, "regularization": reg,
        "evaluation.oracle_cache_dir": oracle_cache}
    if baseline is not None:
        overrides["evaluation.solved_return"] = solved_return(baseline["oracle_return"])
    if checkpoint_dir is not None:
        overrides.update({"run_dir": str(checkpoint_dir), "checkpoint": True})
    agent = make_agent(name, overrides, smoke=smoke, form=form)
    if baseline is not None and not smoke:  # the oracle plans on the written task
        _check_baseline_settings(name, baseline, agent_config(name, overrides).planner.for_task(
            TASKS[name]["task"].cost_fn, TASKS[name]["task"].termination_fn))
    # earlier sessions of this run: their time and commits
    spent: dict[str, Any] = {"wall_seconds": 0.0, "cpu_seconds": 0.0, "git": []}
    progress = None if checkpoint_dir is None else Path(checkpoint_dir) / "suite_progress.json"
    if checkpoint_dir is not None and (Path(checkpoint_dir) / "checkpoint.pt").is_file():
        fresh = agent
        agent = JacPropAgent.load(checkpoint_dir, fresh.env, run_dir=str(checkpoint_dir),
                                  **FORMS[form](TASKS[name]["task"].agent_kwargs()))
        saved, now = agent.config.dotted(), fresh.config.dotted()
        for key in _SESSION_SETTINGS:  # paths and bookkeeping may change between sessions
            saved.pop(key), now.pop(key)
        check_same(saved, now, what="config", path=checkpoint_dir)
        if progress.is_file():
            earlier = json.loads(progress.read_text())
            # only the time up to this checkpoint (not a deleted checkpoint's run)
            if earlier.get("env_steps", math.inf) <= agent.env_steps:
                spent = earlier
    spent["git"] = [*spent["git"], _git()]
    budget = SMOKE_BUDGET if smoke else TASKS[name]["budget"]
    start = agent.env_steps
    tic, cpu_tic = time.perf_counter(), time.process_time()

    def after_episode(_: Any) -> bool:
        """After each episode's checkpoint: note the time spent so far; pause after
        ``stop_after`` steps (through the callback, not a shorter budget: the end of a
        ``learn`` call evaluates, and a pause must not add an evaluation)."""
        if progress is not None:
            write_json_atomic(progress, {
                "env_steps": agent.env_steps, "git": spent["git"],
                "wall_seconds": spent["wall_seconds"] + time.perf_counter() - tic,
                "cpu_seconds": spent["cpu_seconds"] + time.process_time() - cpu_tic})
        return stop_after is None or agent.env_steps - start < stop_after

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # logged LTV fallbacks
        agent.learn(total_timesteps=max(budget - start, 0), callback=after_episode,
                    progress_bar=False)
    # the run's own work, whatever else runs
    cpu_seconds = spent["cpu_seconds"] + time.process_time() - cpu_tic
    wall_seconds = spent["wall_seconds"] + time.perf_counter() - tic
    s = agent.summary()
    agent.env.close()
    if agent.env_steps < budget:
        return None
    curve = [{"env_steps": c["env_steps"], "score": c["eval_return"],
              "returns": c["eval_returns"]} for c in s["eval_curve"]]
    return {
        "task": name, "planner": planner, "regularization": reg, "seed": seed,
        "budget_env_steps": budget, "env_steps": s["env_steps"],
        "env_steps_to_solve": s["env_steps_to_solve"] if baseline is not None else None,
        "final_score": curve[-1]["score"] if curve else None, "curve": curve,
        # per update: the model's one-step error on the new episode before it, and its steps
        "updates": [{"env_steps": r.get("env_steps"), "train_steps": r.get("train_steps"),
                     "one_step_rms": finite_or_none(r.get("one_step_rms"))}
                    for r in agent.logger_rows],
        "model": agent.config.to_dict()["model"],
        **({"agent_settings": agent_settings} if agent_settings else {}),
        **({"form": form} if form != "written" else {}),
        "wall_seconds_per_phase": s["wall_seconds_per_phase"],
        "wall_seconds": wall_seconds, "cpu_seconds": cpu_seconds,
        "git_sessions": spent["git"],  # the commit(s) the run was produced at
        "versions": _versions(),  # constraints.txt pins them; a drifted venv shows here
    }


#: agent settings a suite run may not take from ``--agent-settings``: the suite's own (per run,
#: by protocol, bookkeeping)
_SUITE_OWN = ("seed", "planner.kind", "run_dir", "checkpoint", "evaluation", "torch_threads",
              "progress", "tensorboard", "jacobian_error", "video", "video_every")


def _flatten(settings: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """``{"planner": {"cem": {"samples": 9}}}`` -> ``{"planner.cem.samples": 9}`` (dotted keys
    pass through), the form :meth:`AgentConfig.replace` accepts either way.

    :raises ValueError: a key that is not a string, or a field given twice."""
    out: dict[str, Any] = {}
    for key, value in settings.items():
        if not isinstance(key, str):
            raise ValueError(f"agent setting names must be strings, got {key!r}")
        inner = _flatten(value, f"{prefix}{key}.") if isinstance(value, dict) else {
            f"{prefix}{key}": value}
        for k, v in inner.items():
            if k in out:
                raise ValueError(f"agent setting {k!r} is given twice")
            out[k] = v
    return out


#: ... and the planner settings the stored baseline records (a run planning otherwise would be
#: scored against an oracle it does not match)
_ORACLE_OWN = tuple(f"planner.{k}" for k in _flatten(_planner_settings(PlannerConfig()))
                    if k != "kind")


def check_agent_settings(settings: Any) -> dict[str, Any]:
    """``settings`` as dotted ``AgentConfig`` leaf fields (nested sections flattened), if none
    is the suite's own (:data:`_SUITE_OWN`) or one the stored oracle plans with
    (:data:`_ORACLE_OWN`: set those in the task's settings and recompute its baseline). The
    values are checked when :func:`run` builds every run's config, before the first run.

    :raises ValueError: naming the refused field and why."""
    from agents.config import AgentConfig

    if not isinstance(settings, dict):
        raise ValueError(f"agent settings must be a JSON object of dotted AgentConfig fields, "
                         f"got {type(settings).__name__}")
    flat = _flatten(settings)
    leaves = AgentConfig().dotted()
    for key in flat:
        if any(key == own or key.startswith(own + ".") for own in _SUITE_OWN) or \
                key == "regularization":
            raise ValueError(f"agent setting {key!r} is the suite's own (--seeds, --planners, "
                             f"--regularizations, the evaluation protocol, --checkpoints, "
                             f"one thread and no logging or video per run)")
        if key in _ORACLE_OWN:
            raise ValueError(
                f"agent setting {key!r} changes the planner the stored true-model oracle was "
                f"computed with ({BASELINES_JSON.name}): set it in the task's settings in "
                f"agents.tasks.SUITE and recompute the baseline with "
                f"`python scripts/bench_suite.py --baselines --tasks <task> --seeds` (an "
                f"empty --seeds: the baselines only)")
        if key not in leaves:
            from agents.config import _unknown

            raise _unknown(key)
    return flat


#: settings that may differ between the sessions of a checkpointed run (paths, bookkeeping)
_SESSION_SETTINGS = ("run_dir", "checkpoint", "evaluation.oracle_cache_dir")


def with_solved(runs: list[dict[str, Any]], baselines: dict[str, dict[str, Any]]
                ) -> list[dict[str, Any]]:
    """The runs with ``env_steps_to_solve`` taken from their curves against the stored
    baselines: the first evaluation whose mean return reaches :func:`solved_return` of the
    task's oracle (``None``: never; a run whose task has no baseline keeps its own value). The
    same test the agent makes during the run, so a baseline computed after a run still counts."""
    out = []
    for r in runs:
        b = baselines.get(r["task"])
        if b is not None:
            steps, never = steps_to_reach(r["curve"], solved_return(b["oracle_return"]))
            r = {**r, "env_steps_to_solve": None if never else int(steps)}
        out.append(r)
    return out


def _median_censored(values: list[int | None], budget: int) -> str:
    """Median of env steps to solve where ``None`` means ">= budget" (a lower bound)."""
    xs = sorted((v if v is not None else math.inf) for v in values)
    if not xs:
        return "-"
    med = float(np.median(xs))
    return f">= {budget}" if math.isinf(med) else f"{med:.0f}"


def _runs_of(runs: list[dict[str, Any]], name: str, planner: str, reg: str
             ) -> list[dict[str, Any]]:
    return sorted((r for r in runs if (r["task"], r["planner"], r["regularization"])
                   == (name, planner, reg)), key=lambda r: r["seed"])


def _groups(runs: list[dict[str, Any]], tasks: Any = TASKS
            ) -> Iterator[tuple[str, str, str, list[dict[str, Any]]]]:
    """``(task, planner, regularizer, its runs by seed)`` per configuration ``runs`` hold, in
    the order of ``tasks``, :data:`PLANNERS` and :data:`REGULARIZATIONS`."""
    for name, planner, reg in product(tasks, PLANNERS, REGULARIZATIONS):
        if rs := _runs_of(runs, name, planner, reg):
            yield name, planner, reg, rs


def aggregate(runs: list[dict[str, Any]], baselines: dict[str, dict[str, Any]]
              ) -> list[dict[str, Any]]:
    """One row per task x planner x regularizer: solved, median env steps to solve (censored,
    :func:`with_solved`), final scores and normalized scores (median and per seed), median wall
    per phase."""
    runs = with_solved(runs, baselines)
    rows = []
    for name, planner, reg, rs in _groups(runs):
        finals = [r["final_score"] for r in rs]
        norms = [normalized(f, baselines.get(name)) for f in finals]
        steps = [r["env_steps_to_solve"] for r in rs]
        budget = min(r["budget_env_steps"] for r in rs)
        rows.append({
            "task": name, "planner": planner, "regularization": reg,
            "seeds": [r["seed"] for r in rs],
            "solved": f"{sum(v is not None for v in steps)}/{len(rs)}",
            "env_steps_to_solve_median": _median_censored(steps, budget),
            "env_steps_to_solve": steps,
            "final_score_median": _median_or_none(finals),
            "final_scores": finals,
            "normalized_median": _median_or_none(norms),
            "normalized": norms,
            "wall_median_per_phase": {
                k: float(np.median([r["wall_seconds_per_phase"][k] for r in rs]))
                for k in rs[0]["wall_seconds_per_phase"]},
            "budget_env_steps": budget,
        })
    return rows


def comparisons(runs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Each regularizer R vs none per task and planner, PAIRED on the seeds both ran (equal env
    steps and optimizer steps): median env steps to solve, wins/ties/losses per seed (fewer
    steps to solve; unsolved counts as more than the budget), median final return, better /
    equal / worse final return per seed, and the ratio of the median wall times."""
    out = []
    for name, planner in product(TASKS, PLANNERS):
        by: dict[str, dict[int, dict[str, Any]]] = {}
        for r in runs:
            if r["task"] == name and r["planner"] == planner:
                by.setdefault(r["regularization"], {})[r["seed"]] = r
        for reg in (g for g in REGULARIZATIONS[1:] if g in by and "none" in by):
            seeds = sorted(set(by[reg]) & set(by["none"]))
            if not seeds:
                continue
            R, N = ([by[g][k] for k in seeds] for g in (reg, "none"))
            budget = min(r["budget_env_steps"] for r in R + N)
            # fewer steps to solve is better: minus the steps (an unsolved run: -inf), none's first
            minus_steps = [[-math.inf if r["env_steps_to_solve"] is None
                            else -r["env_steps_to_solve"] for r in rs] for rs in (N, R)]
            # a run shorter than its first evaluation (a smoke budget under one episode) has
            # no final score: the final-score columns pair the seeds that have both
            scored = [(x, y) for x, y in zip(R, N)
                      if None not in (x["final_score"], y["final_score"])]
            wall = [float(np.median([r["wall_seconds_per_phase"]["total"] for r in rs]))
                    for rs in (R, N)]
            out.append({
                "task": name, "planner": planner, "regularization": reg, "seeds": seeds,
                "steps_to_solve": " vs ".join(
                    _median_censored([r["env_steps_to_solve"] for r in rs], budget)
                    for rs in (R, N)),
                "wins_ties_losses": _better_equal_worse(list(zip(*minus_steps))),
                "final_score": " vs ".join(
                    "-" if not scored else _fmt(float(np.median([p[i]["final_score"]
                                                                 for p in scored])))
                    for i in (0, 1)),
                "final_scores_better_equal_worse": _better_equal_worse(
                    [(y["final_score"], x["final_score"]) for x, y in scored]),
                "wall_ratio": wall[0] / wall[1],
            })
    return out


def paired_runs(base: list[dict[str, Any]], variant: list[dict[str, Any]]
                ) -> dict[tuple, list[tuple[dict[str, Any], dict[str, Any]]]]:
    """``(task, planner, regularizer, budget) -> [(base run, variant run), ...]`` by seed, in
    task order; runs without a final score and groups without a pair are left out."""
    def key(r: dict[str, Any]) -> tuple:
        return r["task"], r["planner"], r["regularization"], r["budget_env_steps"]

    order = list(TASKS)
    out = {}
    for k in sorted({key(r) for r in variant},
                    key=lambda k: (order.index(k[0]) if k[0] in order else len(order), k)):
        by_seed = {r["seed"]: r for r in base if key(r) == k}
        pairs = [(by_seed[r["seed"]], r) for r in sorted(variant, key=lambda r: r["seed"])
                 if key(r) == k and r["seed"] in by_seed
                 and None not in (r["final_score"], by_seed[r["seed"]]["final_score"])]
        if pairs:
            out[k] = pairs
    return out


def _better_equal_worse(pairs: list[tuple[float, float]]) -> str:
    """``"b/e/w"``: how many ``(base, other)`` pairs have ``other`` above, equal to, below."""
    better, worse = sum(o > b for b, o in pairs), sum(o < b for b, o in pairs)
    return f"{better}/{len(pairs) - better - worse}/{worse}"


def _median_or_none(vals: list[float | None]) -> float | None:
    vals = [v for v in vals if v is not None]
    return float(np.median(vals)) if vals else None


def settings_comparison(base: list[dict[str, Any]], variant: list[dict[str, Any]],
                        baselines: dict[str, dict[str, Any]]) -> list[dict[str, Any]]:
    """Runs of other agent settings (``variant``, from ``--agent-settings``) vs the suite's
    (``base``), paired by :func:`paired_runs`: per group the seeds, both median finals and
    normalized scores, the per-seed finals, better / equal / worse finals, the median CPU
    seconds of both (wall seconds when a run lacks them: ``seconds`` says which) and their
    median training wall seconds."""
    med = _median_or_none
    out = []
    for k, pairs in paired_runs(base, variant).items():
        finals = [[p[i]["final_score"] for p in pairs] for i in (0, 1)]
        out.append({
            "task": k[0], "planner": k[1], "regularization": k[2],
            "seeds": [p[0]["seed"] for p in pairs],
            "final_median": [med(f) for f in finals],
            "normalized_median": [med([normalized(v, baselines.get(k[0])) for v in f])
                                  for f in finals],
            "finals": finals,
            "better_equal_worse": _better_equal_worse(list(zip(*finals))),
            "seconds": (kind := "cpu_seconds" if all(
                r.get("cpu_seconds") for p in pairs for r in p) else "wall_seconds"),
            "seconds_median": [med([r[kind] for r in rs]) for rs in zip(*pairs)],
            "training_seconds_median": [med([r["wall_seconds_per_phase"]["training"]
                                             for r in rs]) for rs in zip(*pairs)],
        })
    return out


def settings_labels(base: dict[str, Any], variant: dict[str, Any],
                    variant_label: str | None = None) -> tuple[str, str]:
    """Names of two sets of ``--agent-settings`` for the report: the base's (``"the suite's"``
    for the defaults) and what the variant sets differently from it (``k=v, ...``), after
    ``variant_label`` if given (a compared JSON's ``"label"``: runs that differ by code or
    task, not only by settings).

    :raises ValueError: if ``variant_label`` is given and is not a non-blank string."""
    def name(d: dict[str, Any]) -> str:
        return ", ".join(f"{k}={json.dumps(v)}" for k, v in sorted(d.items()))

    if variant_label is not None and not (isinstance(variant_label, str)
                                          and variant_label.strip()):
        raise ValueError(f"the compared JSON's \"label\" must be a non-blank string, got "
                         f"{variant_label!r}")
    changed = {k: v for k, v in variant.items() if base.get(k, object()) != v}
    dropped = sorted(k for k in base if k not in variant)
    diff = (name(changed) + "".join(f", {k}=default" for k in dropped)).strip(", ")
    if variant_label is not None:
        label = variant_label.strip() + (f"; {diff}" if diff else "")
    else:
        label = diff or "same"
    return (f"base ({name(base)})" if base else "the suite's"), label


def settings_figure(base: list[dict[str, Any]], variant: list[dict[str, Any]],
                    label: str, path: Path, base_label: str = "the suite's") -> Path:
    """Learning curves of the paired runs per task: the base's (grey) and the variant's
    (blue), seeds thin and the median thick; the labels wrapped to the panel."""
    import textwrap

    plt = pyplot()

    groups = paired_runs(base, variant)
    fig, axes = plt.subplots(1, len(groups), figsize=(4.3 * len(groups), 3.4), squeeze=False)
    for ax, ((task, planner, reg, _), pairs) in zip(axes.flat, groups.items()):
        for i, color, name in ((0, "0.45", base_label), (1, "tab:blue", label)):
            _plot_runs(ax, [p[i] for p in pairs], color=color, ls="-", alpha=0.4,
                       label=textwrap.fill(f"{name} ({len(pairs)} seeds)", 40))
        ax.set_title(f"{task} {planner}/{reg}", fontsize=10)
        ax.set_xlabel("env steps")
        ax.set_ylabel("mean eval return")
        ax.legend(fontsize=7)
    save_figure(fig, path)
    return path


# ---------------------------------------------------------------------------------------------
# SB3 SAC: a fixed budget, the same evaluation episodes
# ---------------------------------------------------------------------------------------------

SB3_METHODS = ("sac", "ppo", "td3")
#: the reference budget of the SB3 runs (env steps), evaluated 20 times along the way
SB3_STEPS = 100_000


def run_sb3(name: str, algo: str, seed: int, *, steps: int, smoke: bool) -> dict[str, Any]:
    """One SB3 run (:func:`agents.sb3_baselines.train_sb3`) on task ``name`` for ``steps`` env
    steps, evaluated every ``steps / 20`` on the suite's episodes (mean return, the agent's
    protocol); returns its record."""
    import torch

    from agents.sb3_baselines import default_hyperparams, train_sb3

    torch.set_num_threads(1)
    task = TASKS[name]["task"]
    hp = dict(default_hyperparams(algo))
    if smoke:
        steps = 256
        hp.update({"learning_starts": 32, "batch_size": 16, "policy_kwargs": {"net_arch": [16]}}
                  if algo != "ppo" else {"n_steps": 128, "batch_size": 32, "n_epochs": 1})
    every = max(steps // 20, 1) if algo != "ppo" else hp.get("n_steps", 2048)
    agent = make_agent(name, smoke=smoke)  # the evaluation targets of the arm tasks
    targets = agent.evaluator.targets()
    agent.env.close()
    r = train_sb3(algo, task.env_id, steps, seed, every, targets, hyperparams=hp,
                  env_kwargs=dict(task.make_kwargs), eval_seed=EVAL_SEED,
                  n_eval_episodes=EVAL_EPISODES if targets is None else None)
    return {"task": name, "method": algo, "seed": seed, "budget_env_steps": steps,
            "env_steps": r["env_steps"],
            "curve": [{"env_steps": int(st), "score": -float(c)} for st, c in r["curve"]],
            "hyperparams": r["hyperparams"], "train_wall_seconds": r["train_wall_seconds"],
            "wall_seconds": r["total_wall_seconds"]}


def steps_to_reach(curve: list[dict[str, Any]], score: float) -> tuple[float, bool]:
    """``(env steps, is_lower_bound)``: the first evaluation of ``curve`` whose score reaches
    ``score``; a curve that never does gives its last env steps as a lower bound."""
    for c in curve:
        if c["score"] is not None and c["score"] >= score:
            return float(c["env_steps"]), False
    return float(curve[-1]["env_steps"]) if curve else math.inf, True


def reference_rows(state: dict[str, Any], baselines: dict[str, dict[str, Any]],
                   sb3_runs: list[dict[str, Any]], pets_runs: list[dict[str, Any]]
                   ) -> list[dict[str, Any]]:
    """Per task, the numbers of the report's first two tables (:func:`_md_references` says what
    each column is): zero action, oracle, SAC, PETS, the best agent configuration (highest
    median final return), SAC's env steps to its final return, the agent vs PETS."""
    rows = []
    table = state.get("table", [])
    for name in TASKS:
        b = baselines.get(name)
        row: dict[str, Any] = {"task": name, "budget": TASKS[name]["budget"],
                               "zero": b and b["zero_return"], "oracle": b and b["oracle_return"],
                               "oracle_ms_per_step": b and b["oracle_ms_per_step_bound"]}
        sac = [r for r in sb3_runs if r["task"] == name and r["method"] == "sac" and r["curve"]]
        if sac:
            for key, steps in (("sac_50k", 50_000), ("sac_100k", 100_000)):
                row[key] = _median_or_none([score_at(r["curve"], steps) for r in sac])
            row["sac_seeds"] = [r["seed"] for r in sac]
        pets = [r for r in pets_runs if r["task"] == name and r["curve"]]
        if pets:  # scored at the env steps every PETS run reached, and at the furthest one
            ends = [int(r["curve"][-1]["env_steps"]) for r in pets]
            row["pets_points"] = []
            for E in sorted({min(ends), max(ends)}):
                score, got = median_at(pets, E)
                row["pets_points"].append({"env_steps": E, "pets": score,
                                           "pets_seeds": [r["seed"] for r in got]})
            row["pets"], row["pets_env_steps"] = score, E  # the furthest point
            row["pets_wall_per_step"] = _wall_per_step(pets)
        cands = [t for t in table if t["task"] == name and t["final_score_median"] is not None]
        if cands:
            best = max(cands, key=lambda t: t["final_score_median"])
            row["best"] = {k: best[k] for k in ("planner", "regularization", "seeds",
                                                "final_score_median", "normalized_median",
                                                "budget_env_steps")}
            F = best["final_score_median"]
            if sac:
                reach = [steps_to_reach(r["curve"], F) for r in sac]
                v = float(np.median([s for s, _ in reach]))
                lower = all(lb for _, lb in reach) or (
                    float(np.median([math.inf if lb else s for s, lb in reach])) != v)
                row["sac_steps_to_agent_final"] = {"value": v, "lower_bound": bool(lower)}
                row["sac_ratio"] = {"value": v / best["budget_env_steps"],
                                    "lower_bound": bool(lower)}
            agent_runs = _runs_of(state["runs"], name, best["planner"], best["regularization"])
            if sac and agent_runs:  # the agent's own steps to F: the lower-median seed's
                mine = sorted(math.inf if lb else s for s, lb in  # first reach (never: inf)
                              (steps_to_reach(r["curve"], F) for r in agent_runs))
                a = mine[(len(mine) - 1) // 2]
                row["agent_steps_to_final"] = a
                row["sac_ratio_first_reach"] = {
                    "value": v / a if math.isfinite(a) and a > 0 else None,
                    "lower_bound": bool(lower)}
            if pets and agent_runs:
                for point in row["pets_points"]:
                    point["agent"], got = median_at(agent_runs, point["env_steps"])
                    point["agent_seeds"] = len(got)
                row["agent_at_pets_steps"] = row["pets_points"][-1]["agent"]
                row["agent_wall_per_step"] = _wall_per_step(agent_runs)
        rows.append(row)
    return rows


def median_at(runs: list[dict[str, Any]], env_steps: int
              ) -> tuple[float | None, list[dict[str, Any]]]:
    """``(median score, the runs counted)`` at ``env_steps``: the runs whose curve got that far,
    each at its last evaluation at or before it (``None`` if no run counts)."""
    got = [r for r in runs if r["curve"] and r["curve"][-1]["env_steps"] >= env_steps
           and score_at(r["curve"], env_steps) is not None]
    scores = [score_at(r["curve"], env_steps) for r in got]
    return (float(np.median(scores)) if scores else None), got


def _wall_per_step(runs: list[dict[str, Any]]) -> float:
    """Median over runs of wall seconds per env step (training, planning and evaluation)."""
    return float(np.median([r["wall_seconds"] / max(r["env_steps"], 1) for r in runs]))


def score_at(curve: list[dict[str, Any]], steps: float) -> float | None:
    """The score of ``curve`` at ``steps`` env steps (its last evaluation at or before them)."""
    pts = [c["score"] for c in curve if c["env_steps"] <= steps and c["score"] is not None]
    return pts[-1] if pts else None


# ---------------------------------------------------------------------------------------------
# figures and the report
# ---------------------------------------------------------------------------------------------

_COLORS = {"none": "tab:blue", "sampled": "tab:orange", "exact": "tab:purple",
           "smooth": "tab:brown"}
_STYLES = {"ilqr": ":", "cem": "--", "cem-ilqr": "-"}


def _plot_runs(ax: Any, rs: list[dict[str, Any]], *, color: Any, ls: str, label: str,
               alpha: float = 0.35) -> None:
    """Every run's curve thin, their median over seeds (at each evaluation point of any run,
    :func:`score_at`) thick and labelled."""
    for r in rs:
        ax.plot([c["env_steps"] for c in r["curve"]], [c["score"] for c in r["curve"]],
                color=color, ls=ls, lw=0.5, alpha=alpha)
    grid = sorted({c["env_steps"] for r in rs for c in r["curve"]})
    med = [np.median([v for r in rs if (v := score_at(r["curve"], x)) is not None] or [np.nan])
           for x in grid]
    ax.plot(grid, med, color=color, ls=ls, lw=1.8, label=label)


def figures(runs: list[dict[str, Any]], out: Path, baselines: dict[str, dict[str, Any]],
            pets_runs: list[dict[str, Any]], sb3_runs: list[dict[str, Any]]) -> list[Path]:
    """Learning curves per task: every agent configuration (median over seeds, thick; seeds
    thin), PETS (black), SAC over its first budget (red), the zero action and the oracle
    (dotted grey lines); a second figure shows SAC over its whole 100,000 steps (log x)."""
    plt = pyplot()

    names = [n for n in TASKS if any(r["task"] == n for r in runs + pets_runs + sb3_runs)]
    if not names:
        return []
    out.mkdir(parents=True, exist_ok=True)
    cols = min(4, len(names))
    rows_n = math.ceil(len(names) / cols)
    paths = []
    for log_sac in (False, True):
        fig, axes = plt.subplots(rows_n, cols, figsize=(4.3 * cols, 3.3 * rows_n),
                                 squeeze=False)
        for ax, name in zip(axes.flat, names):
            budget = TASKS[name]["budget"]
            for _, planner, reg, rs in _groups([] if log_sac else runs, (name,)):
                _plot_runs(ax, rs, color=_COLORS[reg], ls=_STYLES[planner],
                           label=f"agent {planner}/{reg} ({len(rs)})")
            for r in (p for p in pets_runs if p["task"] == name and not log_sac):
                ax.plot([c["env_steps"] for c in r["curve"]], [c["score"] for c in r["curve"]],
                        color="k", lw=1.0, alpha=0.8,
                        label="PETS (mbrl-lib)" if r["seed"] == min(
                            p["seed"] for p in pets_runs if p["task"] == name) else None)
            for r in (s for s in sb3_runs if s["task"] == name and s["method"] == "sac"):
                pts = [c for c in r["curve"] if log_sac or c["env_steps"] <= budget * 1.05]
                ax.plot([max(c["env_steps"], 1) for c in pts], [c["score"] for c in pts],
                        color="tab:red", lw=1.0, marker=".", ms=3,
                        label=f"SAC seed {r['seed']}")
            b = baselines.get(name)
            if b:
                ax.axhline(b["oracle_return"], color="0.4", ls=":", lw=1, label="oracle")
                ax.axhline(b["zero_return"], color="0.7", ls=":", lw=1, label="zero action")
            if log_sac:
                ax.set_xscale("log")
            ax.set_title(name, fontsize=10)
            ax.set_xlabel("env steps")
            ax.set_ylabel("mean eval return")
            ax.legend(fontsize=6)
        for ax in list(axes.flat)[len(names):]:
            ax.axis("off")
        p = out / ("bench_suite_sac_curves.png" if log_sac else "bench_suite_curves.png")
        save_figure(fig, p)
        paths.append(p)
    return paths


def _table(head: list[str], rows: Iterable[Iterable[Any]]) -> list[str]:
    """A markdown table: the ``head`` row, its rule and one row per item of ``rows``."""
    def row(cells: Iterable[Any]) -> str:
        return f"| {' | '.join(map(str, cells))} |"

    return [row(head), "|" + "---|" * len(head), *map(row, rows)]


def _fmt(v: Any, digits: int = 3) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.{digits}g}"
    return str(v)


def _yes(agent: float | None, other: float) -> str:
    return "-" if agent is None else ("yes" if agent >= other else "no")


def _bound(b: dict[str, Any] | None, fmt: str = "{:.3g}") -> str:
    if b is None or b["value"] is None:
        return "-"
    return (">= " if b["lower_bound"] else "") + fmt.format(b["value"])


def _steps_note(steps: float | None) -> str:
    """`` (agent at N)`` for a finite number of env steps, else ''."""
    return f" (agent at {steps:,.0f})" if steps is not None and math.isfinite(steps) else ""


def _run_commits(runs: list[dict[str, Any]]) -> str:
    """The commits the agent ``runs`` were produced at with their number of runs, e.g.
    ``"abc1234 (3 runs), def5678-dirty (1 run)"`` (a run continued over several sessions counts
    at each of its commits; runs recorded before the suite stored commits: "unrecorded")."""
    counts = Counter(c for r in runs for c in dict.fromkeys(r.get("git_sessions", ["unrecorded"])))
    return ", ".join(f"{c} ({n} run{'s' * (n != 1)})" for c, n in counts.items()) or "-"


def _md_references(state: dict[str, Any], refs: list[dict[str, Any]], rel: str,
                   sources: tuple[str, ...]) -> list[str]:
    """The report's head: the protocol, the tasks, baselines and reference methods, the agent
    vs PETS at equal env steps and the learning-curve figures; ``sources``: the JSON files of
    the agent runs, the baselines, SAC and PETS."""
    return [
        "# Benchmark suite",
        "",
        "Generated by `scripts/bench_suite.py` from `{}` (agent runs), `{}` (zero action, "
        "true-model oracle), `{}` (SB3 SAC) and `{}` (PETS, [notes/pets_peer.md](notes/"
        "pets_peer.md)); git ".format(*sources) + state.get("git", "?") + "; the "
        "agent runs at " + _run_commits(state["runs"]) + "."
        + (f" Every agent run with the settings {json.dumps(state['agent_settings'])} on top "
           "of its task's; normalized scores and solved thresholds are against the stored "
           "true-model oracle, which plans with the task's settings alone."
           if state.get("agent_settings") else ""),
        "",
        "Every method is scored the same way: the mean of the env's own summed rewards over 3 "
        "fixed evaluation episodes (reset seeds 1000-1002). Normalized score: (R - R_zero) / "
        "(R_oracle - R_zero), 0 = doing nothing, 1 = the true-model oracle (the agent's own "
        "MPC on the true MuJoCo dynamics). Solved: within 5 % of the oracle's return.",
        "",
        "## Tasks, baselines and reference methods",
        "",
        *_table(["task", "budget (env steps)", "zero action", "oracle (planning ms/step)",
                 "SAC @ 50k", "SAC @ 100k", "PETS @ its steps",
                 "best agent config: median final (normalized)",
                 "SAC steps to the agent's final / agent's budget", "... / agent's steps to it"],
                ([r["task"], r["budget"], _fmt(r["zero"], 4),
                  f"{_fmt(r['oracle'], 4)} ({_fmt(r['oracle_ms_per_step'])})",
                  _fmt(r.get("sac_50k"), 4), _fmt(r.get("sac_100k"), 4),
                  f"{_fmt(r['pets'], 4)} @ {r['pets_env_steps']}" if "pets" in r else "-",
                  f"{b['planner']}/{b['regularization']}: {_fmt(b['final_score_median'], 4)} "
                  f"({_fmt(b['normalized_median'])})" if (b := r.get("best")) else "-",
                  _bound(r.get("sac_ratio")), _bound(r.get("sac_ratio_first_reach"))
                  + _steps_note(r.get("agent_steps_to_final"))] for r in refs)),
        "",
        "Oracle planning ms/step: its evaluation wall time over the episodes' full length (an "
        "upper bound where an episode ended early). SAC: stable-baselines3 defaults, "
        f"{SB3_STEPS} env steps, evaluated every 5,000. The last two columns divide the env "
        "steps SAC needs to reach the agent's median final return by the agent's budget (the "
        "conservative ratio) and by the agent's own steps to that return (the lower-median "
        "seed's first evaluation at or above it); '>=': the median SAC seed did not reach it "
        "within its budget (a lower bound)." + _settings_sentence(),
        "",
        "The agent vs PETS at equal env steps: the env steps every PETS run reached and the "
        "furthest one (median over the runs that got there; the agent's best configuration, "
        "median over its seeds, each at its last evaluation at or before those env steps), and "
        "wall seconds per env step (training, planning and evaluation, median over runs):",
        "",
        *_table(["task", "env steps", "PETS: median (seeds)", "agent: median (seeds)",
                 "agent >= PETS?", "wall s per env step: agent / PETS"],
                ([r["task"], p["env_steps"],
                  f"{_fmt(p['pets'], 4)} ({', '.join(map(str, p['pets_seeds']))})",
                  f"{_fmt(p.get('agent'), 4)} ({p.get('agent_seeds', 0)})",
                  _yes(p.get("agent"), p["pets"]),
                  f"{_fmt(r.get('agent_wall_per_step'))} / {_fmt(r['pets_wall_per_step'])}"]
                 for r in refs if "pets" in r for p in r["pets_points"])),
        "",
        f"![learning curves per task]({rel}/bench_suite_curves.png)",
        "",
        "Mean evaluation return vs env steps: agent configurations (colour: regularizer; line "
        "style: planner; thick: median over seeds, thin: seeds), PETS (black), SAC within the "
        "agent's budget (red), the oracle and the zero action (dotted).",
        "",
        f"![SAC over 100,000 env steps]({rel}/bench_suite_sac_curves.png)",
        ""
    ]


def _md_configurations(state: dict[str, Any]) -> list[str]:
    """The report's table of every agent configuration."""
    return ["## Every agent configuration", "", *_table(
        ["task", "planner", "regularizer", "solved", "env steps to solve: median (per seed)",
         "final return: median (per seed)", "normalized: median (per seed)",
         "wall s median: training / ltv / planning / eval / total"],
        ([r["task"], r["planner"], r["regularization"], r["solved"],
          f"{r['env_steps_to_solve_median']} ("
          + ", ".join("-" if v is None else str(v) for v in r["env_steps_to_solve"]) + ")",
          f"{_fmt(r['final_score_median'], 4)} ("
          + ", ".join(_fmt(v, 4) for v in r["final_scores"]) + ")",
          f"{_fmt(r['normalized_median'])} ({', '.join(_fmt(v) for v in r['normalized'])})",
          " / ".join(f"{r['wall_median_per_phase'].get(k, 0):.{int(k == 'ltv')}f}"
                     for k in ("training", "ltv", "planning", "eval", "total"))]
         for r in state.get("table", [])))]


def _md_regularizers(cmp: list[dict[str, Any]]) -> list[str]:
    """The report's comparison of each regularizer with none."""
    return [
        "",
        "## JacProp: each regularizer vs none",
        "",
        "Same planner, paired on the seeds both ran, equal env steps and equal optimizer steps. "
        "Fewer steps: env steps to solve (an unsolved run counts as more than its budget). "
        "Better final: a higher final evaluation return.",
        "",
        *_table(["task", "planner", "regularizer R", "seeds",
                 "env steps to solve: median, R vs none", "R fewer / equal / more steps",
                 "final return: median, R vs none", "R better / equal / worse final",
                 "wall ratio R/none"],
                ([c["task"], c["planner"], c["regularization"], ", ".join(map(str, c["seeds"])),
                  c["steps_to_solve"], c["wins_ties_losses"], c["final_score"],
                  c["final_scores_better_equal_worse"], _fmt(c["wall_ratio"])] for c in cmp)),
    ]


def write_markdown(state: dict[str, Any], path: Path, figure_dir: Path,
                   baselines: dict[str, dict[str, Any]], sb3_runs: list[dict[str, Any]],
                   pets_runs: list[dict[str, Any]], sources: tuple[str, ...]) -> None:
    """The report (``docs/benchmark.md``): tasks and baselines, the reference methods next to
    the best agent configuration, every configuration, each regularizer vs none, the figures;
    everything below :data:`NOTES_MARKER` is kept. ``sources``: as :func:`_md_references`."""
    rel = os.path.relpath(figure_dir, path.parent)
    refs = reference_rows(state, baselines, sb3_runs, pets_runs)
    state["references"] = refs
    state["comparisons"] = comparisons(with_solved(state["runs"], baselines))
    lines = [*_md_references(state, refs, rel, sources), *_md_configurations(state),
             *_md_regularizers(state["comparisons"])]
    lines += [
        "",
        "## Compute",
        "",
        f"{len(state['runs'])} agent runs, {state.get('compute_seconds', 0) / 60:.0f} min of "
        f"wall time summed over the runs (one torch thread each) on "
        f"{state.get('machine', '?')}. "
        + state.get("compute_note", "Wall times depend on the machine's load: only ratios "
                    "within a table row pair mean something."),
        "",
    ]
    notes = ""
    if path.is_file() and NOTES_MARKER in path.read_text():
        notes = path.read_text().split(NOTES_MARKER, 1)[1]
    atomic_write_text(path, "\n".join(lines) + "\n" + NOTES_MARKER + notes)


#: everything after this line of the report is written by people and kept on regeneration
NOTES_MARKER = "<!-- notes below are hand-written; scripts/bench_suite.py keeps them -->"


# ---------------------------------------------------------------------------------------------
# the command
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Args:
    """Benchmark suite: the agent on standard MuJoCo tasks against doing nothing, the
    true-model oracle, SB3 SAC and PETS."""

    out: str = "runs/bench_suite.json"
    """the agent runs' JSON (every finished run is appended at once)"""
    seeds: tuple[int, ...] = (0, 1, 2, 3, 4)
    """seeds (seed-major schedule)"""
    tasks: tuple[str, ...] = tuple(TASKS)
    """tasks to run (agents.tasks.SUITE; the module docstring says what each measures)"""
    planners: tuple[str, ...] = ("cem-ilqr",)
    """planners to run (also: ilqr, cem)"""
    regularizations: tuple[str, ...] = ("none", "sampled")
    """regularizers to run (also: exact, smooth)"""
    smoke: bool = False
    """tiny budgets (CI)"""
    resume: bool = False
    """skip runs already in --out"""
    report_only: bool = False
    """no new agent runs: aggregate, draw and report the ones in the JSON files"""
    baselines: bool = False
    """(re)compute the zero-action and oracle returns of --tasks into --baselines-json first"""
    baselines_json: str = str(BASELINES_JSON)
    """the stored baselines (zero action, oracle) per task"""
    figures: str = ""
    """folder for the PNGs ('': no figures)"""
    docs: str = ""
    """write the markdown report here (with --figures)"""
    oracle_cache: str = "runs/oracle_cache"
    """cache of the true-model oracle's costs"""
    checkpoints: str = ""
    """folder of per-run checkpoints (one subfolder per run, written after every episode); a
    run with a checkpoint there continues from it ('': no checkpoints)"""
    stop_after_steps: int = 0
    """with --checkpoints: pause each run after the episode that completes this many new env
    steps, then go on to the next (unfinished runs continue at the next call; 0: to the
    budget)"""
    sb3: tuple[str, ...] = ()
    """run these SB3 methods (e.g. --sb3 sac) on --tasks x --seeds INSTEAD of the agent, for
    SB3_STEPS env steps each (evaluated 20 times), into --sb3-json"""
    sb3_json: str = "docs/results/bench_suite_sac.json"
    """the SB3 runs' JSON (read by the report)"""
    pets_json: str = "docs/results/bench_suite_pets.json"
    """PETS' stored runs (mbrl-lib at 69cd422, docs/notes/pets_peer.md; read by the report)"""
    compare: str = ""
    """with --report-only (instead of the suite's report): a JSON of runs with other
    --agent-settings, paired with --out's runs (task, planner, regularizer, budget, seed):
    prints the paired finals and seconds and, with --figures, draws settings_<its name>.png
    (its top-level "label", if any, names the variant)"""
    agent_settings: str = ""
    """a JSON object of dotted AgentConfig fields applied to every agent run on top of the
    task's (e.g. '{"planner.replan_every": 8}'); recorded in the JSON, which then holds only
    runs of these settings (use another --out)"""
    form: Literal["written", "learned"] = "written"
    """how the agent is given the task (the oracle always plans on its written cost): the
    task's functions; 'learned': no cost, a reward learned from the env's rewards (termination
    and maps kept). A JSON holds the runs of one form"""

    def __post_init__(self) -> None:
        for name, given, known in (("tasks", self.tasks, TASKS), ("sb3", self.sb3, SB3_METHODS),
                                   ("planners", self.planners, PLANNERS),
                                   ("regularizations", self.regularizations, REGULARIZATIONS)):
            if (not given and name != "sb3") or set(given) - set(known):
                raise ValueError(f"--{name} must name some of {list(known)}, got {list(given)}")
        if self.agent_settings:
            if self.report_only or self.sb3:
                raise ValueError("--agent-settings acts on new agent runs; --report-only and "
                                 "--sb3 run none (a report reads each JSON's own settings)")
            try:
                check_agent_settings(json.loads(self.agent_settings))
            except json.JSONDecodeError as e:
                raise ValueError(f"--agent-settings is not JSON: {e}") from e
        if self.compare and (not self.report_only or self.docs):
            raise ValueError("--compare reports stored runs instead of the suite's report: give "
                             "it with --report-only and without --docs")
        if self.stop_after_steps < 0 or (self.stop_after_steps and not self.checkpoints):
            raise ValueError("--stop-after-steps must be >= 0 and needs --checkpoints (a run "
                             f"stopped early continues from its checkpoint), got "
                             f"{self.stop_after_steps}")


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """The command line (``python -m agents.experiments.bench_suite``, ``mbtsr-bench``):
    :class:`Args` -> :func:`run`."""
    return cli.main(Args, run, args=argv,
                    outputs=("out", "docs", "sb3_json", "baselines_json"),
                    folders=("figures",))


def _header(command_state: dict[str, Any], smoke: bool) -> None:
    command_state.update({
        "command": " ".join(sys.argv), "smoke": smoke,
        "machine": f"{os.cpu_count()} cores, {cpu_model()}, {platform.platform()}",
        "git": _git(),
    })


def _git() -> str:
    """The short commit of the checkout, with ``-dirty`` when the code differs from it
    (:func:`~agents.experiments.paper_common.library_version`)."""
    v = library_version()
    return v["commit"][:7] + ("-dirty" if v["library_dirty"] else "")


#: the packages whose numerics a run's numbers depend on
_NUMERIC_PACKAGES = ("torch", "numpy", "scipy", "mujoco", "numba", "casadi")


def _versions() -> dict[str, str]:
    """The installed versions of :data:`_NUMERIC_PACKAGES` (``"missing"``: not installed)."""
    from importlib.metadata import PackageNotFoundError, version

    def one(name: str) -> str:
        try:
            return version(name)
        except PackageNotFoundError:
            return "missing"

    return {name: one(name) for name in _NUMERIC_PACKAGES}


def _load(path: Path) -> dict[str, Any]:
    return json.loads(path.read_text()) if path.is_file() else {"runs": []}


def run(a: Args) -> dict[str, Any]:
    """Baselines (``--baselines``), then the agent runs (or the SB3 runs with ``--sb3``), each
    appended to its JSON at once; then figures and the report (or ``--compare``'s)."""
    bpath = Path(a.baselines_json)
    if a.baselines:
        stored = _load(bpath)
        stored.setdefault("tasks", {})
        _header(stored, a.smoke)
        for name in a.tasks:
            stored["tasks"][name] = b = task_baselines(name, smoke=a.smoke)
            write_json_atomic(bpath, stored)
            print(f"{name}: zero {b['zero_return']:.4g}, oracle {b['oracle_return']:.4g} "
                  f"({b['oracle_seconds']:.0f} s)", flush=True)
    if a.sb3 and not a.report_only:
        return _run_sb3(a)
    path = Path(a.out)
    if a.report_only and not path.is_file():
        raise ValueError(f"--report-only reports the runs in --out, and {path} is no file")
    state = _load(path) if (a.resume or a.report_only) else {"runs": []}
    if not a.report_only:
        _run_agents(a, state, path, bpath)
    baselines = load_baselines(bpath)
    if a.compare:
        return _compare(a, state, baselines)
    state["table"] = aggregate(state["runs"], baselines)
    state["compute_seconds"] = float(sum(r["wall_seconds"] for r in state["runs"]))
    write_json_atomic(path, state)
    if a.figures:
        sb3_runs = _load(Path(a.sb3_json))["runs"]
        pets_runs = _load(Path(a.pets_json))["runs"]
        figures(state["runs"], Path(a.figures), baselines, pets_runs, sb3_runs)
        if a.docs:
            write_markdown(state, Path(a.docs), Path(a.figures), baselines, sb3_runs,
                           pets_runs, tuple(str(r.relative_to(REPO) if r.is_relative_to(REPO)
                                                else r) for r in (Path(p).resolve() for p in (
                               a.out, a.baselines_json, a.sb3_json, a.pets_json))))
            write_json_atomic(path, state)
    return state


def _run_sb3(a: Args) -> dict[str, Any]:
    """The SB3 runs of ``--sb3`` on --tasks x --seeds (seed-major), each appended to
    ``--sb3-json`` at once (``--resume``: skipping the ones there)."""
    spath = Path(a.sb3_json)
    state = _load(spath) if a.resume else {"runs": []}
    _header(state, a.smoke)
    done = {(r["task"], r["method"], r["seed"]) for r in state["runs"]}
    for seed, name, algo in product(a.seeds, a.tasks, a.sb3):
        if (name, algo, seed) not in done:
            rec = run_sb3(name, algo, seed, steps=SB3_STEPS, smoke=a.smoke)
            state["runs"].append(rec)
            write_json_atomic(spath, state)
            print(f"{name} {algo} seed {seed}: final {rec['curve'][-1]['score']:.4g}, "
                  f"{rec['wall_seconds']:.0f} s", flush=True)
    return state


def _run_agents(a: Args, state: dict[str, Any], path: Path, bpath: Path) -> None:
    """The agent runs of --tasks x --planners x --regularizations x --seeds (seed-major) not yet
    in ``state``, each appended to it and written to ``path`` at once; every run's config is
    checked before the first run starts."""
    settings = check_agent_settings(json.loads(a.agent_settings)) if a.agent_settings else {}
    for name, planner, reg in product(a.tasks, a.planners, a.regularizations):
        try:
            agent_config(name, {**settings, "planner.kind": planner, "regularization": reg},
                         smoke=a.smoke)
        except ValueError as e:
            raise ValueError(f"the config of {name} with {planner}/{reg}"
                             + (" and --agent-settings" if settings else "") + f": {e}") from e
    if state["runs"] and (state.get("agent_settings", {}), state.get("form", "written")
                          ) != (settings, a.form):
        raise ValueError(f"{path} holds runs with agent settings "
                         f"{state.get('agent_settings', {})} and form "
                         f"{state.get('form', 'written')!r}, these are {settings} and "
                         f"{a.form!r}: give another --out")
    state["agent_settings"] = settings
    state["form"] = a.form
    _header(state, a.smoke)  # a report keeps the stamps of the runs it reports
    done = {(r["task"], r["planner"], r["regularization"], r["seed"]) for r in state["runs"]}
    for seed, name, planner, reg in product(a.seeds, a.tasks, a.planners, a.regularizations):
        if (name, planner, reg, seed) in done:
            continue
        form = "" if a.form == "written" else f"_{a.form}"  # a run resumes in its own form
        ckpt = (Path(a.checkpoints) / f"{name}_{planner}_{reg}{form}_seed{seed}"
                if a.checkpoints else None)
        rec = run_one(name, planner, reg, seed, smoke=a.smoke, oracle_cache=a.oracle_cache,
                      baseline=load_baselines(bpath).get(name),  # baselines may land late
                      checkpoint_dir=ckpt, stop_after=a.stop_after_steps or None,
                      agent_settings=settings, form=a.form)
        if rec is None:
            print(f"{name} {planner}/{reg} seed {seed}: paused, continues from {ckpt}",
                  flush=True)
            continue
        state["runs"].append(rec)
        state["table"] = aggregate(state["runs"], load_baselines(bpath))
        write_json_atomic(path, state)
        print(f"{name} {planner}/{reg} seed {seed}: final {_fmt(rec['final_score'], 4)}, "
              f"solved at {rec['env_steps_to_solve']}, {rec['wall_seconds']:.0f} s", flush=True)


def _compare(a: Args, state: dict[str, Any], baselines: dict[str, dict[str, Any]]
             ) -> dict[str, Any]:
    """``--compare``: prints the runs of its JSON paired with ``state``'s
    (:func:`settings_comparison`) and, with ``--figures``, draws them (:func:`settings_figure`).

    :raises ValueError: an unreadable JSON, a bad ``"label"``, no run that pairs."""
    try:
        other = json.loads(Path(a.compare).read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise ValueError(f"--compare {a.compare}: not a readable JSON of runs ({e})") from e
    try:
        base_label, label = settings_labels(state.get("agent_settings") or {},
                                            other.get("agent_settings") or {},
                                            other.get("label"))
    except ValueError as e:
        raise ValueError(f"--compare {a.compare}: {e}") from None
    rows = settings_comparison(state["runs"], other.get("runs", []), baselines)
    if not rows:
        raise ValueError(f"--compare {a.compare}: none of its runs pairs with a run of "
                         f"{a.out} (same task, planner, regularizer, budget and seed)")
    for row in rows:
        print(f"{row['task']} {row['planner']}/{row['regularization']} seeds "
              f"{row['seeds']}: {label} {_fmt(row['final_median'][1], 4)} "
              f"({_fmt(row['normalized_median'][1])}) vs {base_label} "
              f"{_fmt(row['final_median'][0], 4)} ({_fmt(row['normalized_median'][0])}); "
              f"better/equal/worse {row['better_equal_worse']}; {row['seconds']} "
              f"{_fmt(row['seconds_median'][1])} vs {_fmt(row['seconds_median'][0])}, "
              f"training {_fmt(row['training_seconds_median'][1])} vs "
              f"{_fmt(row['training_seconds_median'][0])}")
    if a.figures:
        settings_figure(state["runs"], other["runs"], label,
                        Path(a.figures) / f"settings_{Path(a.compare).stem}.png",
                        base_label=base_label)
    return {**state, "settings_comparison": rows}


def console() -> None:
    """The console script ``mbtsr-bench``: :func:`main`, exit code 0 (errors: 2)."""
    main()


if __name__ == "__main__":
    main()
