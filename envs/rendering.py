"""Render an episode to frames and write them as a GIF/MP4 or a PNG strip.

Headless: make the env with ``render_mode="rgb_array"``; ``import envs`` selects
``MUJOCO_GL=egl`` before MuJoCo is loaded. Frames are ``uint8`` ``[H, W, 3]`` arrays.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import gymnasium as gym
import numpy as np

from mbtsr.rollout import run_episode
from mbtsr.validation import as_array

__all__ = ["render_episode", "save_png_strip", "save_video"]


def render_episode(
    env: gym.Env,
    actions: np.ndarray,
    seed: int | None = None,
    *,
    reset_options: dict | None = None,
) -> list[np.ndarray]:
    """Reset ``env`` and render one frame before and one after each action.

    :param env: an env made with ``render_mode="rgb_array"``.
    :param actions: ``[T, m]`` actions applied open loop (clipped into the action space), via
        the one rollout loop :func:`mbtsr.rollout.run_episode`.
    :param seed: reset seed.
    :return: ``T + 1`` frames (fewer if the episode ends early).
    """
    if env.render_mode != "rgb_array":
        raise ValueError(f"env must be made with render_mode='rgb_array', got {env.render_mode!r}")
    actions = as_array("actions", actions, ndim=2)
    rec = run_episode(env, lambda obs, t: actions[t], seed=seed, options=reset_options,
                      max_steps=actions.shape[0], render=True)
    return rec.frames


def _check_frames(frames: Sequence[np.ndarray]) -> list[np.ndarray]:
    if len(frames) == 0:
        raise ValueError("frames is empty")
    out = [np.asarray(f) for f in frames]
    shape = out[0].shape
    if len(shape) != 3 or shape[2] not in (3, 4):
        raise ValueError(f"frames must be [H, W, 3|4] images, got shape {list(shape)}")
    if any(f.shape != shape for f in out):
        raise ValueError("all frames must have the same shape")
    return [f.astype(np.uint8) for f in out]


def _atomic_write(path: Path, write) -> None:
    tmp = path.with_name(path.name + ".tmp" + path.suffix)
    write(tmp)
    os.replace(tmp, path)


def save_video(frames: Sequence[np.ndarray], path: str | os.PathLike, fps: float = 50) -> Path:
    """Write ``frames`` to ``path``: ``.gif`` (Pillow via imageio) or ``.mp4`` (needs ffmpeg).

    :raises ValueError: unknown extension, or ``.mp4`` without ``imageio-ffmpeg`` installed.
    """
    import imageio.v2 as imageio

    frames = _check_frames(frames)
    path = Path(path)
    suffix = path.suffix.lower()
    if fps <= 0:
        raise ValueError(f"fps must be > 0, got {fps!r}")
    if suffix == ".gif":
        # GIF stores frame durations in ms (10 ms resolution)
        _atomic_write(path, lambda p: imageio.mimsave(p, frames, duration=1000.0 / fps, loop=0))
    elif suffix == ".mp4":
        try:
            import imageio_ffmpeg  # noqa: F401
        except ImportError:
            raise ValueError(
                "writing .mp4 needs imageio-ffmpeg (pip install imageio-ffmpeg); use .gif"
            ) from None
        _atomic_write(path, lambda p: imageio.mimsave(p, frames, fps=fps))
    else:
        raise ValueError(f"path must end in .gif or .mp4, got {path.name!r}")
    return path


def save_png_strip(frames: Sequence[np.ndarray], path: str | os.PathLike, n: int = 6) -> Path:
    """Write ``n`` evenly spaced frames (first and last included) side by side as a PNG."""
    import imageio.v2 as imageio

    frames = _check_frames(frames)
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ValueError(f"n must be an integer >= 1, got {n!r}")
    idx = np.unique(np.linspace(0, len(frames) - 1, min(n, len(frames))).round().astype(int))
    strip = np.concatenate([frames[i] for i in idx], axis=1)
    path = Path(path)
    _atomic_write(path, lambda p: imageio.imwrite(p, strip, format="png"))
    return path
