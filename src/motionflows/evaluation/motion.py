"""Motion metrics on poses in metres: prediction errors (Habibie et al. 2017) and motion
quality (foot sliding, bone-length variation, jerk, Frechet distances, sample diversity).

Inputs are *denormalised* features, numpy or jax arrays: poses (N, T, 63) in the floor-
projected root frame (y up, the character faces +z, +x is its left; joint j is
``pose[..., 3j:3j+3]``), controls (N, T, 3) = (forward, sideways, turn) per frame, the root
displacement from frame t to t+1 in the root frame of t (m/frame, m/frame with + = left =
+x, rad/frame with + = counter-clockwise seen from above). Sample sets have a leading
sample axis: (S, N, T, 63).

World frame: frame 0's root sits at the origin facing +z; ``integrate_root`` chains the
controls and ``to_global`` places each root-frame pose on that trajectory.
"""

from __future__ import annotations

import itertools
from typing import Any

import numpy as np

from motionflows.data.names import FOOT_JOINTS, NUM_JOINTS, PARENTS, POSE_DIM

PAPER_FRAMES_60FPS: tuple[int, ...] = (70, 90, 120, 160, 210)
"""Frames (0-based index in a 60-fps window) at which Habibie et al. report errors."""


def _xp(a: Any):
    """numpy for numpy input, jax.numpy for jax arrays (so the helpers work in both)."""
    if type(a).__module__.startswith("jax") or hasattr(a, "aval"):
        import jax.numpy as jnp

        return jnp
    return np


def _check_pose(pose: Any, name: str = "pose") -> None:
    shape = tuple(np.shape(pose))
    if len(shape) < 2 or shape[-1] != POSE_DIM:
        raise ValueError(f"{name} must have shape (..., T, {POSE_DIM}) in metres, got {shape}")


def _check_control(control: Any, name: str = "control") -> None:
    shape = tuple(np.shape(control))
    if len(shape) < 2 or shape[-1] != 3:
        raise ValueError(
            f"{name} must have shape (..., T, 3) = (forward, sideways, turn), got {shape}"
        )


def integrate_root(control: Any) -> tuple[Any, Any]:
    """Chain per-frame root displacements into a world trajectory.

    control (..., T, 3) -> positions (..., T, 3) (y = 0) and yaw (..., T), with
    ``p_0 = 0``, ``yaw_0 = 0`` and, for t < T - 1::

        yaw_{t+1} = yaw_t + turn_t
        p_{t+1}   = p_t + R_y(yaw_t) (sideways_t, 0, forward_t)

    where ``R_y(a)`` rotates counter-clockwise seen from above (+y): local +z (facing) ->
    (sin a, 0, cos a), local +x (left) -> (cos a, 0, -sin a). The last frame's control
    (moving T-1 -> T) is not used.
    """
    _check_control(control)
    xp = _xp(control)
    fwd, side, turn = control[..., 0], control[..., 1], control[..., 2]
    zero = xp.zeros_like(turn[..., :1])
    yaw = xp.concatenate([zero, xp.cumsum(turn[..., :-1], axis=-1)], axis=-1)
    cos, sin = xp.cos(yaw), xp.sin(yaw)
    dx = side * cos + fwd * sin
    dz = -side * sin + fwd * cos
    x = xp.concatenate([zero, xp.cumsum(dx[..., :-1], axis=-1)], axis=-1)
    z = xp.concatenate([zero, xp.cumsum(dz[..., :-1], axis=-1)], axis=-1)
    return xp.stack([x, xp.zeros_like(x), z], axis=-1), yaw


def to_global(pose: Any, control: Any) -> Any:
    """Root-frame poses (..., T, 63) placed on the trajectory of ``control`` (..., T, 3):
    world joint = p_t + R_y(yaw_t) local joint (heights unchanged). Returns (..., T, 63)."""
    _check_pose(pose)
    _check_control(control)
    if np.shape(pose)[-2] != np.shape(control)[-2]:
        raise ValueError(
            f"pose and control need the same number of frames, got {np.shape(pose)} and "
            f"{np.shape(control)}"
        )
    xp = _xp(pose)
    pos, yaw = integrate_root(control)
    j = pose.reshape(pose.shape[:-1] + (NUM_JOINTS, 3))
    cos, sin = xp.cos(yaw)[..., None], xp.sin(yaw)[..., None]
    lx, ly, lz = j[..., 0], j[..., 1], j[..., 2]
    wx = pos[..., 0:1] + lx * cos + lz * sin
    wz = pos[..., 2:3] - lx * sin + lz * cos
    return xp.stack([wx, ly, wz], axis=-1).reshape(pose.shape)


