"""Motion on the test takes shorter than a window: on Bandai, nearly every run.

A take shorter than the window is one padded window (its last pose frozen under a zero
control, ``valid`` False there), which the bench's likelihood and motion tables leave out:
padding is not motion. The Bandai runs of most styles (every one of D2-C's) last 2.0-3.8 s,
less than the 4 s window, so those tables hold walks and turns only. This module scores
such takes with the same motion metrics on frames ``skip .. frames - 1`` of each:

* the takes: the padded windows with at least ``frames`` recorded frames
  (:func:`short_windows`);
* the control: each take's own, with the padded frames holding its last recorded control
  (:func:`held_control`: a run going on, not the stop the padding stores), so a model that
  reads the whole window's control (the fixed-length Glow, the VAE-LSTM) sees a run; a
  causal MoGlow's first ``frames`` frames do not depend on it;
* ``skip``: the models start from a mean-pose history (the bench's rule) while a Bandai
  run starts at full speed, so the first half second, the start-up, is left out.

Diversity is not scored (one take per control). The metrics are
:func:`motionflows.bench.scoring.motion_metrics`; the ground truth of the same frames is
the reference of the Frechet distances and its own row.
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from motionflows.bench.scoring import motion_metrics
from motionflows.bench.speed import sample_in_chunks
from motionflows.windows import subset

SHORT_FRAMES = 40
"""Frames sampled from each short take's start (2 s at 20 fps; a D2-C run lasts 2.2-3.8 s)."""

SHORT_SKIP = 10
"""Of those, the first frames left out of the scores (the start from a mean pose)."""

SHORT_METRICS = (
    "foot_sliding",
    "skate_ratio",
    "contact_rate",
    "bone_length_std",
    "jerk",
    "fd_pose",
    "fd_window3",
    "diverged",
)
"""The motion metrics of the short takes' table (diversity and the errors at Habibie et
al.'s report times, most of which fall after a short take's end, are left out)."""


def short_windows(windows: Any, frames: int) -> np.ndarray:
    """(M,) indices of the padded windows of ``windows`` with at least ``frames`` recorded
    frames (a take shorter than the window, one window each)."""
    valid = np.asarray(windows.valid, bool).reshape(len(windows.pose), -1)
    recorded = valid.sum(axis=1)
    return np.flatnonzero(~valid.all(axis=1) & (recorded >= frames))


def pick_short(windows: Any, frames: int, limit: int, seed: int = 2) -> np.ndarray:
    """At most ``limit`` of :func:`short_windows` (a deterministic subset, as
    :func:`motionflows.windows.pick` draws the complete windows)."""
    idx = short_windows(windows, frames)
    return idx[subset(len(idx), limit, seed=seed)]


def held_control(windows: Any, idx: np.ndarray) -> np.ndarray:
    """(M, T, 3) controls of windows ``idx`` (data units) with every padded frame holding
    the window's last recorded control; ``windows`` is not changed."""
    control = np.array(np.asarray(windows.control)[idx], np.float32)
    valid = np.asarray(windows.valid, bool).reshape(len(windows.pose), -1)[idx]
    last = valid.sum(axis=1) - 1  # recorded frames come first in a padded window
    for i, n in enumerate(last):
        control[i, n + 1 :] = control[i, n]
    return control


def take_kinds(windows: Any, idx: np.ndarray) -> dict[str, int]:
    """How many windows of each motion the take names of ``idx`` say (Bandai's
    ``dataset-2_run_normal_012`` -> ``run``); a name without that pattern counts as itself."""
    kinds: Counter[str] = Counter()
    for name in np.asarray(windows.take, dtype=object)[idx]:
        parts = Path(str(name)).stem.split("_")
        kinds[parts[1] if len(parts) > 2 else str(name)] += 1
    return dict(sorted(kinds.items()))


def short_take_spans(window: int, sizes: dict) -> tuple[int, int] | None:
    """(skip, frames) of the bench's short-take rows for windows of ``window`` frames:
    frames = the budget's ``short_frames`` (default :data:`SHORT_FRAMES`; the smoke budget's
    windows are shorter) but at most ``window - 1``, skip = :data:`SHORT_SKIP` scaled by
    frames / SHORT_FRAMES; None when that leaves fewer than 4 frames scored."""
    frames = min(int(sizes.get("short_frames", SHORT_FRAMES)), window - 1)
    skip = SHORT_SKIP * frames // SHORT_FRAMES
    return (skip, frames) if frames - skip >= 4 else None


def score_short_takes(
    windows: Any,
    idx: np.ndarray,
    span: tuple[int, int],
    fps: float,
    *,
    sample=None,
) -> dict:
    """Motion metrics on frames ``span`` = (skip, frames) of the short takes ``idx`` of
    ``windows`` (data units): of the recorded motion, or with ``sample`` of its draws.

    ``sample(control)`` takes the held controls (M, T, 3) in data units (:func:`held_control`)
    and returns poses (M, T, 63) in metres, e.g. a model's sampler between its
    standardiser's maps. Returns :func:`~motionflows.bench.scoring.motion_metrics`'s
    scalars (no ``prediction``).
    """
    frames = slice(*span)
    truth_m = np.asarray(windows.pose, np.float32)[idx][:, frames]
    control_m = held_control(windows, idx)
    drawn_m = truth_m if sample is None else np.asarray(sample(control_m), np.float32)[:, frames]
    metrics = motion_metrics(drawn_m, control_m[:, frames], truth_m, None, float(fps))
    metrics.pop("prediction", None)
    return metrics


def drawing(sampler, model, standardizer, key):
    """``sample`` for :func:`score_short_takes`: control (M, T, 3) in data units -> the
    model's draws (M, T, 63) in metres, by ``sampler`` (:func:`motionflows.bench.make_sampler`)
    in chunks with ``key``, between the standardiser's maps."""

    def sample(control_m):
        control = np.asarray(standardizer.normalize_control(control_m), np.float32)
        draws = sample_in_chunks(sampler, model, control, key)
        return standardizer.denormalize_pose(draws)

    return sample
