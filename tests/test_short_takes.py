"""The short test takes (``motionflows.bench.short_takes`` and ``benchmarks/short_takes.py``):
the takes a window cannot hold, scored on their recorded frames."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from motionflows.bench import short_takes
from motionflows.data.pipeline import make_windows
from motionflows.data.synthetic import straight_walk


def _clips():
    """A long walk (complete windows) and two runs shorter than a 40-frame window."""
    walk = dataclasses.replace(straight_walk(1.2, seconds=4.0), name="dataset-2_walk_normal_001")
    runs = [
        dataclasses.replace(
            straight_walk(2.4, seconds=s, seed=i), name=f"dataset-2_run_normal_00{i}"
        )
        for i, s in enumerate((1.5, 0.8))
    ]
    return [walk, *runs]


def test_short_windows_are_the_padded_takes_with_enough_recorded_frames():
    script = short_takes
    windows, stats = make_windows(_clips(), 40, 10, short="pad", min_frames=10)
    recorded = windows.valid.sum(axis=1)
    assert stats["padded_windows"] == 2 and len(windows) > 2
    for frames in (10, 25):
        idx = script.short_windows(windows, frames)
        assert set(idx) == {i for i in range(len(windows)) if frames <= recorded[i] < 40}
    assert len(script.short_windows(windows, 10)) == 2  # both runs; no complete window
    assert script.take_kinds(windows, script.short_windows(windows, 10)) == {"run": 2}


def test_held_control_runs_on_where_the_padding_stores_a_stop():
    script = short_takes
    windows, _ = make_windows(_clips(), 40, 10, short="pad", min_frames=10)
    idx = script.short_windows(windows, 10)
    stored = windows.control.copy()
    held = script.held_control(windows, idx)
    for row, i in zip(held, idx, strict=True):
        n = int(windows.valid[i].sum())
        assert np.all(windows.control[i, n:] == 0)  # what the pipeline stores
        np.testing.assert_array_equal(row[:n], windows.control[i, :n])
        np.testing.assert_array_equal(row[n:], np.repeat(windows.control[i, n - 1 : n], 40 - n, 0))
        assert row[-1, 0] > 0.05  # still running forward (2.4 m/s = 0.12 m/frame)
    np.testing.assert_array_equal(windows.control, stored)  # the window set is not changed


def test_a_missing_run_is_one_message_and_exit_code_2(benchmark_script, tmp_path, capsys):
    script = benchmark_script("short_takes")
    assert script.main([str(tmp_path / "nope"), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "nope" in err and "Traceback" not in err


def test_a_skip_that_leaves_too_few_frames_is_refused_before_any_run_loads(
    benchmark_script, tmp_path, capsys
):
    script = benchmark_script("short_takes")
    for skip in ("-1", "37"):
        argv = [str(tmp_path / "nope"), "--frames", "40", "--skip", skip]
        assert script.main([*argv, "--out", str(tmp_path)]) == 2
        err = capsys.readouterr().err
        assert "--skip" in err and "nope" not in err  # refused before the run is looked at


def test_spans_scale_to_the_window_and_skip_the_start():
    assert short_takes.short_take_spans(80, {}) == (10, 40)  # the cpu and quick budgets
    assert short_takes.short_take_spans(32, {"short_frames": 16}) == (4, 16)  # smoke
    assert short_takes.short_take_spans(30, {}) == (7, 29)  # never a whole window
    assert short_takes.short_take_spans(5, {}) is None  # too short to score 4 frames


def test_scores_are_of_the_recorded_frames_and_of_the_draws():
    """The ground truth scores its own recorded frames (FD 0); a sampler's draws are cut to
    the same frames and it is given the held controls."""
    windows, _ = make_windows(_clips(), 40, 10, short="pad", min_frames=10)
    idx = short_takes.short_windows(windows, 10)
    truth = short_takes.score_short_takes(windows, idx, (2, 10), 20.0)
    assert truth["fd_pose"] < 1e-6 and truth["diverged"] == 0
    seen = []

    def sample(control_m):
        seen.append(control_m)
        return np.asarray(windows.pose)[idx] + 0.05  # every joint 5 cm off

    drawn = short_takes.score_short_takes(windows, idx, (2, 10), 20.0, sample=sample)
    np.testing.assert_array_equal(seen[0], short_takes.held_control(windows, idx))
    assert drawn["fd_pose"] > 1e-3  # a shifted pose distribution
    assert drawn["jerk"] == pytest.approx(truth["jerk"], rel=1e-5)  # an offset is not motion
