"""Feature recipe: controls, root frame, resampling, augmentation involutions, real data."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from motionflows.config import DataConfig
from motionflows.data import clip_from_bvh
from motionflows.data.augment import (
    augment_clips,
    lock_clip,
    mirror_clip,
    reverse_clip,
    reverse_time,
    tempo_clip,
)
from motionflows.data.features import (
    ROOT_SIGMA_S,
    carry_to_next_root,
    features_from_positions,
    integrate_control,
    resample,
    world_from_features,
)
from motionflows.data.names import JOINT_NAMES, NUM_JOINTS
from motionflows.data.synthetic import generate, straight_walk
from motionflows.evaluation.motion import bone_lengths, foot_sliding

DEV = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "bandai_locomotion_dev"


def _t_pose(n):
    """A rigid T-pose-ish body (n, 21, 3) facing +z with left = +x."""
    base = np.zeros((NUM_JOINTS, 3))
    base[:, 1] = 1.0
    for name, x, y in [
        ("LeftUpLeg", 0.1, 0.9),
        ("RightUpLeg", -0.1, 0.9),
        ("LeftArm", 0.2, 1.4),
        ("RightArm", -0.2, 1.4),
        ("LeftFoot", 0.1, 0.1),
        ("RightFoot", -0.1, 0.1),
        ("LeftToe", 0.1, 0.0),
        ("RightToe", -0.1, 0.0),
        ("Hips", 0.0, 0.9),
    ]:
        base[JOINT_NAMES.index(name)] = (x, y, 0.0)
    return np.repeat(base[None], n, 0)


def _rot(p, yaw):
    c, s = np.cos(yaw), np.sin(yaw)
    x, z = p[..., 0], p[..., 2]
    return np.stack([c * x + s * z, p[..., 1], -s * x + c * z], -1)


def test_rigid_translation_gives_exact_controls():
    n, fps = 60, 20.0
    body = _t_pose(n)
    yaw0 = 0.7  # facing direction (sin, 0, cos)(yaw0)
    world = _rot(body, yaw0)
    speed, side = 1.2, 0.3  # m/s forward and to the left
    fwd = np.array([np.sin(yaw0), 0, np.cos(yaw0)])
    left = np.array([np.cos(yaw0), 0, -np.sin(yaw0)])
    t = np.arange(n)[:, None, None] / fps
    world = world + t * (speed * fwd + side * left)
    clip = features_from_positions(world, fps, fps)
    np.testing.assert_allclose(clip.control[:, 0], speed / fps, atol=1e-6)
    np.testing.assert_allclose(clip.control[:, 1], side / fps, atol=1e-6)
    np.testing.assert_allclose(clip.control[:, 2], 0.0, atol=1e-6)
    pose = clip.pose.reshape(-1, NUM_JOINTS, 3)
    # root frame: character faces +z, left arm on +x, feet on the floor
    assert (pose[:, JOINT_NAMES.index("LeftArm"), 0] > 0.15).all()
    assert pose[:, [3, 4, 7, 8], 1].min() == pytest.approx(0.0, abs=1e-6)
    assert pose[:, 0, 1].mean() == pytest.approx(0.9, abs=1e-6)


def test_the_gait_cycle_stays_in_the_pose_not_in_the_control():
    """A body walking at 1.2 m/s whose hips sway 3 cm sideways once per stride (1 Hz) and
    surge 2 cm forward twice per stride: the control must say how the character travels
    (constant speed), not the stride (with Holden's 0.05 s root smoothing the sideways
    control swings by +-0.18 m/s and the forward one by +-0.24 m/s), and the sway must be
    in the pose, so the world motion still rebuilds exactly."""
    n, fps, speed = 200, 20.0, 1.2
    t = np.arange(n) / fps
    sway = 0.03 * np.sin(2 * np.pi * 1.0 * t)
    surge = 0.02 * np.sin(2 * np.pi * 2.0 * t)
    body = _t_pose(n)
    offset = np.stack([sway, np.zeros(n), speed * t + surge], -1)
    world = body + offset[:, None, :]
    clip = features_from_positions(world, fps, fps)
    core = slice(20, -20)
    np.testing.assert_allclose(
        clip.control[core, 0], speed / fps, atol=0.1 * 0.02 * 4 * np.pi / fps
    )
    np.testing.assert_allclose(clip.control[core, 1], 0.0, atol=0.2 * 0.03 * 2 * np.pi / fps)
    hip_x = clip.pose[core, 0]  # the sway, in the root frame (+x = left)
    assert hip_x.max() - hip_x.min() > 0.8 * 0.06
    rebuilt = world_from_features(clip.pose, clip.control)
    np.testing.assert_allclose(
        rebuilt - rebuilt[:1, :1],
        world[:-1] - world[:1, :1],
        atol=1e-5,  # float32 clip
    )


def test_turning_left_is_positive_and_integrates_back():
    n, fps = 80, 20.0
    rate = 0.5  # rad/s counter-clockwise
    yaw = rate * np.arange(n) / fps
    body = _t_pose(n)
    # walk on a circle of radius r: centre on the left of the start
    r = 2.0
    pos = np.stack([r - r * np.cos(yaw), np.zeros(n), r * np.sin(yaw)], -1)
    world = _rot(body, yaw[:, None]) + pos[:, None, :]
    clip = features_from_positions(world, fps, fps)
    core = clip.control[10:-10]
    np.testing.assert_allclose(core[:, 2], rate / fps, atol=2e-4)
    # the root is smoothed over time: a circle of radius r shrinks by exp(-(w sigma)^2 / 2)
    shrink = np.exp(-0.5 * (rate * ROOT_SIGMA_S) ** 2)
    np.testing.assert_allclose(core[:, 0], shrink * r * rate / fps, rtol=3e-3)
    rebuilt = world_from_features(clip.pose, clip.control)
    # rebuilt world equals the original up to the start pose (rigid transform)
    rp, _ = integrate_control(clip.control)
    assert np.linalg.norm(rp[-1]) == pytest.approx(np.linalg.norm(pos[n - 1] - pos[0]), rel=0.02)
    assert rebuilt.shape == (n - 1, NUM_JOINTS, 3)


def test_resample_keeps_speed():
    x = np.arange(31, dtype=float)[:, None] * 0.05  # 1.5 m/s at 30 fps
    y = resample(x, 30.0, 20.0)
    assert y.shape[0] == 21
    np.testing.assert_allclose(np.diff(y[:, 0]), 0.075)
    # a BVH's rounded "Frame Time: 0.0333333" at a target of 30 fps: copied, not
    # interpolated 1e-6 of a frame off (which lost the last frame)
    np.testing.assert_array_equal(resample(x, 1 / 0.0333333, 30.0), x)


def test_synthetic_straight_walk_control_matches_speed():
    for speed in (1.1, 2.5, -0.8):
        clip = straight_walk(speed, seconds=5.0, seed=1)
        core = clip.control[5:-5]
        assert core[:, 0].mean() == pytest.approx(speed / 20.0, rel=0.03)
        assert abs(core[:, 1].mean()) < 0.005 / 20 * 20  # < 5 mm/frame sideways drift
        assert abs(core[:, 2].mean()) < 0.01 / 20.0


def test_mirror_and_reverse_are_involutions():
    clip = generate(1, 4.0, seed=3)[0]
    twice = mirror_clip(mirror_clip(clip))
    np.testing.assert_array_equal(twice.pose, clip.pose)
    np.testing.assert_array_equal(twice.control, clip.control)
    back = reverse_clip(reverse_clip(clip))
    np.testing.assert_allclose(back.pose, clip.pose)
    np.testing.assert_allclose(back.control, clip.control, atol=1e-7)
    # they do something
    assert not np.allclose(mirror_clip(clip).pose, clip.pose)
    assert not np.allclose(reverse_clip(clip).control, clip.control)


def test_reverse_control_is_the_true_backward_step():
    clip = generate(1, 4.0, seed=4)[0]
    pos, yaw = integrate_control(clip.control)
    _, rc = reverse_time(clip.pose, clip.control)
    # integrate the reversed control from the last point with the last heading
    rpos, _ = integrate_control(rc[:-1], yaw0=yaw[-2], start=pos[-2])
    np.testing.assert_allclose(rpos[-1], pos[0], atol=1e-4)


def test_tempo_replays_the_take_at_another_speed_with_the_same_strides():
    clip = generate(1, 6.0, seed=6)[0]
    # r = 1: the take again, but for its last frame (whose loss moves the root smoothing's
    # boundary: compare away from the end, 3 sigma of the root's Gaussian)
    same = tempo_clip(clip, 1.0)
    k = len(clip.pose) - 1 - int(3 * ROOT_SIGMA_S * clip.fps) - 1
    np.testing.assert_allclose(same.pose[:k], clip.pose[:k], atol=1e-5)
    np.testing.assert_allclose(same.control[:k], clip.control[:k], atol=1e-5)
    slow = tempo_clip(clip, 0.8)
    n = len(clip.pose)
    assert len(slow.pose) == int(np.floor((n - 1) / 0.8 + 1e-6)) and slow.meta["tempo"] == 0.8
    # the same path in the world, walked at 0.8 times the speed
    path = np.linalg.norm(clip.control[:-1, :2], axis=-1).sum()
    slow_path = np.linalg.norm(slow.control[:, :2], axis=-1).sum()
    assert slow_path == pytest.approx(path, rel=0.02)
    speed = np.linalg.norm(clip.control[:, :2], axis=-1).mean()
    assert np.linalg.norm(slow.control[:, :2], axis=-1).mean() == pytest.approx(
        0.8 * speed, rel=0.03
    )
    # the same poses, more of them: every slow frame is close to some frame of the take
    joints = slow.pose.reshape(-1, NUM_JOINTS, 3)
    orig = clip.pose.reshape(-1, NUM_JOINTS, 3)
    nearest = np.abs(joints[:, None] - orig[None]).max(axis=(2, 3)).min(axis=1)
    assert np.median(nearest) < 0.03
    with pytest.raises(ValueError, match="tempo"):
        tempo_clip(clip, 0.0)
    # augment_clips adds each training take at 1/tempo and tempo times its speed
    out = augment_clips([clip], mirror=True, reverse=False, tempo=1.25)
    assert sorted(round(c.meta.get("tempo", 1.0), 3) for c in out) == [0.8, 0.8, 1, 1, 1.25, 1.25]


@pytest.mark.parametrize(
    "tempo, replay, rates",
    [
        (1.25, "slower", [0.8]),
        (0.8, "slower", [0.8]),
        (1.25, "faster", [1.25]),
        (1.0, "slower", []),
    ],
)
def test_tempo_replay_keeps_one_side(tempo, replay, rates):
    """``tempo_replay``: only the slower (longer strides for the speed) or only the faster
    replays, whichever way ``tempo`` is written; ``tempo`` 1 stays off."""
    clip = generate(1, 4.0, seed=6)[0]
    out = augment_clips([clip], mirror=True, reverse=False, tempo=tempo, tempo_replay=replay)
    got = sorted(round(c.meta.get("tempo", 1.0), 3) for c in out)
    assert got == sorted([1, 1] + 2 * rates)
    slow = [c for c in out if c.meta.get("tempo", 1.0) < 1]
    assert all(len(c.pose) > len(clip.pose) for c in slow)
    with pytest.raises(ValueError, match="tempo_replay"):
        augment_clips([clip], mirror=False, reverse=False, tempo=1.25, tempo_replay="slow")
    with pytest.raises(ValueError, match="data.tempo_replay"):
        DataConfig(tempo=1.25, tempo_replay="slow")


def test_mirror_swaps_left_right_and_turn_sign():
    clip = generate(1, 4.0, seed=5)[0]
    m = mirror_clip(clip)
    p, q = clip.pose.reshape(-1, 21, 3), m.pose.reshape(-1, 21, 3)
    np.testing.assert_allclose(q[:, 13, 0], -p[:, 17, 0])
    np.testing.assert_allclose(m.control[:, 2], -clip.control[:, 2])
    np.testing.assert_allclose(m.control[:, 0], clip.control[:, 0])


@pytest.mark.skipif(not DEV.is_dir(), reason="../shared/data not present")
def test_dev_files_load_with_plausible_height_and_speed():
    files = sorted(DEV.glob("*.bvh"))
    assert len(files) >= 200
    walk_speeds, turns = [], {}
    for f in files:
        clip = clip_from_bvh(f)
        assert clip.pose.dtype == np.float32 and np.isfinite(clip.pose).all()
        hip = clip.pose[:, 1].mean()
        assert 0.7 <= hip <= 1.1, (f.name, hip)
        content = f.stem.split("_")[1]
        if content == "walk":
            walk_speeds.append(clip.control[:, 0].mean() * clip.fps)
        turns.setdefault(content, []).append(np.degrees(clip.control[:, 2].sum()))
    assert 0.8 <= np.median(walk_speeds) <= 1.5
    assert 60 < np.mean(turns["walk-turn-left"]) < 110
    assert -110 < np.mean(turns["walk-turn-right"]) < -60


@pytest.mark.skipif(not DEV.is_dir(), reason="../shared/data not present")
def test_pseudo_fingertip_follows_forearm_and_is_not_a_copy():
    clip = clip_from_bvh(DEV / "dataset-2_walk_normal_001.bvh")
    p = clip.pose.reshape(-1, 21, 3)
    for elbow, hand, tip in ((14, 15, 16), (18, 19, 20)):
        fore = p[:, hand] - p[:, elbow]
        bone = p[:, tip] - p[:, hand]
        np.testing.assert_allclose(np.linalg.norm(bone, axis=-1), 0.08, atol=1e-3)
        cos = np.sum(fore * bone, -1) / np.linalg.norm(fore, axis=-1) / 0.08
        assert cos.mean() > 0.9
    # walking backwards has negative forward control; run is faster than walk
    back = clip_from_bvh(DEV / "dataset-1_walk-back_active_001.bvh")
    assert back.control[:, 0].mean() * 20 < -0.5
    run = clip_from_bvh(DEV / "dataset-2_run_normal_001.bvh", fps=60.0)
    assert run.fps == 60.0 and run.control[:, 0].mean() * 60 > 1.8


def test_carry_to_next_root_keeps_joints_still_in_the_world():
    """Poses built frame by frame with carry_to_next_root stand still in the world on their
    control (to_global gives frame 0 at every frame), while a turning, sideways control
    moves the root: the carry undoes exactly the root's move and turn."""
    from motionflows.evaluation.motion import to_global

    rng = np.random.default_rng(0)
    t = 7
    control = np.stack(
        [rng.uniform(0.02, 0.1, t), rng.uniform(-0.03, 0.03, t), rng.uniform(-0.2, 0.2, t)], -1
    )
    pose = [rng.normal(size=NUM_JOINTS * 3)]
    for i in range(1, t):
        pose.append(carry_to_next_root(pose[-1], control[i - 1]))
    pose = np.stack(pose)
    world = to_global(pose, control)
    np.testing.assert_allclose(world, np.repeat(world[:1], t, 0), atol=1e-12)
    assert np.abs(np.diff(pose, axis=0)).max() > 0.05  # the root-frame poses did change
    # heights are never touched; jax arrays give the same
    np.testing.assert_array_equal(pose[:, 1::3], np.repeat(pose[:1, 1::3], t, 0))
    import jax.numpy as jnp

    np.testing.assert_allclose(
        np.asarray(carry_to_next_root(jnp.asarray(pose[:-1]), jnp.asarray(control[:-1]))),
        pose[1:],
        atol=1e-5,
    )


