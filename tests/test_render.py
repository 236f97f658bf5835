"""Rendering: GIF frame count and subsampling, compare panel, control plot, clear errors."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from motionflows.data.synthetic import straight_walk
from motionflows.render import animate, frame_grid, plot_controls, render_clip


@pytest.fixture(scope="module")
def clip():
    c = straight_walk(1.1, seconds=0.6, seed=0)
    return c


def test_animate_writes_gif_with_expected_frames(clip, tmp_path):
    out = animate(
        clip.pose,
        clip.control,
        tmp_path / "a.gif",
        fps=20.0,
        title="walk",
        compare=clip.pose[::-1].copy(),
    )
    with Image.open(out) as im:
        assert im.n_frames == len(clip)
        assert im.size[0] < 600  # small
    # 60 fps input is subsampled to <= 20 fps
    pose60 = np.repeat(clip.pose[:4], 3, axis=0)
    ctrl60 = np.repeat(clip.control[:4], 3, axis=0) / 3
    out60 = animate(pose60, ctrl60, tmp_path / "b.gif", fps=60.0)
    with Image.open(out60) as im:
        assert im.n_frames == 4
        assert im.info["duration"] == 50


def test_render_clip_and_plots(clip, tmp_path):
    files = render_clip(clip, tmp_path)
    assert files["gif"].exists() and files["controls"].exists()
    with Image.open(files["controls"]) as im:
        assert im.size[0] > 200
    assert frame_grid(clip.pose, clip.control, tmp_path / "g.png", n=3).exists()


def test_bad_inputs_are_clear(clip, tmp_path):
    with pytest.raises(ValueError, match=r"\(T, 63\)"):
        animate(clip.pose[:, :60], clip.control, tmp_path / "x.gif")
    with pytest.raises(ValueError, match="metres"):
        animate(clip.pose * 100, clip.control, tmp_path / "x.gif")
    with pytest.raises(ValueError, match=r"\(T, 3\)"):
        plot_controls(clip.control[:, :2], tmp_path / "c.png")
