"""benchmarks/foot_heights.py: its stance statistics see feet that leave the floor."""

from __future__ import annotations

import numpy as np

from motionflows.data.names import FOOT_JOINTS
from motionflows.data.synthetic import straight_walk


def test_stance_heights_see_a_wandering_floor_and_not_a_planted_one(benchmark_script):
    clip = straight_walk(1.2, seconds=4.0)
    pose = clip.pose[None]
    stats = benchmark_script("foot_heights").stance_heights
    planted = stats(pose, fps=clip.fps)
    assert abs(planted["block_min_height_cm"]["mean"]) < 0.5  # the synthetic feet touch y = 0
    assert planted["block_min_height_cm"]["within_window_std"] < 0.2
    assert planted["contact_rate"] > 0.2
    # the same walk with both feet raised by 0, 2, 0, 2 cm in its four seconds
    t = pose.shape[1]
    lift = 0.02 * ((np.arange(t) // round(clip.fps)) % 2)
    wandering = pose.reshape(1, t, 21, 3).copy()
    wandering[:, :, list(FOOT_JOINTS), 1] += lift[None, :, None]
    moved = stats(wandering.reshape(1, t, 63), fps=clip.fps)
    assert abs(moved["block_min_height_cm"]["within_window_std"] - 1.0) < 0.1  # std of 0, 2, 0, 2
    assert (
        abs(moved["block_min_height_cm"]["mean"] - planted["block_min_height_cm"]["mean"] - 1.0)
        < 0.1
    )
    assert moved["contact_rate"] < planted["contact_rate"]


def test_strides_are_timed_on_the_walking_windows_only(benchmark_script):
    strides = benchmark_script("foot_heights").strides
    walk = straight_walk(1.2, seconds=4.0)
    stand = straight_walk(0.0, seconds=4.0)
    pose = np.stack([walk.pose, stand.pose])
    control = np.stack([walk.control, stand.control])
    row = strides(pose, control, fps=walk.fps)
    assert row["walking_windows"] == 1 and row["found"] == 1.0  # the standing window is left out
    speed = walk.control[:, 0].mean() * walk.fps
    assert abs(row["length_m"] - speed * row["period_s"]) < 0.01
    assert 0.7 < row["period_s"] < 1.1  # the synthetic walk's cadence at 1.2 m/s


def test_moved_is_the_length_of_a_joints_move(benchmark_script):
    """``moved_cm`` took the largest single coordinate change (3 cm for a (3, 0, 4) cm move)
    and called it the largest joint move."""
    fh = benchmark_script("foot_heights")
    sample = np.zeros((1, 2, 63))
    locked = sample.copy()
    locked[0, 1, 9:12] = [0.03, 0.0, 0.04]  # joint 3 moved 5 cm in frame 1
    assert fh.moved_cm(locked, sample) == {"p50": 2.5, "p99": 4.95, "max": 5.0}
