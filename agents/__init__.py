"""Things that act in an environment: the Algorithm-1 agent, its evaluation protocol, the SB3
baselines, the learned model as an env and the experiments (docs/architecture.md, "Module map").
``from agents import JacPropAgent, AgentConfig`` imports the heavy parts on first use.
"""

from __future__ import annotations

import importlib
from typing import Any

__all__ = ["AgentConfig", "JacPropAgent"]

_HOME = {"AgentConfig": "agents.config", "JacPropAgent": "agents.jacprop_agent"}


def __getattr__(name: str) -> Any:
    if name in _HOME:
        return getattr(importlib.import_module(_HOME[name]), name)
    raise AttributeError(f"module 'agents' has no attribute {name!r}")
