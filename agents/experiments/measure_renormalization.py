"""One-step prediction error on held-out data vs episodes, with and without re-normalization.

Reacher-v5 keeps its goal in the observation (constant within an episode, different across
episodes), so the input statistics of the first episode describe the goal coordinates badly.
Runs the default agent (``renormalize=True``, statistics refitted from all data before every
update) against ``renormalize=False`` (first episode's statistics frozen), same seeds::

    python scripts/measure_renormalization.py --episodes 12 --seeds 0 1 2
"""

from __future__ import annotations

import json
import time
import warnings
from dataclasses import dataclass

import casadi as ca
import gymnasium as gym
import torch

from agents.config import AgentConfig
from agents.evaluation import run_episode
from agents.jacprop_agent import JacPropAgent
from mbtsr import excitation
from mbtsr.io import write_json_atomic
from mbtsr.metrics import prediction_rms
from mbtsr.trajectory import Trajectory

ENV = "Reacher-v5"


@dataclass(frozen=True)
class Args:
    """One-step prediction error on held-out data vs episodes, with and without
    re-normalization (Reacher-v5)."""

    episodes: int = 12
    """agent episodes per run"""
    seeds: tuple[int, ...] = (0, 1, 2)
    """agent seeds (each runs with and without renormalize)"""
    json: str = "docs/results/renormalization.json"
    """results file (rewritten after every run)"""


def reacher_cost(obs, a):
    """Distance of fingertip to target (obs[8:10]) plus effort: Reacher's own reward terms."""
    return ca.sumsqr(obs[8:10]) + 0.1 * ca.sumsqr(a)


def heldout(n: int, seed: int) -> list[Trajectory]:
    env = gym.make(ENV)
    out = []
    for i in range(n):
        sig = excitation.filtered_gaussian(50, 2, window=8, scale=1.0, seed=seed + i)
        sig = 0.5 * sig / excitation.filtered_gaussian_std(8, 1.0)
        rec = run_episode(env, lambda o, t, s=sig: s[t], seed=seed + i)
        out.append(Trajectory(rec.obs, rec.actions, 0.02))
    return out


def run(a: Args) -> dict:
    """Run every seed with and without re-normalization; return (and write) the results."""
    torch.set_num_threads(1)
    test = heldout(8, 10_000)
    results = {"env": ENV, "episodes": a.episodes, "seeds": list(a.seeds), "runs": []}
    for seed in a.seeds:
        for renorm in (True, False):
            env = gym.make(ENV)
            cfg = AgentConfig(seed=seed, renormalize=renorm, progress=False, tensorboard=False,
                              torch_threads=1).replace({"evaluation.every": 0})
            agent = JacPropAgent(env, cfg, cost_fn=reacher_cost)
            errs, tic = [], time.perf_counter()
            for _ in range(a.episodes):
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", RuntimeWarning)
                    agent.learn(1, progress_bar=False)
                errs.append(float(prediction_rms(agent.model, test)))
            run = {"seed": seed, "renormalize": renorm, "heldout_one_step_rms": errs,
                   "env_steps": [r["env_steps"] for r in agent.logger_rows],
                   "wall": time.perf_counter() - tic}
            results["runs"].append(run)
            print(json.dumps({k: run[k] for k in ("seed", "renormalize", "wall")}),
                  [f"{e:.4f}" for e in errs], flush=True)
            write_json_atomic(a.json, results, indent=2)
    return results
