"""Things that act in an environment.

- :class:`agents.jacprop_agent.JacPropAgent` with :class:`agents.config.AgentConfig`: the
  paper's Algorithm 1 (Bagge Carlson et al., arXiv:1806.09919) as an episodic model-based agent
  with a Stable-Baselines3-style ``learn / predict / save / load`` surface;
- :mod:`agents.evaluation`: the "solved" protocol (fixed random targets, the true-model MPC
  oracle) shared by the agent and the model-free baselines;
- :mod:`agents.sb3_baselines`: Stable-Baselines3 baselines on the same task;
- :mod:`agents.model_env`: the learned, frozen model as a Gymnasium env (MBPO-style);
- :mod:`agents.experiments`: the benchmarks and the paper's experiments as ``Args`` dataclasses
  with ``run(args)`` functions, the logic behind the thin ``scripts/*.py``.

``from agents import JacPropAgent, AgentConfig`` works; the heavy imports happen on first use.
"""

from __future__ import annotations

from typing import Any

__all__ = ["AgentConfig", "JacPropAgent"]


def __getattr__(name: str) -> Any:
    if name == "JacPropAgent":
        from agents.jacprop_agent import JacPropAgent

        return JacPropAgent
    if name == "AgentConfig":
        from agents.config import AgentConfig

        return AgentConfig
    raise AttributeError(f"module 'agents' has no attribute {name!r}")
