"""Env wrappers shared by the tests."""

from __future__ import annotations

import gymnasium as gym


class TerminateAfter(gym.Wrapper):
    """Terminates every episode after ``k`` steps (``terminated=True``)."""

    def __init__(self, env: gym.Env, k: int) -> None:
        super().__init__(env)
        self.k, self.t = k, 0

    def reset(self, **kwargs):
        self.t = 0
        return self.env.reset(**kwargs)

    def step(self, action):
        obs, r, term, trunc, info = self.env.step(action)
        self.t += 1
        return obs, r, term or self.t >= self.k, trunc, info
