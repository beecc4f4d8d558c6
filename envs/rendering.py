"""Render an episode to frames and write them as a GIF/MP4 or a PNG strip.

Headless: make the env with ``render_mode="rgb_array"``; ``import envs`` selects
``MUJOCO_GL=egl`` before MuJoCo is loaded. Frames are ``uint8`` ``[H, W, 3]`` arrays.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Sequence
from pathlib import Path

import gymnasium as gym
import numpy as np

from mbtsr.episode import run_episode
from mbtsr.io import atomic_write
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
        the one rollout loop :func:`mbtsr.episode.run_episode`.
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
    if len(shape) != 3 or shape[2] not in (3, 4) or shape[0] < 1 or shape[1] < 1:
        raise ValueError(f"frames must be [H, W, 3|4] images with H, W >= 1, got shape "
                         f"{list(shape)}")
    if any(f.shape != shape for f in out):
        raise ValueError("all frames must have the same shape")
    for i, f in enumerate(out):
        if f.dtype != np.uint8 and (f.dtype.kind not in "iuf" or not np.all(np.isfinite(f))
                                    or f.min() < 0 or f.max() > 255):
            raise ValueError(f"frames[{i}] must be uint8 or real values in [0, 255], got "
                             f"dtype {f.dtype}")
    return [f.astype(np.uint8) for f in out]


def save_video(frames: Sequence[np.ndarray], path: str | os.PathLike, fps: float = 50) -> Path:
    """Write ``frames`` to ``path`` as an H.264 ``.mp4`` (imageio-ffmpeg) or a ``.gif`` (Pillow);
    without ffmpeg an ``.mp4`` becomes a ``.gif`` with a warning (docs/environments.md,
    "Rendering").

    :param frames: ``[H, W, 3|4]`` images, all the same shape.
    :param path: ends in ``.mp4`` or ``.gif``; written atomically (temp file then rename).
    :param fps: frames per second, > 0.
    :return: the path actually written (``.gif`` after a fallback).
    :raises ValueError: unknown extension, empty or mismatched frames, ``fps <= 0``.
    """
    frames = _check_frames(frames)
    path = Path(path)
    suffix = path.suffix.lower()
    if isinstance(fps, bool) or not np.isfinite(fps) or fps <= 0:
        raise ValueError(f"fps must be a finite number > 0, got {fps!r}")
    if suffix not in (".gif", ".mp4"):
        raise ValueError(f"path must end in .gif or .mp4, got {path.name!r}")
    if suffix == ".mp4":
        exe = _ffmpeg_exe()
        if exe is not None:
            atomic_write(path, lambda p: _write_mp4(frames, p, fps))
            return path
        warnings.warn(
            "ffmpeg not found (pip install imageio-ffmpeg): writing a GIF instead of "
            f"{path.name}",
            RuntimeWarning,
            stacklevel=2,
        )
        path = path.with_suffix(".gif")
    import imageio.v2 as imageio

    # GIF stores frame durations in ms (10 ms resolution)
    atomic_write(path, lambda p: imageio.mimsave(p, frames, duration=1000.0 / fps, loop=0))
    return path


def _ffmpeg_exe() -> str | None:
    """Path of the ffmpeg binary imageio-ffmpeg uses, or None when there is none."""
    try:
        import imageio_ffmpeg

        return imageio_ffmpeg.get_ffmpeg_exe()
    except (ImportError, RuntimeError):
        return None


def _write_mp4(frames: list[np.ndarray], path: Path, fps: float) -> None:
    import imageio_ffmpeg

    h, w = frames[0].shape[:2]
    pad = ((0, h % 2), (0, w % 2), (0, 0))
    writer = imageio_ffmpeg.write_frames(
        str(path),
        (w + w % 2, h + h % 2),
        fps=fps,
        codec="libx264",
        pix_fmt_in="rgb24",
        pix_fmt_out="yuv420p",
        macro_block_size=1,
        ffmpeg_log_level="error",
    )
    writer.send(None)  # start the ffmpeg process
    try:
        for f in frames:
            writer.send(np.ascontiguousarray(np.pad(f[..., :3], pad, mode="edge")))
    finally:
        writer.close()


def save_png_strip(frames: Sequence[np.ndarray], path: str | os.PathLike, n: int = 6) -> Path:
    """Write ``n`` evenly spaced frames (first and last included) side by side as a PNG."""
    import imageio.v2 as imageio

    frames = _check_frames(frames)
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ValueError(f"n must be an integer >= 1, got {n!r}")
    idx = np.unique(np.linspace(0, len(frames) - 1, min(n, len(frames))).round().astype(int))
    strip = np.concatenate([frames[i] for i in idx], axis=1)
    path = Path(path)
    atomic_write(path, lambda p: imageio.imwrite(p, strip, format="png"))
    return path