def _creeping(seed=6):
    """A synthetic take whose ankles and toes creep back and forth by up to 2 cm."""
    clip = generate(1, 6.0, seed=seed)[0]
    pose = clip.pose.copy()
    for joint in (3, 4, 7, 8):  # both ankles and toes
        pose[:, 3 * joint + 2] += 0.02 * np.sin(0.7 * np.arange(len(pose)))
    return type(clip)(pose, clip.control, clip.fps, clip.name, dict(clip.meta))


def test_lock_clip_plants_the_feet_of_a_training_take_and_keeps_its_bones():
    clip = _creeping()
    locked = lock_clip(clip)
    slide = [foot_sliding(c.pose, c.control, fps=c.fps) for c in (clip, locked)]
    assert slide[0] > 0.1 and slide[1] < 0.2 * slide[0]
    np.testing.assert_allclose(bone_lengths(locked.pose), bone_lengths(clip.pose), atol=1e-4)
    np.testing.assert_array_equal(locked.control, clip.control)
    assert locked.meta["foot_locked"] and locked.name == clip.name
    # augment_clips locks the takes before the copies: the mirrored and the tempo
    # replays of a locked take are planted too
    out = augment_clips([clip], mirror=True, reverse=False, tempo=1.25, foot_lock=True)
    assert len(out) == 6 and all(c.meta["foot_locked"] for c in out)
    for c in out:
        assert foot_sliding(c.pose, c.control, fps=c.fps) < 0.3 * slide[0]
    plain = augment_clips([clip], mirror=True, reverse=False)
    assert not any(c.meta.get("foot_locked") for c in plain)