def _joints(pose: Any) -> np.ndarray:
    arr = np.asarray(pose, dtype=np.float64)
    return arr.reshape(arr.shape[:-1] + (NUM_JOINTS, 3))


def prediction_frames(
    fps: float, window: int | None = None, frames_at_60: tuple[int, ...] = PAPER_FRAMES_60FPS
) -> tuple[int, ...]:
    """The paper's report frames at another frame rate: ``round(f * fps / 60)`` (the same
    times). With ``window``, frames outside the window raise a ValueError."""
    frames = tuple(int(round(f * float(fps) / 60.0)) for f in frames_at_60)
    if window is not None and max(frames) >= window:
        raise ValueError(
            f"report frames {frames} (at {fps} fps) need windows of more than {max(frames)} "
            f"frames, got {window}; use longer test windows or pass fewer frames_at_60"
        )
    return frames


def _as_samples(pred: Any, target_shape: tuple[int, ...], name: str) -> np.ndarray:
    arr = np.asarray(pred, dtype=np.float64)
    if arr.shape == target_shape:
        arr = arr[None]
    if arr.shape[1:] != target_shape:
        raise ValueError(
            f"{name} must have shape {target_shape} or (S,) + {target_shape}, got {arr.shape}"
        )
    return arr


def _frames(frames, t: int) -> np.ndarray:
    idx = np.arange(t) if frames is None else np.asarray(frames, dtype=int)
    if idx.size and (idx.min() < 0 or idx.max() >= t):
        raise ValueError(f"frames {idx.tolist()} out of range for windows of {t} frames")
    return idx


def pose_error(pred: Any, target: Any, *, frames=None) -> np.ndarray:
    """Mean Euclidean joint error of root-relative joints (each joint minus the Hips joint,
    so the hip's offset from the floor-projected root is not scored), per frame.

    pred (N, T, 63) or samples (S, N, T, 63); target (N, T, 63), metres. Returns (F,)
    metres: the mean over the 20 non-root joints, windows and samples, at ``frames``
    (default every frame)."""
    _check_pose(target, "target")
    tgt = np.asarray(target, dtype=np.float64)
    p = _joints(_as_samples(pred, tgt.shape, "pred"))
    q = _joints(tgt)[None]
    idx = _frames(frames, tgt.shape[-2])
    p = p - p[..., :1, :]
    q = q - q[..., :1, :]
    d = np.linalg.norm(p[..., idx, 1:, :] - q[..., idx, 1:, :], axis=-1)
    return d.mean(axis=(0, 1, 3))


def motion_error(
    pred: Any, target: Any, control: Any, *, pred_control: Any = None, frames=None
) -> np.ndarray:
    """Mean Euclidean error of all 21 joints in world coordinates, per frame (metres, (F,)).

    Both motions are placed in the world with :func:`to_global`: the target on
    ``control`` (N, T, 3) and the prediction on ``pred_control`` (its own root trajectory,
    for models that output one; (N, T, 3) or (S, N, T, 3)), default ``control``. Against
    :func:`pose_error` it adds the hip's offset from the root and, with ``pred_control``,
    the drift of the trajectory. With the same control the rigid placement preserves
    distances, so the two errors then differ only by the root joint terms."""
    _check_pose(target, "target")
    tgt = np.asarray(target, dtype=np.float64)
    ctl = np.asarray(control, dtype=np.float64)
    if ctl.shape != tgt.shape[:-1] + (3,):
        raise ValueError(f"control must have shape {tgt.shape[:-1] + (3,)}, got {ctl.shape}")
    p = _as_samples(pred, tgt.shape, "pred")
    pc = ctl if pred_control is None else np.asarray(pred_control, dtype=np.float64)
    pc = np.broadcast_to(pc, p.shape[:-1] + (3,))
    pw = _joints(to_global(p, pc))
    qw = _joints(to_global(tgt, ctl))[None]
    idx = _frames(frames, tgt.shape[-2])
    d = np.linalg.norm(pw[..., idx, :, :] - qw[..., idx, :, :], axis=-1)
    return d.mean(axis=(0, 1, 3))


