"""Things that act in an environment: the Algorithm-1 agent, its evaluation protocol, the SB3
baselines, the learned model as an env and the experiments (docs/architecture.md, "Module map").
``from agents import JacPropAgent, AgentConfig`` imports the heavy parts on first use.
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
