"""Which windows of a split are scored, and their standardised arrays (one rule for all).

A :class:`~motionflows.data.WindowSet` may pad the tail of a take shorter than the window
(``valid`` False on the padded frames, a frozen last pose). Such a window is not motion, so
the trainer's validation, ``motionflows eval`` and the bench score only *complete* windows
(every frame recorded); a subset of at most ``limit`` of them is drawn deterministically
from a seed. Arrays are standardised with the run's standardiser: pose (N, T, 63),
control (N, T, 3), float32.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from motionflows.errors import RunError


def complete_windows(windows: Any) -> np.ndarray:
    """(M,) indices of the windows of ``windows`` whose every frame was recorded (all of
    them when the set has no ``valid`` mask)."""
    valid = getattr(windows, "valid", None)
    if valid is None:
        return np.arange(len(windows.pose))
    return np.flatnonzero(np.asarray(valid).reshape(len(windows.pose), -1).all(axis=1))


def subset(n: int, limit: int, seed: int) -> np.ndarray:
    """Sorted indices of at most ``limit`` of ``range(n)``: all of them if ``n <= limit``,
    else the first ``limit`` of a permutation drawn with ``default_rng(seed)``."""
    if n <= limit:
        return np.arange(n)
    return np.sort(np.random.default_rng(seed).permutation(n)[:limit])


def pick(windows: Any, limit: int, seed: int) -> np.ndarray:
    """Indices of a deterministic subset (at most ``limit``) of the complete windows."""
    full = complete_windows(windows)
    return full[subset(len(full), limit, seed)]


def standardized(standardizer: Any, windows: Any, idx: np.ndarray) -> tuple[np.ndarray, ...]:
    """(pose (N, T, 63), control (N, T, 3)) of windows ``idx``, standardised, float32."""
    pose = standardizer.normalize_pose(np.asarray(windows.pose)[idx])
    control = standardizer.normalize_control(np.asarray(windows.control)[idx])
    return np.asarray(pose, np.float32), np.asarray(control, np.float32)


def split_windows(
    dataset: Any, split: str, *, batch_size: int = 32, fallback_batches: int = 8
) -> tuple[np.ndarray, np.ndarray]:
    """Standardised (pose, control) of every complete window of ``split``.

    A dataset that offers only ``batch(split, batch_size, seed=0, index=i)`` and a
    standardiser (the minimum the trainer needs) is read batch by batch instead: enough
    batches to cover the split once, or ``fallback_batches`` when its size is unknown.
    """
    windows = _windows(dataset, split)
    if windows is None or not hasattr(dataset.standardizer, "normalize_pose"):
        return _read_batches(dataset, split, windows, batch_size, fallback_batches)
    keep = complete_windows(windows)
    if hasattr(dataset, "arrays"):  # standardised once and cached by the dataset
        arrays = dataset.arrays(split)
        pose, control = arrays["pose"][keep], arrays["control"][keep]
    else:
        pose, control = standardized(dataset.standardizer, windows, keep)
    if len(pose) == 0:
        raise RunError(f"the {split} split has no complete windows to evaluate")
    return np.asarray(pose, np.float32), np.asarray(control, np.float32)


def _read_batches(dataset, split, windows, batch_size, fallback_batches):
    """Every window of ``split`` through ``dataset.batch`` (already standardised)."""
    n = None if windows is None else len(windows.pose)
    count = max(1, fallback_batches) if n is None else -(-n // batch_size)
    batches = [dataset.batch(split, batch_size, seed=0, index=i) for i in range(count)]
    pose = np.concatenate([np.asarray(b["pose"], np.float32) for b in batches])[:n]
    control = np.concatenate([np.asarray(b["control"], np.float32) for b in batches])[:n]
    return pose, control


def _windows(dataset: Any, split: str) -> Any:
    """The WindowSet of ``split``, or None when the dataset exposes none."""
    if hasattr(dataset, "split"):
        return dataset.split(split)
    return getattr(dataset, split, None)