def prediction_errors(
    pred: Any, target: Any, control: Any, *, fps: float, pred_control: Any = None
) -> dict[str, Any]:
    """The paper's table: pose and motion error at the report frames (times of frames 70,
    90, 120, 160, 210 at 60 fps), averaged over windows and the S samples.

    Returns ``{"frames": [...], "seconds": [...], "pose_error": [...], "motion_error":
    [...], "num_samples": S}`` (metres)."""
    tgt = np.asarray(target)
    frames = prediction_frames(fps, tgt.shape[-2])
    p = _as_samples(pred, tgt.shape, "pred")
    return {
        "frames": list(frames),
        "seconds": [f / float(fps) for f in frames],
        "pose_error": pose_error(p, tgt, frames=frames).tolist(),
        "motion_error": motion_error(
            p, tgt, control, pred_control=pred_control, frames=frames
        ).tolist(),
        "num_samples": int(p.shape[0]),
    }


# ---------------------------------------------------------------------- motion quality
def foot_sliding(pose: Any, control: Any, *, fps: float, contact_height: float = 0.05) -> float:
    """Mean horizontal speed (m/s) of the feet while in ground contact.

    Per foot (ankle + toe joints), the foot is in contact at frame t when its lowest joint
    is below ``contact_height`` metres (the features put the floor at y = 0) at both t and
    t+1; its speed is the horizontal (x, z) world speed of the mean of its two joints from
    t to t+1. Returns the mean over all contact steps of all feet and windows (0 when there
    is no contact at all: report the contact rate alongside, see :func:`contact_rate`).
    pose (..., T, 63), control (..., T, 3)."""
    w = _joints(to_global(np.asarray(pose, dtype=np.float64), np.asarray(control, np.float64)))
    total, count = 0.0, 0
    for ankle, toe in (FOOT_JOINTS[:2], FOOT_JOINTS[2:]):
        low = np.minimum(w[..., ankle, 1], w[..., toe, 1])
        contact = (low[..., :-1] < contact_height) & (low[..., 1:] < contact_height)
        centre = 0.5 * (w[..., ankle, :] + w[..., toe, :])
        step = centre[..., 1:, :] - centre[..., :-1, :]
        speed = np.hypot(step[..., 0], step[..., 2]) * float(fps)
        total += float((speed * contact).sum())
        count += int(contact.sum())
    return total / count if count else 0.0


def contact_rate(pose: Any, *, contact_height: float = 0.05) -> float:
    """Fraction of (frame, foot) pairs whose lowest foot joint is below ``contact_height``."""
    j = _joints(pose)
    rates = [
        np.minimum(j[..., a, 1], j[..., b, 1]) < contact_height
        for a, b in (FOOT_JOINTS[:2], FOOT_JOINTS[2:])
    ]
    return float(np.mean(rates))


def bone_lengths(pose: Any) -> np.ndarray:
    """Bone lengths (..., T, 20) in metres, one per non-root joint (to its parent)."""
    j = _joints(pose)
    child = [i for i, p in enumerate(PARENTS) if p >= 0]
    parent = [PARENTS[i] for i in child]
    return np.linalg.norm(j[..., child, :] - j[..., parent, :], axis=-1)


def bone_length_variation(pose: Any) -> float:
    """Mean over windows and bones of the standard deviation over time of each bone's length
    (metres). Rigid skeletons give 0."""
    lengths = bone_lengths(pose)
    return float(lengths.std(axis=-2).mean())


def jerk(pose: Any, *, fps: float, control: Any = None) -> float:
    """Mean magnitude of the third time derivative of joint positions (m/s^3), finite
    differences at ``fps``; in world coordinates when ``control`` is given, else in the root
    frame. Needs T >= 4."""
    p = np.asarray(pose, dtype=np.float64)
    if control is not None:
        p = to_global(p, np.asarray(control, dtype=np.float64))
    j = _joints(p)
    if j.shape[-3] < 4:
        raise ValueError(f"jerk needs at least 4 frames, got {j.shape[-3]}")
    d3 = np.diff(j, n=3, axis=-3) * float(fps) ** 3
    return float(np.linalg.norm(d3, axis=-1).mean())


