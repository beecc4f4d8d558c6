"""Callbacks of :meth:`agents.jacprop_agent.JacPropAgent.learn`: Stable-Baselines3's
``BaseCallback`` objects, called as an SB3 algorithm does, next to plain functions called after
every episode with ``{"agent", "row"}`` (``False`` stops learning); docs/agent.md, "Callbacks".
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback, CallbackList

__all__ = ["Callbacks"]


class Callbacks:
    """The callbacks of one ``learn`` call.

    :param callback: ``None``, a ``BaseCallback``, a list of them, a function
        ``f({"agent", "row"}) -> bool | None``, or a list mixing both.
    :raises TypeError: anything else (naming the offending item).
    """

    def __init__(self, callback: Any) -> None:
        items = [] if callback is None else list(callback) if isinstance(callback, list | tuple) \
            else [callback]
        for c in items:
            if not isinstance(c, BaseCallback) and not callable(c):
                raise TypeError("callback must be a stable_baselines3 BaseCallback, a function "
                                f"of {{'agent', 'row'}}, or a list of them; got {c!r}")
        self.sb3_list = CallbackList([c for c in items if isinstance(c, BaseCallback)])
        self.plain = [c for c in items if not isinstance(c, BaseCallback)]
        self.stopped = False  # an SB3 callback's on_step returned False

    def start(self, agent: Any, total_timesteps: int | None) -> None:
        """``init_callback`` and ``on_training_start`` of the SB3 callbacks (``locals`` with
        the agent as ``self`` and this call's ``total_timesteps``)."""
        self.sb3_list.init_callback(agent)
        self.sb3_list.on_training_start({"self": agent, "total_timesteps": total_timesteps}, {})

    def rollout_start(self, episode: int) -> None:
        """``on_rollout_start`` before episode ``episode``'s rollout."""
        self.sb3_list.update_locals({"episode": episode})
        self.sb3_list.on_rollout_start()

    def step_hook(self, count: Callable[[], None]) -> Callable[[np.ndarray], bool] | None:
        """``stop(new_obs) -> bool`` for :func:`mbtsr.episode.run_episode` (``None`` without SB3
        callbacks): after every env step ``count()`` (the agent's step counter) and ``on_step``;
        ``True`` (``on_step`` returned ``False``) ends the rollout and learning."""
        if not self.sb3_list.callbacks:
            return None
        calls = {"n": 0}

        def stop(new_obs: np.ndarray) -> bool:
            calls["n"] += 1
            if calls["n"] == 1:  # the observation of the reset, before any step
                return False
            self.sb3_list.update_locals({"new_obs": new_obs, "step": calls["n"] - 2})
            count()
            if not self.sb3_list.on_step():
                self.stopped = True
            return self.stopped
        return stop

    def episode_end(self, agent: Any, row: dict[str, Any]) -> bool:
        """``on_rollout_end`` and the plain functions after an episode; ``False``: stop."""
        go = not self.stopped
        self.sb3_list.update_locals({"row": row})
        self.sb3_list.on_rollout_end()
        for f in self.plain:
            if f({"agent": agent, "row": row}) is False:
                go = False
        return go

    def end(self) -> None:
        """``on_training_end``."""
        self.sb3_list.on_training_end()
