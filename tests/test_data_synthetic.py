"""Synthetic locomotion: deterministic, plausible ranges, planted feet, gait follows speed."""

from __future__ import annotations

import numpy as np
import pytest

from motionflows.data import register_skeleton
from motionflows.data.bvh import parse_bvh
from motionflows.data.features import world_from_features
from motionflows.data.skeleton import (
    BANDAI,
    SkeletonMapping,
    VirtualJoint,
    get_skeleton,
    joint_positions,
)
from motionflows.data.synthetic import generate, straight_walk


@pytest.fixture(scope="module")
def clips():
    return generate(8, 12.0, seed=11)


def test_deterministic_in_seed(clips):
    again = generate(2, 12.0, seed=11)
    np.testing.assert_array_equal(again[1].pose, clips[1].pose)
    other = generate(2, 12.0, seed=12)
    assert not np.allclose(other[0].pose, clips[0].pose)
    assert clips[0].pose.shape == (240, 63) and clips[0].fps == 20.0


def test_ranges_cover_locomotion(clips):
    pose = np.concatenate([c.pose for c in clips]).reshape(-1, 21, 3)
    control = np.concatenate([c.control for c in clips]) * 20.0
    assert 0.78 < pose[:, 0, 1].mean() < 0.95  # hip height (m)
    assert control[:, 0].max() > 2.0  # runs
    assert control[:, 0].min() < -0.3  # walks backwards
    assert np.abs(control[:, 1]).max() > 0.25  # sidesteps
    assert np.abs(control[:, 2]).max() > 0.3  # turns (rad/s)
    assert np.hypot(control[:, 0], control[:, 1]).max() < 3.8
    # feet reach the floor; the head stays above 1.2 m
    assert pose[:, [3, 4, 7, 8], 1].min() == pytest.approx(0.0, abs=1e-6)
    assert pose[:, 12, 1].min() > 1.1
    assert np.percentile(pose[:, 0, 1], 1) > 0.72  # no deep crouches


def test_feet_are_planted_in_stance():
    clip = straight_walk(1.3, seconds=6.0, seed=3)
    world = world_from_features(clip.pose, clip.control)
    for toe in (4, 8):
        low = world[:-1, toe, 1] < 0.01
        speed = np.linalg.norm(np.diff(world[:, toe, [0, 2]], axis=0), axis=-1) * 20
        assert low.mean() > 0.3
        assert np.median(speed[low]) < 0.05  # m/s while on the floor (the body moves 1.3)


def _cadence(clip):
    """Dominant frequency (Hz) of the left ankle's forward position."""
    z = clip.pose.reshape(-1, 21, 3)[:, 3, 2]
    z = z - z.mean()
    spec = np.abs(np.fft.rfft(z * np.hanning(len(z))))
    freqs = np.fft.rfftfreq(len(z), 1 / clip.fps)
    return freqs[np.argmax(spec[1:]) + 1]


def test_gait_frequency_follows_speed():
    slow = _cadence(straight_walk(0.8, seconds=10.0, seed=1))
    fast = _cadence(straight_walk(1.7, seconds=10.0, seed=1))
    run = _cadence(straight_walk(3.0, seconds=10.0, seed=1))
    assert slow < fast < run
    assert 0.6 < slow < 1.2 and 1.2 < run < 2.0


def test_style_varies_between_clips(clips):
    stds = [c.pose.reshape(-1, 21, 3)[:, 15, 2].std() for c in clips]  # hand swing
    assert max(stds) > 1.3 * min(stds)


def test_skeleton_registry_and_virtual_joint():
    assert get_skeleton("bandai") is BANDAI and get_skeleton("cmu").unit == pytest.approx(
        0.0254 / 0.45
    )
    with pytest.raises(ValueError, match="known: bandai, cmu"):
        get_skeleton("nope")
    with pytest.raises(ValueError, match="21"):
        SkeletonMapping("bad", ("Hips",), 1.0)
    with pytest.raises(ValueError, match="twice"):
        SkeletonMapping("dup", ("Hips",) * 21, 1.0)
    # a one-joint file mapped with virtual joints: a rigid point rotates with its parent
    text = (
        "HIERARCHY\nROOT R\n{\n OFFSET 0 0 0\n CHANNELS 6 Xposition Yposition Zposition "
        "Zrotation Xrotation Yrotation\n End Site\n {\n  OFFSET 0 1 0\n }\n}\nMOTION\n"
        "Frames: 1\nFrame Time: 0.1\n1 2 3 0 0 90\n"
    )
    joints = ("R",) + tuple(VirtualJoint("R", (float(k + 1), 0.0, 0.0)) for k in range(20))
    mapping = SkeletonMapping("unit-test", joints, unit=0.5)
    register_skeleton(mapping, overwrite=True)
    pos = joint_positions(parse_bvh(text), "unit-test")
    np.testing.assert_allclose(pos[0, 0], [0.5, 1.0, 1.5])
    # Ry(90) maps (1,0,0) to (0,0,-1): joint 1 = (1,2,3) + (0,0,-1), times 0.5
    np.testing.assert_allclose(pos[0, 1], [0.5, 1.0, 1.0])
    with pytest.raises(ValueError, match="exists"):
        register_skeleton(mapping)
    roundtrip = SkeletonMapping.from_dict(mapping.to_dict())
    assert roundtrip == mapping
