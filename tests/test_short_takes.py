"""benchmarks/short_takes.py: it scores the takes the bench skips, on their recorded frames."""

from __future__ import annotations

import dataclasses

import numpy as np

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


def test_short_windows_are_the_padded_takes_with_enough_recorded_frames(benchmark_script):
    script = benchmark_script("short_takes")
    windows, stats = make_windows(_clips(), 40, 10, short="pad", min_frames=10)
    recorded = windows.valid.sum(axis=1)
    assert stats["padded_windows"] == 2 and len(windows) > 2
    for frames in (10, 25):
        idx = script.short_windows(windows, frames)
        assert set(idx) == {i for i in range(len(windows)) if frames <= recorded[i] < 40}
    assert len(script.short_windows(windows, 10)) == 2  # both runs; no complete window
    assert script.take_kinds(windows, script.short_windows(windows, 10)) == {"run": 2}


def test_held_control_runs_on_where_the_padding_stores_a_stop(benchmark_script):
    script = benchmark_script("short_takes")
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
