"""SAC trained inside the learned model (``agents.model_env.ModelEnv``), evaluated in the real env.

What it measures and how to run it: docs/experiments.md, section ``model_env_sac``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Literal

import gymnasium as gym
import numpy as np
import torch

import envs  # noqa: F401  (registers mbtsr/TwoLinkArm-v0)
from agents import AgentConfig, JacPropAgent
from agents.cli import main as command
from agents.evaluation import evaluate_policy_costs, evaluation_targets
from agents.experiments.paper_common import write_result
from agents.model_env import ModelEnv
from agents.sb3_baselines import make_sb3_model


@dataclass(frozen=True)
class Args:
    """SAC in the learned model vs in the real env (mbtsr/TwoLinkArm-v0)."""

    out: str | None = "runs/model_env_sac.json"
    """Where to write the results (None: do not write)."""
    smoke: bool = False
    """tiny CI size: the options not given take SMOKE's values"""
    model_episodes: int = 6
    """Real episodes the agent learns its model from."""
    n_excitation_episodes: int = 2
    """Of those, the first ones use the excitation signal (the rest the agent's MPC)."""
    sac_steps: int = 5000
    """SAC steps inside the model (and the budget of the 'same steps' real-env baseline)."""
    member: Literal["mean", "step", "episode"] = "step"
    """Model transition: ensemble mean, a random member per step, or one per episode."""
    eval_episodes: int = 10
    """Real evaluation episodes (the agent's fixed evaluation targets)."""
    real_baselines: bool = True
    """Also train SAC in the real env (for the model's real steps and for sac_steps)."""
    seed: int = 0
    """Seed of the agent, SAC, the ModelEnv and the random policy."""


#: --smoke: the tiny CI size (options given on the command line win)
SMOKE = {"smoke": True, "model_episodes": 2, "n_excitation_episodes": 1, "sac_steps": 200,
         "eval_episodes": 1, "real_baselines": False, "out": "runs/model_env_sac_smoke.json"}


def main(argv: list[str] | None = None) -> dict:
    """The command line (``--help``: the options)."""
    return command(Args, run, args=argv, outputs=("out",), presets={"--smoke": SMOKE})


def real_cost(policy: Any, targets: np.ndarray) -> list[float]:
    """The real arm's cost per evaluation episode of ``policy`` on ``targets`` (seed 1000)."""
    return evaluate_policy_costs(policy, "mbtsr/TwoLinkArm-v0", targets, seed=1000).tolist()


def sac(env: gym.Env, steps: int, seed: int) -> tuple[Any, float]:
    """SB3 SAC with the benchmark's hyperparameters trained ``steps`` steps in ``env``, and its
    wall seconds."""
    model = make_sb3_model("sac", env, seed)
    tic = time.perf_counter()
    model.learn(steps)
    return model, time.perf_counter() - tic


def run(args: Args) -> dict:
    """Learn the model, train SAC in it, evaluate everything in the real env."""
    torch.set_num_threads(1)
    targets = evaluation_targets(args.eval_episodes, seed=1000)
    cfg = AgentConfig(seed=args.seed, progress=False, tensorboard=False).replace(
        {"collection.n_excitation_episodes": args.n_excitation_episodes, "evaluation.every": 0})
    agent = JacPropAgent(gym.make("mbtsr/TwoLinkArm-v0"), cfg)
    agent.learn(episodes=args.model_episodes, progress_bar=False)
    menv = ModelEnv.from_agent(agent, member=args.member)
    menv.reset(seed=args.seed)
    sac_model, wall = sac(menv, args.sac_steps, args.seed)
    rng = np.random.default_rng(args.seed)
    out = {
        "args": vars(args),
        "real_steps_for_model": agent.env_steps,
        "wall_seconds_sac_in_model": wall,
        "cost": {
            "sac_in_model": real_cost(sac_model, targets),
            "random": real_cost(lambda obs: rng.uniform(-1, 1, 2), targets),
            "agent_mpc": real_cost(agent, targets),
        },
    }
    if args.real_baselines:
        for name, steps in (("sac_real_same_real_steps", agent.env_steps),
                            ("sac_real_same_steps", args.sac_steps)):
            model, _ = sac(gym.make("mbtsr/TwoLinkArm-v0"), steps, args.seed)
            out["cost"][name] = real_cost(model, targets)
    for name, costs in out["cost"].items():
        print(f"{name:>26}: mean real cost {np.mean(costs):9.2f}  (return {-np.mean(costs):.2f})")
    write_result(args.out, out)
    return out


if __name__ == "__main__":
    main()
