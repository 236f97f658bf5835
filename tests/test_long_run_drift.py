"""benchmarks/long_run_drift.py: its per-block table measures a skeleton that drifts."""

from __future__ import annotations

import numpy as np

from motionflows.data.synthetic import straight_walk


def test_drift_table_sees_a_growing_skeleton_and_not_a_rigid_one(benchmark_script):
    clip = straight_walk(1.2, seconds=6.0)
    pose, control = clip.pose[None], clip.control[None]
    t = pose.shape[1]
    table = benchmark_script("long_run_drift").drift_table
    rigid = table(pose, control, fps=clip.fps, block=40, reference=20)
    assert len(rigid) == t // 40
    assert max(r["bone_error_m"] for r in rigid) < 0.005  # the synthetic skeleton is rigid
    assert all(r["contact_rate"] > 0.2 and r["jerk_m_s3"] > 0 for r in rigid)
    # the same walk with every joint's offset from the root scaled up by 5 % per second
    joints = pose.reshape(1, t, 21, 3)
    root = joints[:, :, :1]
    scale = 1.0 + 0.05 * np.arange(t)[None, :, None, None] / clip.fps
    grown = (root + (joints - root) * scale).reshape(1, t, 63)
    drift = [r["bone_error_m"] for r in table(grown, control, fps=clip.fps, block=40, reference=20)]
    assert all(b > a for a, b in zip(drift, drift[1:], strict=False))
    assert drift[-1] > 10 * max(r["bone_error_m"] for r in rigid)
