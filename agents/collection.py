"""Collection (Algorithm 1, step (a)): training rollouts in the real env, an excitation signal or
a planner's actions plus exploration noise (:func:`mbtsr.episode.run_episode`)."""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from agents.config import CollectionConfig
from agents.tasks import EnvSpec, StateMap
from mbtsr import excitation
from mbtsr.episode import EpisodeRecord, as_policy, run_episode
from mbtsr.trajectory import Trajectory

__all__ = ["Collector"]


class Collector:
    """Training rollouts of the agent in ``env``.

    :param env: the training env.
    :param spec: its :class:`~agents.tasks.EnvSpec` (episode length, action box, ``dt``).
    :param config: the agent's ``collection`` settings.
    :param state_map: observation -> model state (a rollout's trajectory is in model states).
    """

    def __init__(self, env: gym.Env, spec: EnvSpec, config: CollectionConfig,
                 state_map: StateMap) -> None:
        self.env, self.spec, self.config, self.state_map = env, spec, config, state_map
        # continue_rollouts: ((obs, info), steps so far, the TimeLimit's step count) of the env's
        # running episode
        self._handover: tuple[tuple[np.ndarray, dict], int, int | None] | None = None

    def forget(self) -> None:
        """The env was (or may have been) used elsewhere: the next rollout starts from a reset."""
        self._handover = None

    def excitation(self, T: int, seed: int) -> np.ndarray:
        """``[T, m]`` excitation: a unit-std signal x ``excitation_scale`` x the half-range."""
        col, spec = self.config, self.spec
        if col.excitation == "filtered_gaussian":
            sig = excitation.unit_filtered_gaussian(T, spec.act_dim, window=col.excitation_window,
                                                    seed=seed)
        else:
            sig = excitation.multisine(T, spec.act_dim, seed=seed) / excitation.multisine_std(
                5, 1.0)
        mid, half = 0.5 * (spec.u_max + spec.u_min), 0.5 * (spec.u_max - spec.u_min)
        return np.clip(mid + half * col.excitation_scale * sig, spec.u_min, spec.u_max)

    def exploration_noise(self, T: int, seed: int) -> np.ndarray:
        """``[T, m]`` noise on a training rollout's planned actions: Gaussian, std
        ``exploration_std`` x the half-range, a moving average of ``exploration_window`` steps."""
        col, spec = self.config, self.spec
        half = 0.5 * (spec.u_max - spec.u_min)
        unit = excitation.unit_filtered_gaussian(T, spec.act_dim, window=col.exploration_window,
                                                 seed=seed)
        return col.exploration_std * half * unit

    def rollout(
        self,
        policy: Any,
        *,
        episode: int,
        reset_seed: int,
        signal_seed: int,
        max_steps: int | None = None,
        render: bool = False,
        stop: Any = None,
    ) -> tuple[EpisodeRecord, Trajectory]:
        """One training rollout: the excitation signal (``policy=None``) or ``policy``'s
        actions (SB3-style ``predict``) plus exploration noise, ``collection.rollout_steps``
        long (or to the episode's end; at most ``max_steps``).

        :param episode: the agent's episode index (the trajectory's ``meta``).
        :param reset_seed: the env's reset seed; ``signal_seed``: the excitation's or noise's.
        :param render: keep rendered frames in the record.
        :param stop: ``stop(obs) -> bool`` of :func:`mbtsr.episode.run_episode`, or ``None``.
        :return: ``(record, trajectory)``: the model-state trajectory ``x [T+1, n]``, ``u [T, m]``.
        """
        spec = self.spec
        start, done_steps, elapsed = self._handover or (None, 0, None)
        self._handover = None
        if start is not None and _elapsed_steps(self.env) != elapsed:
            warnings.warn("collection.continue_rollouts: the env was stepped or reset since the "
                          "last training rollout, so this one starts from a reset", stacklevel=3)
            start, done_steps = None, 0
        T = min(self.config.rollout_steps or spec.episode_steps, spec.episode_steps - done_steps)
        if max_steps is not None:
            T = min(T, max_steps)
        if policy is None:
            U = self.excitation(T, signal_seed)

            def act(obs: np.ndarray, t: int) -> np.ndarray:
                return U[t]
        else:
            noise, planned = self.exploration_noise(T, signal_seed), as_policy(policy)

            def act(obs: np.ndarray, t: int) -> np.ndarray:
                return planned(obs, t) + noise[t]

        rec = run_episode(self.env, act, seed=reset_seed, max_steps=T, render=render, start=start,
                          stop=stop)
        traj = Trajectory(
            self.state_map.state(rec.obs), rec.actions, spec.dt,
            meta={"episode": episode, "seed": None if start is not None else reset_seed},
        )
        if (self.config.continue_rollouts and not (rec.terminated or rec.truncated)
                and done_steps + rec.T < spec.episode_steps):
            self._handover = ((rec.obs[-1].copy(), dict(rec.info)), done_steps + rec.T,
                              _elapsed_steps(self.env))
        return rec, traj


def save_video(frames: list, run_dir: str | Path, episode: int, dt: float | None) -> None:
    """``<run_dir>/videos/episode_<episode>.mp4`` (:func:`envs.rendering.save_video` writes a
    ``.gif`` instead, with a warning, when no ffmpeg is available)."""
    if not frames:
        return
    from envs.rendering import save_video as write

    folder = Path(run_dir) / "videos"
    folder.mkdir(parents=True, exist_ok=True)
    write(frames, folder / f"episode_{episode:04d}.mp4", fps=1.0 / dt if dt else 30.0)


def _elapsed_steps(env: gym.Env | None) -> int | None:
    """The step count of ``env``'s ``TimeLimit`` since its last reset (``None`` without one)."""
    try:
        return int(env.get_wrapper_attr("_elapsed_steps"))
    except (AttributeError, TypeError, ValueError):
        return None
