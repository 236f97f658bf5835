"""benchmarks/long_run_drift.py: its per-block table measures a skeleton that drifts."""

from __future__ import annotations

import numpy as np
import pytest

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


def test_spans_score_the_named_stretches_of_the_control(benchmark_script):
    """``--spans`` rows are the metrics of exactly those frames; bad spans are refused."""
    clip = straight_walk(1.2, seconds=6.0)
    pose, control = clip.pose[None], clip.control[None]
    script = benchmark_script("long_run_drift")
    rows = script.drift_table(pose, control, fps=clip.fps, block=40, reference=20, spans=[(10, 50)])
    alone = script.drift_table(
        pose[:, 10:50], control[:, 10:50], fps=clip.fps, block=40, reference=20
    )
    assert rows[0]["seconds"] == [0.5, 2.5]
    for key in ("foot_sliding_m_s", "contact_rate", "jerk_m_s3"):
        assert rows[0][key] == alone[0][key]
    assert script._parse_spans("0-2, 5-8", 8.0) == [(0.0, 2.0), (5.0, 8.0)]
    for bad in ("2-1", "0-9", "walk", "3"):
        with pytest.raises(ValueError, match="A-B"):
            script._parse_spans(bad, 8.0)
    assert script.main(["pretrained:moglow-bandai", "--spans", "4-2"]) == 2
