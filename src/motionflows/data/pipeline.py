"""Clips -> fixed-length windows, the standardiser, and seeded batch indexing.

Windows: a clip of T >= W frames gives starts ``0, hop, 2 hop, ...`` plus, when the tail
would otherwise be lost, one final window ending at the last frame. A clip with
``min_frames <= T < W`` is padded to W frames (``short="pad"``: the last pose repeated,
zero control; ``WindowSet.valid`` marks the real frames) or dropped (``short="drop"``);
clips below ``min_frames`` are dropped. Every drop is counted in the dataset ``info`` and
warned about, never silent.

Standardiser: per channel ``z = (x - mean) / std`` with ``std`` floored (near-constant
channels); ``log|dz/dx|`` per frame = ``-sum(log pose_std)``.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from motionflows.data.features import Clip
from motionflows.data.names import CONTROL_DIM, POSE_DIM


@dataclasses.dataclass
class WindowSet:
    """Windows of one split. pose (N, T, 63) metres, control (N, T, 3), take (N,) names,
    start (N,) first frame in the take, valid (N, T) bool (False on padding)."""

    pose: np.ndarray
    control: np.ndarray
    take: np.ndarray
    start: np.ndarray
    valid: np.ndarray

    def __len__(self) -> int:
        return int(self.pose.shape[0])

    @property
    def window(self) -> int:
        return int(self.pose.shape[1])

    @classmethod
    def empty(cls, window: int) -> WindowSet:
        return cls(np.zeros((0, window, POSE_DIM), np.float32),
                   np.zeros((0, window, CONTROL_DIM), np.float32),
                   np.zeros((0,), dtype=object), np.zeros((0,), np.int64),
                   np.zeros((0, window), bool))  # fmt: skip


def window_starts(length: int, window: int, hop: int) -> list[int]:
    """Window starts covering a take of ``length >= window`` frames (tail included)."""
    starts = list(range(0, length - window + 1, hop))
    if starts[-1] + window < length:
        starts.append(length - window)
    return starts


SHORT_TAKES: tuple[str, ...] = ("pad", "drop")
"""What :func:`make_windows` does with a take shorter than the window (``short=``)."""


def make_windows(
    clips: list[Clip], window: int, hop: int, *, short: str = "pad", min_frames: int | None = None
) -> tuple[WindowSet, dict]:
    """Cut clips into windows. Returns the set and counts (frames used, padded, dropped)."""
    if window < 2 or hop < 1:
        raise ValueError(f"window must be >= 2 and hop >= 1, got window={window}, hop={hop}")
    if short not in SHORT_TAKES:
        raise ValueError(f"short must be 'pad' or 'drop', got {short!r}")
    min_frames = max(2, window // 4) if min_frames is None else int(min_frames)
    poses, controls, takes, starts, valids = [], [], [], [], []
    stats = dict(frames_total=0, frames_used=0, padded_windows=0, padded_frames=0,
                 dropped_clips=[], windows=0)  # fmt: skip
    for clip in clips:
        n = len(clip)
        stats["frames_total"] += n
        if n >= window:
            for s in window_starts(n, window, hop):
                poses.append(clip.pose[s : s + window])
                controls.append(clip.control[s : s + window])
                takes.append(clip.name)
                starts.append(s)
                valids.append(np.ones(window, bool))
            stats["frames_used"] += n
        elif n >= min_frames and short == "pad":
            pad = window - n
            poses.append(np.concatenate([clip.pose, np.repeat(clip.pose[-1:], pad, 0)]))
            controls.append(
                np.concatenate([clip.control, np.zeros((pad, CONTROL_DIM), np.float32)])
            )
            takes.append(clip.name)
            starts.append(0)
            valids.append(np.arange(window) < n)
            stats["frames_used"] += n
            stats["padded_windows"] += 1
            stats["padded_frames"] += pad
        else:
            stats["dropped_clips"].append(f"{clip.name} ({n} frames)")
    if not poses:
        return WindowSet.empty(window), stats
    ws = WindowSet(
        pose=np.stack(poses).astype(np.float32),
        control=np.stack(controls).astype(np.float32),
        take=np.array(takes, dtype=object),
        start=np.array(starts, np.int64),
        valid=np.stack(valids),
    )
    stats["windows"] = len(ws)
    return ws, stats


@dataclasses.dataclass
class Standardizer:
    """Per-channel affine standardisation of pose (63) and control (3).

    ``normalize_pose(x) = (x - pose_mean) / pose_std`` (metres -> standardised);
    ``log_det_per_frame = -sum(log pose_std)`` = log|d normalize_pose / dx| for one frame,
    so ``log p_metres(x) = log p_std(z) + T * log_det_per_frame`` over T frames.
    Works on numpy and jax arrays of shape (..., 63) / (..., 3).
    """

    pose_mean: np.ndarray
    pose_std: np.ndarray
    control_mean: np.ndarray
    control_std: np.ndarray

    def __post_init__(self):
        for name, dim in (
            ("pose_mean", POSE_DIM),
            ("pose_std", POSE_DIM),
            ("control_mean", CONTROL_DIM),
            ("control_std", CONTROL_DIM),
        ):
            value = np.asarray(getattr(self, name), dtype=np.float32)
            if value.shape != (dim,):
                raise ValueError(f"Standardizer.{name} must have shape ({dim},), got {value.shape}")
            if not np.isfinite(value).all():
                raise ValueError(f"Standardizer.{name} has non-finite values")
            setattr(self, name, value)
        if (self.pose_std <= 0).any() or (self.control_std <= 0).any():
            raise ValueError("Standardizer stds must be positive")

    @classmethod
    def fit(
        cls,
        pose: np.ndarray,
        control: np.ndarray,
        *,
        valid: np.ndarray | None = None,
        pose_floor: float = 1e-3,
        control_floor: float = 1e-4,
    ) -> Standardizer:
        """Fit on windows pose (N, T, 63) / control (N, T, 3) (only ``valid`` frames).

        Floors: ``std >= pose_floor`` metres and ``std >= control_floor``.
        """
        p = np.asarray(pose, np.float64).reshape(-1, POSE_DIM)
        c = np.asarray(control, np.float64).reshape(-1, CONTROL_DIM)
        if valid is not None:
            v = np.asarray(valid, bool).reshape(-1)
            p, c = p[v], c[v]
        if p.shape[0] < 2:
            raise ValueError("cannot fit a Standardizer on fewer than 2 frames")
        return cls(
            p.mean(0),
            np.maximum(p.std(0), pose_floor),
            c.mean(0),
            np.maximum(c.std(0), control_floor),
        )

    @property
    def log_det_per_frame(self) -> float:
        return float(-np.sum(np.log(self.pose_std.astype(np.float64))))

    def log_jacobian(self, num_frames: int = 1) -> float:
        """log|det d normalize_pose / dx| over ``num_frames`` frames (nats): add it to a
        standardised-space log-likelihood to get the metre-space one."""
        return num_frames * self.log_det_per_frame

    def normalize_pose(self, x):
        return (x - self.pose_mean) / self.pose_std

    def denormalize_pose(self, z):
        return z * self.pose_std + self.pose_mean

    def normalize_control(self, c):
        return (c - self.control_mean) / self.control_std

    def denormalize_control(self, z):
        return z * self.control_std + self.control_mean

    def to_dict(self) -> dict:
        return {
            k: [float(v) for v in getattr(self, k)]
            for k in ("pose_mean", "pose_std", "control_mean", "control_std")
        }

    @classmethod
    def from_dict(cls, d: dict) -> Standardizer:
        return cls(
            **{
                k: np.asarray(d[k], np.float32)
                for k in ("pose_mean", "pose_std", "control_mean", "control_std")
            }
        )


def batch_indices(
    n: int,
    batch_size: int,
    *,
    seed: int,
    index: int,
    shuffle: bool = True,
    drop_last: bool = True,
    salt: int = 0,
) -> np.ndarray:
    """Window indices of batch ``index``: epoch = index // batches_per_epoch, permutation
    from (seed, epoch, salt). drop_last: batches_per_epoch = n // B (if n < B one batch of B,
    wrapping around); otherwise ceil(n / B) with a short last batch."""
    if n < 1:
        raise ValueError("the split has no windows; use a smaller window or more data")
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    if index < 0:
        raise ValueError(f"index must be >= 0, got {index}")
    per_epoch = batches_per_epoch(n, batch_size, drop_last=drop_last)
    epoch, j = divmod(int(index), per_epoch)
    if shuffle:
        order = np.random.default_rng([int(seed), int(epoch), int(salt)]).permutation(n)
    else:
        order = np.arange(n)
    if drop_last and n < batch_size:
        return np.resize(order, batch_size)
    return order[j * batch_size : (j + 1) * batch_size]


def batches_per_epoch(n: int, batch_size: int, *, drop_last: bool = True) -> int:
    if drop_last:
        return max(1, n // batch_size)
    return max(1, -(-n // batch_size))