def frechet_distance(real: Any, generated: Any, *, eps: float = 1e-6) -> float:
    """Frechet distance between Gaussians fitted to two feature sets (M, D) and (M', D):
    ``|mu_r - mu_g|^2 + tr(S_r + S_g - 2 (S_r S_g)^(1/2))`` (units: the features' squared).
    The matrix square root is computed through the symmetric form
    ``tr((S_r^(1/2) S_g S_r^(1/2))^(1/2))``; ``eps`` is added to the diagonals."""
    a = np.asarray(real, dtype=np.float64)
    b = np.asarray(generated, dtype=np.float64)
    if a.ndim != 2 or b.ndim != 2 or a.shape[1] != b.shape[1]:
        raise ValueError(f"features must be (M, D) with equal D, got {a.shape} and {b.shape}")
    if a.shape[0] < 2 or b.shape[0] < 2:
        raise ValueError("need at least 2 feature vectors on each side")
    mu_a, mu_b = a.mean(0), b.mean(0)
    eye = eps * np.eye(a.shape[1])
    s_a = np.cov(a, rowvar=False) + eye
    s_b = np.cov(b, rowvar=False) + eye
    w, v = np.linalg.eigh(s_a)
    root_a = (v * np.sqrt(np.clip(w, 0.0, None))) @ v.T
    middle = root_a @ s_b @ root_a
    tr_sqrt = np.sqrt(np.clip(np.linalg.eigvalsh(0.5 * (middle + middle.T)), 0.0, None)).sum()
    value = float(np.sum((mu_a - mu_b) ** 2) + np.trace(s_a) + np.trace(s_b) - 2.0 * tr_sqrt)
    return max(value, 0.0)


def pose_features(pose: Any, *, frames: int = 1) -> np.ndarray:
    """Feature vectors for :func:`frechet_distance`: all runs of ``frames`` consecutive
    root-frame poses, flattened: (..., T, 63) -> (M, 63 * frames)."""
    p = np.asarray(pose, dtype=np.float64)
    _check_pose(p)
    t = p.shape[-2]
    if t < frames:
        raise ValueError(f"need at least {frames} frames, got {t}")
    stacked = np.concatenate([p[..., i : t - frames + 1 + i, :] for i in range(frames)], -1)
    return stacked.reshape(-1, POSE_DIM * frames)


def frechet_pose_distance(real: Any, generated: Any) -> float:
    """Frechet distance (m^2) between the per-frame pose statistics of two motion sets."""
    return frechet_distance(pose_features(real), pose_features(generated))


def frechet_window_distance(real: Any, generated: Any, *, frames: int = 3) -> float:
    """Frechet distance (m^2) between the statistics of ``frames``-frame pose windows."""
    return frechet_distance(
        pose_features(real, frames=frames), pose_features(generated, frames=frames)
    )


def diversity(samples: Any) -> float:
    """Sample diversity under one control: the mean over windows, frames and all pairs of
    samples of the mean per-joint Euclidean distance between two samples (metres).
    samples (S, N, T, 63) with S >= 2 samples drawn for the same N controls."""
    s = np.asarray(samples, dtype=np.float64)
    if s.ndim != 4 or s.shape[-1] != POSE_DIM or s.shape[0] < 2:
        raise ValueError(f"samples must be (S >= 2, N, T, {POSE_DIM}), got {s.shape}")
    j = _joints(s)
    dists = [
        np.linalg.norm(j[a] - j[b], axis=-1).mean()
        for a, b in itertools.combinations(range(s.shape[0]), 2)
    ]
    return float(np.mean(dists))


def motion_quality(
    pose: Any, control: Any, *, fps: float, contact_height: float = 0.05
) -> dict[str, float]:
    """The per-motion metrics for one set of motions (N, T, 63) with controls (N, T, 3):
    foot sliding (m/s), contact rate, bone-length std (m), jerk in the world (m/s^3)."""
    return {
        "foot_sliding": foot_sliding(pose, control, fps=fps, contact_height=contact_height),
        "contact_rate": contact_rate(pose, contact_height=contact_height),
        "bone_length_std": bone_length_variation(pose),
        "jerk": jerk(pose, fps=fps, control=control),
    }
