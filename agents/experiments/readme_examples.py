"""What the README's examples get on the defaults: each Python block of README.md run as written,
over several seeds (the agents' ``seed`` replaced), each agent's final evaluation recorded.

What it measures and how to run it: docs/experiments.md, section ``readme_examples``.
"""

from __future__ import annotations

import contextlib
import re
import tempfile
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from agents.cli import main as command
from agents.experiments.paper_common import REPO, machine_info, write_result
from mbtsr.io import write_json_atomic


@dataclass(frozen=True)
class Args:
    """Run the README's Python examples as written, once per seed, and record each agent's
    final evaluation (the README states their medians and ranges)."""

    out: str | None = None
    """write the results to this JSON file (rewritten after every run)"""
    smoke: bool = False
    """tiny CI size: the first block, one seed, capped at 2 episodes of 10 steps"""
    blocks: tuple[int, ...] = ()
    """the README's Python blocks to run, counted from 0 (empty: every block)"""
    seeds: tuple[int, ...] = (0, 1, 2)
    """the seeds: every AgentConfig the blocks build gets ``seed`` replaced"""


#: --smoke: the tiny CI size (options given on the command line win)
SMOKE = {"smoke": True, "blocks": (0,), "seeds": (0,)}


def main(argv: list[str] | None = None) -> dict:
    """The command line (``--help``: the options)."""
    return command(Args, run, args=argv, outputs=("out",), presets={"--smoke": SMOKE})


def readme_blocks(path: Path = REPO / "README.md") -> list[str]:
    """The Python code blocks of the README, in order."""
    return re.findall(r"```python\n(.*?)```", path.read_text(), flags=re.S)


def run_block(code: str, seed: int, *, smoke: bool = False) -> list[dict[str, Any]]:
    """Run one README block in a fresh temporary folder with every agent's seed set to ``seed``
    (``smoke``: at most 2 episodes of 10 steps); one record per agent it builds."""
    from agents import AgentConfig, JacPropAgent

    agents: list[Any] = []
    init, learn = JacPropAgent.__init__, JacPropAgent.learn

    def seeded_init(self, env, config=None, *args, **kwargs):
        config = (AgentConfig() if config is None else config).replace(seed=seed, progress=False)
        if smoke:
            config = config.replace({"collection.episode_steps": 10, "training.steps": 3,
                                     "planner.horizon": 5, "evaluation.episodes": 1})
        init(self, env, config, *args, **kwargs)
        agents.append(self)

    def capped_learn(self, total_timesteps=None, callback=None, log_interval=None, *,
                     progress_bar=None, episodes=None):
        return learn(self, total_timesteps if not smoke else None, callback, log_interval,
                     progress_bar=progress_bar, episodes=2 if smoke else episodes)

    with tempfile.TemporaryDirectory() as tmp, contextlib.chdir(tmp), \
            warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # logged LTV fallbacks
        JacPropAgent.__init__, JacPropAgent.learn = seeded_init, capped_learn
        try:
            exec(compile(code, "README.md", "exec"), {"__name__": "readme_example"})
        finally:
            JacPropAgent.__init__, JacPropAgent.learn = init, learn
    records = []
    for agent in agents:
        s = agent.summary()
        records.append({
            "env_id": agent.env_id, "seed": seed, "task": agent.task.source,
            "env_steps": agent.env_steps, "final_eval_return": s["final_eval_return"],
            "final_eval_returns": s["final_eval_returns"],
            "final_cost_ratio": s["final_cost_ratio"],
            "wall_seconds": s["wall_seconds_per_phase"]["total"]})  # the agent's learn calls
    return records


def run(args: Args) -> dict:
    """Run the blocks over the seeds; print and return the results (and write ``args.out``)."""
    blocks = readme_blocks()
    chosen = args.blocks or tuple(range(len(blocks)))
    if not set(chosen) <= set(range(len(blocks))):
        raise ValueError(f"--blocks must be in 0..{len(blocks) - 1}, got {list(chosen)}")
    result: dict[str, Any] = {"config": {"blocks": list(chosen), "seeds": list(args.seeds),
                                       "smoke": args.smoke},
                              "machine": machine_info(), "runs": []}
    for b in chosen:
        for seed in args.seeds:
            for rec in run_block(blocks[b], seed, smoke=args.smoke):
                result["runs"].append({"block": b, **rec})
                print(f"block {b} {rec['env_id']} seed {seed}: final return "
                      f"{rec['final_eval_return']}, {rec['wall_seconds']:.0f} s", flush=True)
            if args.out:  # each block's runs kept at once; "wrote" said at the end
                write_json_atomic(args.out, result)
    result["summary"] = summarize(result["runs"])
    write_result(args.out, result)
    return result


def summarize(runs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per block, env and task source (one agent of an env per block in the README): median
    and range of the final return."""
    keys = sorted({(r["block"], r["env_id"], r["task"]) for r in runs}, key=str)
    out = []
    for block, env_id, task in keys:
        finals = [r["final_eval_return"] for r in runs
                  if (r["block"], r["env_id"], r["task"]) == (block, env_id, task)]
        vals = [f for f in finals if f is not None]
        out.append({"block": block, "env_id": env_id, "task": task, "finals": finals,
                    "median": float(np.median(vals)) if vals else None,
                    "min": min(vals, default=None), "max": max(vals, default=None)})
    return out


if __name__ == "__main__":
    main()
