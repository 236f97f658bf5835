"""Rendering: GIF size, frame count and subsampling, compare panel, PNG stills, the world-space
drawing following the integrated path, contact marks, control plot, clear errors."""

from __future__ import annotations

import numpy as np
import pytest
from mpl_toolkits.mplot3d import proj3d
from PIL import Image

from motionflows import render
from motionflows.data.synthetic import straight_walk
from motionflows.evaluation.motion import foot_contacts, integrate_root, to_global
from motionflows.render import (
    animate,
    frame_grid,
    plot_controls,
    render_clip,
    render_still,
    world_joints,
)


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
        assert im.size[0] >= 1000  # two panels, sample and compare
    single = animate(clip.pose, clip.control, tmp_path / "s.gif", still=tmp_path / "s.png")
    with Image.open(single) as im, Image.open(tmp_path / "s.png") as still:
        assert im.n_frames == len(clip)
        assert im.size[0] >= 640
        assert still.size[0] >= 1280  # dpi 200 for papers
    # 60 fps input is subsampled to <= 20 fps
    pose60 = np.repeat(clip.pose[:4], 3, axis=0)
    ctrl60 = np.repeat(clip.control[:4], 3, axis=0) / 3
    out60 = animate(pose60, ctrl60, tmp_path / "b.gif", fps=60.0)
    with Image.open(out60) as im:
        assert im.n_frames == 4
        assert im.info["duration"] == 50


def test_a_gif_lasts_as_long_as_its_motion_at_any_frame_rate(clip, tmp_path):
    """GIF delays are whole centiseconds: at 30 fps a constant round(1000 / 30) ms delay was
    stored as 30 ms, a clip 10 % too fast. The delays now add up to T / fps."""
    for fps in (24.0, 30.0, 50.0, 20.0):
        assert abs(sum(render.gif_durations(97, fps)) - 1000 * 97 / fps) <= 5
    pose30, ctrl30 = np.repeat(clip.pose[:5], 3, axis=0), np.repeat(clip.control[:5], 3, 0) / 3
    out = animate(pose30[:14], ctrl30[:14], tmp_path / "c.gif", fps=30.0, dpi=20)
    with Image.open(out) as im:
        delays = []
        for k in range(im.n_frames):
            im.seek(k)
            delays.append(im.info["duration"])
    assert len(delays) == 7 and abs(sum(delays) - 1000 * 14 / 30) <= 5, delays


def test_animate_keeps_palette_indices_not_every_rgb_frame(clip, tmp_path):
    """A long clip's GIF must not hold every drawn RGB frame in memory at once (it did:
    ~1.5 MB a frame, an out-of-memory kill for a long sample), and a clip longer than
    ``max_seconds`` is cut, with a warning."""
    import tracemalloc

    pose, control = np.tile(clip.pose, (8, 1)), np.tile(clip.control, (8, 1))  # 96 frames
    animate(clip.pose, clip.control, tmp_path / "warm.gif", dpi=20)  # matplotlib's own setup
    tracemalloc.start()
    animate(pose, control, tmp_path / "long.gif", dpi=20)
    peak = tracemalloc.get_traced_memory()[1] / (128 * 96 * 3)  # in RGB frames at dpi 20
    tracemalloc.stop()
    assert peak < 80, peak  # ~40 (the palette's frames and the figure), ~138 before
    with pytest.warns(UserWarning, match=r"first 1 s of 4\.8 s"):
        cut = animate(pose, control, tmp_path / "cut.gif", dpi=20, max_seconds=1.0)
    with Image.open(cut) as im:
        assert im.n_frames == 20


def test_render_clip_and_plots(clip, tmp_path):
    files = render_clip(clip, tmp_path)
    assert files["gif"].exists() and files["controls"].exists() and files["still"].exists()
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
    with pytest.raises(ValueError, match="out of range"):
        render_still(clip.pose, clip.control, tmp_path / "x.png", frame=len(clip))


def _turning(clip):
    control = clip.control.copy()
    control[:, 2] = 0.08  # a left turn of 0.08 rad/frame, so the path curves
    return control


def test_drawing_follows_the_integrated_path(clip, tmp_path):
    control = _turning(clip).astype(np.float64)
    pose, truth = clip.pose.astype(np.float64), clip.pose[::-1].astype(np.float64)
    stage, n = render._stage(pose, control, truth, "t", None, 100, 20.0)
    root = np.asarray(integrate_root(control)[0])
    world = to_global(pose, control).reshape(n, -1, 3)
    world_truth = to_global(truth, control).reshape(n, -1, 3)
    for t in (0, n // 2, n - 1):
        assert stage.frame(t, 20.0).shape[1] >= 640
        np.testing.assert_allclose(stage.drawn[0], world[t], atol=1e-9)
        np.testing.assert_allclose(stage.drawn[1], world_truth[t], atol=1e-9)  # same path
        ax = stage.panels[0]["ax"]
        assert np.mean(ax.get_xlim()) == pytest.approx(root[t, 0])  # camera follows the root
        assert np.mean(ax.get_zlim()) == pytest.approx(root[t, 2])
        ahead = root[t + 3] if t + 3 < n else 2 * root[t] - root[t - 3]
        x_now, x_ahead = (proj3d.proj_transform(*p, ax.get_proj())[0] for p in (root[t], ahead))
        assert x_now < x_ahead  # the camera turns with the path: walks to the right
    np.testing.assert_allclose(world_joints(pose, control), world)


def test_camera_swings_round_a_turn_to_stay_on_the_walkers_right():
    control = np.tile([0.06, 0.0, np.pi / 40], (80, 1))  # 4 s, 270 degrees to the left
    root, yaw = (np.asarray(a) for a in integrate_root(control))
    azimuth = np.radians(render._camera_azimuths(yaw, 20.0))
    step = np.diff(root, axis=0)
    right = np.stack([-step[:, 2], step[:, 0]], 1) / np.linalg.norm(step, axis=1)[:, None]
    camera = np.stack([np.sin(azimuth), np.cos(azimuth)], 1)[:-1]  # towards (x, z)
    assert np.all((camera * right).sum(1) > 0.2)  # a fixed camera would end up at -1


def test_contact_marks_show_a_dragged_foot_as_a_streak(clip):
    # a frozen pose dragged along the path: the planted foot's footprints spread over the
    # root's whole path; a walk's footprints stay in place during each contact
    frozen = np.repeat(clip.pose[:1], len(clip), axis=0)
    straight = clip.control * [1.0, 0.0, 0.0]  # no turn: footprints move like the root
    world = world_joints(frozen, straight)
    low, prints = render._contact_marks(world)
    contact = foot_contacts(frozen)
    assert contact.any()
    np.testing.assert_array_equal(np.isfinite(prints[..., 0]), contact)
    foot = int(np.argmax(contact.sum(0)))
    spread = np.ptp(prints[contact[:, foot], foot, 2])
    path = np.asarray(integrate_root(straight)[0])[contact[:, foot], 2]
    assert spread == pytest.approx(np.ptp(path), abs=1e-6) and spread > 0.3
    assert np.all(prints[contact][:, 1] == 0.0)  # drawn on the floor
    walk_low, walk_prints = render._contact_marks(world_joints(clip.pose, clip.control))
    step = np.abs(np.diff(walk_prints[..., 2], axis=0))  # NaN unless in contact at both
    assert np.nanmax(step) < 0.03 < np.ptp(np.nan_to_num(walk_prints[..., 2]))
