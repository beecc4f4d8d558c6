"""Ablation of the Algorithm-1 agent: episodes to "solve" the arm per regularization and seed.

Bagge Carlson et al., "Tangent-Space Regularization for Neural-Network Models of Dynamical
Systems" (arXiv:1806.09919): the agent of ``agents.jacprop_agent`` with sampled Jacobian
propagation (``sampled``), the exact Jacobian penalty it approximates (``exact``) and no
tangent-space regularization (``none``), all other settings at their defaults::

    python scripts/agent_ablation.py                       # 3 regularizations x 5 seeds
    python scripts/agent_ablation.py --episodes 15 --workers 2 --json ablation.json
    python scripts/agent_ablation.py --config arm.yaml     # a config file as every run's base
    python scripts/agent_ablation.py --help                # every option

Every run evaluates after every episode (10 fixed targets, no early exit, so every cost ratio is
exact) and does NOT stop when solved, so the episodes needed for any threshold can be read off
afterwards: the issue's 1.2 x oracle and the stricter 1.1 and 1.05. One JSON per run in
``<out>/runs`` (a killed sweep resumes); the summary (JSON + markdown table) in ``<out>``.
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from mbtsr.io import atomic_write_text, write_json_atomic
from mbtsr.report import markdown_table

THRESHOLDS = (1.2, 1.1, 1.05)


@dataclass(frozen=True)
class Args:
    """Agent ablation over regularizations x seeds."""

    variants: str = "sampled,exact,none,sampled:regularization.sigma=0.5"
    """comma-separated variants ``regularization[:field=value;...]`` (dotted AgentConfig
    fields)"""
    seeds: int = 5
    """seeds 0 .. seeds-1"""
    episodes: int = 10
    """episodes per run (the issue's budget is 30; all runs solve far earlier)"""
    workers: int = 2
    """parallel runs"""
    backend: Literal["process", "ray"] = "process"
    """mbtsr.runner backend"""
    address: str = ""
    """Ray only: address of an existing cluster (``auto``, ``host:6379``); empty: a private local
    Ray instance for the sweep (docs/troubleshooting.md)"""
    out: str = "runs/agent_ablation"
    """folder of the per-run JSON files (a killed sweep resumes), summary.json and table.md"""
    oracle_cache_dir: str = "runs/oracle_cache"
    """cache of the true-model oracle's cost"""
    config: str = ""
    """an AgentConfig file (YAML/JSON written by hand, or a run's config.json) as the base of
    every run; --agent-config, the variants and what the sweep sets per run (seed, the
    regularizer, evaluation, run_dir, ...; printed) apply on top"""
    agent_config: str = "{}"
    """JSON of further AgentConfig overrides for every run (dotted fields,
    '{"training.steps": 200}')"""
    json: str = ""
    """write the summary here too"""
    report_only: bool = False
    """only rebuild the summary from the finished runs in --out"""

    def __post_init__(self) -> None:
        for name in ("seeds", "episodes", "workers"):
            if getattr(self, name) < 1:
                raise ValueError(f"--{name} must be >= 1, got {getattr(self, name)}")
        try:
            json.loads(self.agent_config)
        except json.JSONDecodeError as e:
            raise ValueError(f"--agent-config is not JSON: {e}") from None


def parse_variants(text: str) -> dict[str, dict]:
    """``"sampled,none,sampled:regularization.sigma=0.5"`` -> ``{name: {"regularization",
    "overrides"}}`` (names such as ``sampled_sigma0.5``); values are parsed as JSON when
    possible (numbers, booleans)."""
    out = {}
    for item in filter(None, (v.strip() for v in text.split(","))):
        reg, _, rest = item.partition(":")
        overrides = {}
        for pair in filter(None, rest.split(";")):
            key, _, value = pair.partition("=")
            try:
                overrides[key] = json.loads(value)
            except json.JSONDecodeError:
                overrides[key] = value
        name = "_".join([reg, *(f"{k.rsplit('.', 1)[-1]}{v}" for k, v in overrides.items())])
        out[name] = {"regularization": reg, "overrides": overrides}
    return out


def agent_fields(config: dict, seed: int) -> dict:
    """The AgentConfig (dotted fields) of one run."""
    return {
        **config["overrides"],
        **config["variant_overrides"],
        "regularization": config["regularization"],
        "seed": seed,
        "evaluation.every": 1,
        "evaluation.early_exit": False,
        "evaluation.stop_when_solved": False,
        "checkpoint": False,
        "progress": False,
        "tensorboard": False,
        "torch_threads": 1,
        "evaluation.oracle_cache_dir": config["oracle_cache_dir"],
    }


def run_one(config: dict, seed: int) -> dict:
    """One agent run (a module-level function for the process pool)."""
    import gymnasium as gym

    import envs  # noqa: F401
    from agents.config import AgentConfig
    from agents.jacprop_agent import JacPropAgent

    t0 = time.perf_counter()
    env = gym.make(config["env_id"])
    agent = JacPropAgent(env, AgentConfig.default(agent_fields(config, seed)))
    agent.learn(config["episodes"], progress_bar=False)
    rows = agent.logger_rows
    out = {
        "regularization": config["regularization"],
        "seed": seed,
        "rows": rows,
        "summary": agent.summary(),
        "wall_seconds": time.perf_counter() - t0,
    }
    for thr in THRESHOLDS:
        hit = [r for r in rows if r.get("eval_cost") is not None and r["cost_ratio"] <= thr]
        out[f"episodes_to_{thr}"] = hit[0]["episode"] + 1 if hit else None
    env.close()
    return out


def report(records: list[dict], args: Args) -> dict:
    """Per-regularization table of episodes to each threshold and model errors."""
    import numpy as np

    table = {}
    for reg in parse_variants(args.variants):
        runs = sorted((r["result"] for r in records if r["name"] == reg),
                      key=lambda r: r["seed"])
        if not runs:
            continue
        entry = {"seeds": [r["seed"] for r in runs]}
        for thr in THRESHOLDS:
            entry[f"episodes_to_{thr}"] = [r[f"episodes_to_{thr}"] for r in runs]
            entry[f"solved_{thr}"] = sum(v is not None for v in entry[f"episodes_to_{thr}"])
        last = [r["rows"][-1] for r in runs]
        entry["final_cost_ratio"] = [x["cost_ratio"] for x in last]
        for col in ("one_step_rms", "jacobian_error"):
            # mean over the MPC episodes of the error on the new data before the update
            entry[f"mean_{col}"] = [
                float(np.nanmean([row[col] for row in r["rows"][2:]])) for r in runs
            ]
        entry["wall_seconds"] = [r["wall_seconds"] for r in runs]
        table[reg] = entry
    oracle = next((r["result"]["summary"]["oracle_cost"] for r in records), None)
    return {"episodes": args.episodes, "thresholds": THRESHOLDS, "oracle_cost": oracle,
            "table": table}


def markdown(summary: dict) -> str:
    header = ["variant", "seed", "episodes to 1.2x", "to 1.1x", "to 1.05x", "final ratio",
              "mean 1-step RMS", "mean Jacobian error"]
    cols = ["episodes_to_1.2", "episodes_to_1.1", "episodes_to_1.05", "final_cost_ratio",
            "mean_one_step_rms", "mean_jacobian_error"]
    return markdown_table(header, [[reg, seed, *(e[c][i] for c in cols)]
                                   for reg, e in summary["table"].items()
                                   for i, seed in enumerate(e["seeds"])])


def sweep_configs(args: Args) -> dict[str, dict]:
    """The sweep's run configs by variant name: the --config file's settings, --agent-config
    and the variant on top, what :func:`agent_fields` sets per run last; every variant's
    AgentConfig is checked here, before any run.

    :raises ValueError: naming the file, or the variant and the field.
    """
    from agents.config import AgentConfig, file_changes

    overrides = json.loads(args.agent_config)
    if args.config:
        per_run = {*agent_fields({"overrides": {}, "variant_overrides": {}, "regularization": "",
                                  "oracle_cache_dir": None}, 0), "run_dir",
                   *(f"regularization.{k}_weight" for k in ("sampled", "exact", "smooth"))}
        from_file, fixed = file_changes(args.config, per_run)
        if fixed:
            print(f"--config {args.config}: the sweep sets {', '.join(fixed)} per run")
        overrides = {**from_file, **overrides}
    base = {"env_id": "mbtsr/TwoLinkArm-v0", "episodes": args.episodes, "overrides": overrides,
            "oracle_cache_dir": str(Path(args.oracle_cache_dir).resolve())}
    configs = {name: {**base, "regularization": v["regularization"],
                      "variant_overrides": v["overrides"]}
               for name, v in parse_variants(args.variants).items()}
    for name, config in configs.items():
        try:
            AgentConfig.default(agent_fields(config, 0))
        except ValueError as err:
            raise ValueError(f"variant {name!r}: {err}") from None
    return configs


def run(args: Args) -> dict:
    """Run (or resume) the sweep, write and return the summary."""
    from mbtsr.runner import load_results, run_sweep

    out = Path(args.out)
    configs = sweep_configs(args)
    if not args.report_only:
        # the oracle once, before the workers start (they read it from the cache)
        import gymnasium as gym

        import envs  # noqa: F401
        from agents.config import AgentConfig
        from agents.jacprop_agent import JacPropAgent

        first = next(iter(configs.values()))
        probe = JacPropAgent(gym.make(first["env_id"]),
                             AgentConfig.default(agent_fields(first, 0)))
        print(f"oracle mean cost {probe.compute_oracle():.4g}")
        run_sweep(run_one, configs, range(args.seeds), out, backend=args.backend,
                  workers=args.workers, address=args.address or None)
    records = [r for r in load_results(out) if r["status"] == "ok" and r["name"] in configs]
    summary = report(records, args)
    summary["command"] = " ".join(["python", "scripts/agent_ablation.py", *sys.argv[1:]])
    write_json_atomic(out / "summary.json", summary)
    if args.json:
        write_json_atomic(args.json, summary)
    table = markdown(summary)
    atomic_write_text(out / "table.md", table + "\n")
    print(table)
    return summary

