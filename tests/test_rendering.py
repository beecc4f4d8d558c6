"""Episode videos: MP4 through imageio-ffmpeg, GIF as the fallback (written and read back)."""

from __future__ import annotations

import imageio.v2 as imageio
import imageio_ffmpeg
import numpy as np
import pytest

from envs import rendering
from envs.rendering import save_video


def _frames(n: int, h: int, w: int) -> list[np.ndarray]:
    """``n`` flat frames whose colour changes frame to frame (easy to recognise after H.264)."""
    rng = np.random.default_rng(0)
    colours = rng.integers(30, 226, size=(n, 3))
    return [np.broadcast_to(c, (h, w, 3)).astype(np.uint8) for c in colours]


def _read_mp4(path) -> tuple[dict, list[np.ndarray]]:
    gen = imageio_ffmpeg.read_frames(str(path))
    meta = next(gen)
    w, h = meta["size"]
    frames = [np.frombuffer(b, np.uint8).reshape(h, w, 3) for b in gen]
    return meta, frames


def test_mp4_round_trip_keeps_frame_count_size_fps_and_colours(tmp_path):
    frames = _frames(12, 48, 64)
    out = save_video(frames, tmp_path / "episode.mp4", fps=25)
    assert out == tmp_path / "episode.mp4"
    assert out.read_bytes()[4:8] == b"ftyp"  # an MP4 container, not a renamed GIF
    meta, back = _read_mp4(out)
    assert meta["size"] == (64, 48)
    assert meta["fps"] == pytest.approx(25)
    assert meta["codec"].startswith("h264")
    assert len(back) == len(frames)
    for f, g in zip(frames, back):  # lossy codec: flat colours survive to a few levels
        np.testing.assert_allclose(g.mean(axis=(0, 1)), f[0, 0], atol=6)
    assert [p.name for p in tmp_path.iterdir()] == ["episode.mp4"]  # no temp file left


def test_mp4_pads_odd_sizes_and_drops_alpha(tmp_path):
    frames = [np.dstack([f, np.full(f.shape[:2], 255, np.uint8)]) for f in _frames(3, 31, 45)]
    meta, back = _read_mp4(save_video(frames, tmp_path / "odd.mp4", fps=10))
    assert meta["size"] == (46, 32)
    assert len(back) == 3


def test_gif_is_the_fallback_when_ffmpeg_is_missing(tmp_path, monkeypatch):
    monkeypatch.setattr(rendering, "_ffmpeg_exe", lambda: None)
    frames = _frames(5, 16, 20)
    with pytest.warns(RuntimeWarning, match="GIF instead of episode.mp4"):
        out = save_video(frames, tmp_path / "episode.mp4", fps=20)
    assert out == tmp_path / "episode.gif"
    back = imageio.mimread(out)
    assert len(back) == 5 and back[0].shape[:2] == (16, 20)
    assert not (tmp_path / "episode.mp4").exists()


@pytest.mark.parametrize("bad", [0, -1.0, float("nan"), float("inf"), True])
def test_bad_fps_is_rejected_by_name(tmp_path, bad):
    with pytest.raises(ValueError, match="fps"):
        save_video(_frames(2, 8, 8), tmp_path / "x.mp4", fps=bad)


def test_bad_extension_and_empty_frames_are_rejected(tmp_path):
    with pytest.raises(ValueError, match=r"\.gif or \.mp4"):
        save_video(_frames(2, 8, 8), tmp_path / "x.avi")
    with pytest.raises(ValueError, match="empty"):
        save_video([], tmp_path / "x.mp4")
