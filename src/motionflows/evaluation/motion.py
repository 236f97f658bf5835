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

from motionflows.data.features import array_module, integrate_root
from motionflows.data.names import FOOT_JOINTS, NUM_JOINTS, PARENTS, POSE_DIM

PAPER_FRAMES_60FPS: tuple[int, ...] = (70, 90, 120, 160, 210)
"""Frames (0-based index in a 60-fps window) at which Habibie et al. report errors."""


_xp = array_module  # numpy in, numpy out; jax in, jax out


def _check_pose(pose: Any, name: str = "pose") -> None:
    shape = tuple(np.shape(pose))
    if len(shape) < 2 or shape[-1] != POSE_DIM:
        raise ValueError(f"{name} must have shape (..., T, {POSE_DIM}) in metres, got {shape}")


def _check_finite(x: Any, name: str) -> None:
    """ValueError when numpy ``x`` holds NaN or inf: a metric of such motion would be NaN or,
    worse, a clean-looking number computed as if the frame were not there."""
    if not np.isfinite(x).all():
        raise ValueError(
            f"{name} contains non-finite values (NaN or inf); leave diverged samples out "
            "first (motionflows.bench.scoring.diverged finds them)"
        )


def _check_control(control: Any, name: str = "control") -> None:
    shape = tuple(np.shape(control))
    if len(shape) < 2 or shape[-1] != 3:
        raise ValueError(
            f"{name} must have shape (..., T, 3) = (forward, sideways, turn), got {shape}"
        )


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
    distances, so this is then the mean over all 21 joints of the root-frame error, where
    :func:`pose_error` measures each joint relative to the Hips: a prediction off only in
    the hip's position by d scores |d| / 21 here and |d| on every joint there."""
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
CONTACT_RULES: tuple[str, ...] = ("floor", "absolute")
"""Foot-contact rules of :func:`foot_contacts`: ``"floor"`` (the default, calibrated on real
mocap) and ``"absolute"`` (the rule of reports before 2026-12: 5 cm above y = 0)."""
FLOOR_CONTACT_M = 0.015
"""``"floor"`` rule: a foot is in contact within 1.5 cm of the estimated floor."""
FLOOR_PERCENTILE = 5.0
"""``"floor"`` rule: the floor is this percentile of the feet's lowest-joint heights."""
FLOOR_MAX_OFFSET_M = 0.05
"""``"floor"`` rule: the estimated floor is clipped to +-5 cm of y = 0, so a character that
floats (or sinks) stays out of (or in) contact instead of defining its own floor."""
ABSOLUTE_CONTACT_M = 0.05
"""``"absolute"`` rule: a foot is in contact below 5 cm (the features' floor is y = 0)."""
SKATE_SPEED_M_S = 0.5
"""Skate ratio threshold: a contact step faster than 0.5 m/s (2.5 cm per frame at 20 fps,
the threshold of the foot-skating ratio of Karunratanakul et al. 2023) is a skate."""


def foot_heights(joints: np.ndarray) -> np.ndarray:
    """(..., 2): the height of each foot's lowest joint (ankle or toe), left then right, of
    joints (..., 21, 3) in metres (sequences: (..., T, 21, 3) -> (..., T, 2)); numpy or jax."""
    xp = _xp(joints)
    return xp.stack([xp.minimum(joints[..., a, 1], joints[..., b, 1]) for a, b in _FEET], axis=-1)


_FEET = (FOOT_JOINTS[:2], FOOT_JOINTS[2:])


def contact_floor(heights: np.ndarray) -> np.ndarray:
    """The ``"floor"`` rule's floor (...,) of feet heights (..., T, 2) in metres: the
    ``FLOOR_PERCENTILE`` of both feet's heights over the frames, clipped to
    +-``FLOOR_MAX_OFFSET_M``. numpy or jax."""
    xp = _xp(heights)
    flat = heights.reshape(heights.shape[:-2] + (-1,))
    return xp.clip(
        xp.percentile(flat, FLOOR_PERCENTILE, axis=-1), -FLOOR_MAX_OFFSET_M, FLOOR_MAX_OFFSET_M
    )


def foot_contacts(
    pose: Any, *, rule: str = "floor", contact_height: float | None = None
) -> np.ndarray:
    """Per-frame foot contact (..., T, 2) bool (left, right), decided by height only.

    A foot's height is that of its lowest joint (ankle or toe). Rules:

    * ``"floor"`` (default): the floor of each sequence (..., T) is the 5th percentile of
      both feet's heights over its frames, clipped to [-5 cm, +5 cm]; a foot is in contact
      while it is less than ``contact_height`` (default 1.5 cm) above that floor. Calibrated
      on the Bandai dev takes (every 80-frame window at 20 fps, hop 10): ground truth
      walking slides at 0.13 m/s with contact rate 0.57 and skate ratio 0.04 (521 windows;
      turns 0.14 / 0.59 and 0.12 / 0.59, walking backwards 0.08 / 0.56), running 0.12 /
      0.43 / 0.01 (106 windows of the longer runs; whole run takes: 0.13 / 0.29).
    * ``"absolute"``: in contact below ``contact_height`` (default 5 cm) above y = 0, the
      rule of earlier reports (on the same windows: walking 0.58 m/s, running 0.94 m/s).

    Speed is never part of the test, so a foot dragged along the ground counts as sliding.
    numpy in (float64 inside), numpy out; a jax array in (any dtype, jittable), jax out.
    """
    if _xp(pose) is np:
        _check_finite(pose, "pose")
        j = _joints(pose)
    else:
        j = pose.reshape(pose.shape[:-1] + (NUM_JOINTS, 3))
    heights = foot_heights(j)
    if rule == "floor":
        h = FLOOR_CONTACT_M if contact_height is None else float(contact_height)
        return heights < contact_floor(heights)[..., None, None] + h
    if rule == "absolute":
        h = ABSOLUTE_CONTACT_M if contact_height is None else float(contact_height)
        return heights < h
    raise ValueError(f"unknown contact rule {rule!r}; valid: {', '.join(CONTACT_RULES)}")


def foot_speeds(pose: Any, control: Any, *, fps: float) -> np.ndarray:
    """(..., T-1, 2): the horizontal (x, z) world speed (m/s) of each foot's centre (the
    mean of its ankle and toe), left then right, over each step t -> t+1 of pose
    (..., T, 63) with control (..., T, 3)."""
    w = _joints(to_global(np.asarray(pose, np.float64), np.asarray(control, np.float64)))
    centre = np.stack([0.5 * (w[..., a, :] + w[..., b, :]) for a, b in _FEET], axis=-2)
    step = np.diff(centre, axis=-3)
    return np.hypot(step[..., 0], step[..., 2]) * float(fps)


def _contact_steps(pose, control, fps, rule, contact_height):
    """(speed, contact) of each foot step t -> t+1, both (..., T-1, 2): the foot centre's
    :func:`foot_speeds` and contact at both t and t+1."""
    pose = np.asarray(pose, dtype=np.float64)
    _check_finite(control, "control")
    contact = foot_contacts(pose, rule=rule, contact_height=contact_height)
    both = contact[..., :-1, :] & contact[..., 1:, :]
    return foot_speeds(pose, control, fps=fps), both


def foot_sliding(
    pose: Any,
    control: Any,
    *,
    fps: float,
    rule: str = "floor",
    contact_height: float | None = None,
) -> float:
    """Mean horizontal speed (m/s) of the feet while in ground contact.

    A step t -> t+1 of a foot counts when the foot is in contact (:func:`foot_contacts`,
    ``rule`` and ``contact_height``) at both t and t+1; its speed is the horizontal (x, z)
    world speed of the mean of the foot's ankle and toe. Returns the mean over all contact
    steps of both feet and all sequences (0 when there is none: report :func:`contact_rate`
    beside it). A frozen pose dragged along a path scores the root's speed; real walking
    about 0.13 m/s (see :func:`foot_contacts`). pose (..., T, 63), control (..., T, 3)."""
    speed, both = _contact_steps(pose, control, fps, rule, contact_height)
    count = int(both.sum())
    return float((speed * both).sum()) / count if count else 0.0


def skate_ratio(
    pose: Any,
    control: Any,
    *,
    fps: float,
    speed: float = SKATE_SPEED_M_S,
    rule: str = "floor",
    contact_height: float | None = None,
) -> float:
    """Foot-skating ratio: the fraction of contact steps (as in :func:`foot_sliding`) whose
    horizontal foot speed exceeds ``speed`` m/s (default 0.5 m/s, 2.5 cm/frame at 20 fps).
    Bandai dev ground truth (80-frame windows): walking 0.04, running 0.01. 0 when there is
    no contact."""
    step_speed, both = _contact_steps(pose, control, fps, rule, contact_height)
    count = int(both.sum())
    return float(((step_speed > float(speed)) & both).sum()) / count if count else 0.0


def contact_rate(pose: Any, *, rule: str = "floor", contact_height: float | None = None) -> float:
    """Fraction of (frame, foot) pairs in contact (:func:`foot_contacts`)."""
    return float(np.mean(foot_contacts(pose, rule=rule, contact_height=contact_height)))


def stride_period(
    pose: Any,
    *,
    fps: float,
    shortest: float = 0.5,
    longest: float = 2.0,
    min_correlation: float = 0.3,
) -> np.ndarray:
    """The gait's stride period (seconds; two steps, one of each foot) of each window (N,).

    The feet alternate once per stride, so the horizontal vector from the right ankle to
    the left one, d_t (root frame), repeats with the stride. Its autocorrelation
    r(L) = corr(d_t, d_{t+L}) over lags L from ``shortest`` to ``longest`` seconds (at most
    half the window) peaks at the period: the first local maximum within 80 % of the
    highest, refined by a parabola through its neighbours. NaN where no peak reaches
    ``min_correlation`` (standing, shuffling). Stride length = speed x period."""
    _check_pose(pose)
    j = _joints(np.asarray(pose, dtype=np.float64))
    left, right = FOOT_JOINTS[0], FOOT_JOINTS[2]
    d = (j[..., left, :] - j[..., right, :])[..., [0, 2]]  # (..., T, 2) horizontal
    d = d.reshape(-1, *d.shape[-2:])
    t = d.shape[1]
    first = max(1, round(shortest * fps))
    lags = np.arange(first, min(round(longest * fps), t // 2) + 1)
    if lags.size < 3:  # a peak needs a lag on each side within half the window
        raise ValueError(f"stride_period needs at least {2 * (first + 2)} frames, got {t}")
    r = np.empty((d.shape[0], lags.size))
    for k, lag in enumerate(lags):
        a, b = d[:, :-lag], d[:, lag:]
        a = a - a.mean(1, keepdims=True)
        b = b - b.mean(1, keepdims=True)
        den = np.sqrt((a * a).sum((1, 2)) * (b * b).sum((1, 2)))
        r[:, k] = (a * b).sum((1, 2)) / np.maximum(den, 1e-12)
    out = np.full(d.shape[0], np.nan)
    for n, rn in enumerate(r):
        top = rn.max()
        if top < min_correlation:
            continue
        peaks = [k for k in range(1, lags.size - 1) if rn[k] >= rn[k - 1] and rn[k] >= rn[k + 1]]
        peaks = [k for k in peaks if rn[k] >= 0.8 * top]
        if not peaks:
            continue
        k = peaks[0]
        curve = rn[k - 1] - 2 * rn[k] + rn[k + 1]
        shift = 0.5 * (rn[k - 1] - rn[k + 1]) / curve if curve < 0 else 0.0
        out[n] = (lags[k] + shift) / float(fps)
    return out.reshape(np.shape(pose)[:-2])


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


def control_distances(control: Any, pool: Any) -> np.ndarray:
    """Squared distances (N, M) between control sequences (N, T, 3) and a pool (M, T, 3):
    the sum over frames and channels after dividing each channel by its standard deviation
    over the pool's frames, so forward, sideways and turn count alike (a channel that is
    constant in the pool is left as it is). The distance behind
    :func:`natural_diversity` and :func:`nearest_control`."""
    c, q = np.asarray(control, dtype=np.float64), np.asarray(pool, dtype=np.float64)
    _check_control(c, "control")
    _check_control(q, "pool")
    if c.ndim != 3 or c.shape[1:] != q.shape[1:] or len(q) == 0:
        raise ValueError(
            f"control_distances needs controls (N, T, 3) and a non-empty pool (M, T, 3) of "
            f"the same T, got {c.shape} and {q.shape}"
        )
    scale = q.reshape(-1, q.shape[-1]).std(axis=0)
    scale = np.where(scale > 0, scale, 1.0)
    a, b = (c / scale).reshape(len(c), -1), (q / scale).reshape(len(q), -1)
    return np.sum(a**2, axis=1)[:, None] + np.sum(b**2, axis=1)[None, :] - 2.0 * a @ b.T


def nearest_control(control: Any, pool: Any) -> np.ndarray:
    """For each control sequence (N, T, 3), the index (N,) into ``pool`` (M, T, 3) of the
    sequence closest by :func:`control_distances`: motion matching's query, whole windows.
    The bench's "nearest training window" row places the training poses so found on the
    test controls, real motion chosen for the control it was asked."""
    return np.argmin(control_distances(control, pool), axis=1)


def natural_diversity(pose: Any, control: Any, *, takes: Any = None) -> float:
    """The data's own diversity under (nearly) one control: a reference for :func:`diversity`.

    Each window i (pose (N, T, 63) metres, control (N, T, 3)) is paired with its nearest
    neighbour j in control space: the window, from another take when ``takes`` (N,) is
    given, whose control sequence is closest by :func:`control_distances` (Euclidean over
    frames and channels after dividing each control channel by its standard deviation over
    the set, so forward, sideways and turn count alike). Returns the mean over windows of
    the mean per-joint distance (metres) between the poses of i and j: how different two
    real motions with close controls are. Needs N >= 2 (and two takes when ``takes`` is given)."""
    p = _joints(pose)
    c = np.asarray(control, dtype=np.float64)
    _check_control(c)
    if p.ndim != 4 or c.shape[:2] != p.shape[:2] or p.shape[0] < 2:
        raise ValueError(
            f"natural_diversity needs (N >= 2, T, 63) poses with (N, T, 3) controls, got "
            f"{np.shape(pose)} and {c.shape}"
        )
    dist = control_distances(c, c)
    if takes is None:
        np.fill_diagonal(dist, np.inf)
    else:
        t = np.asarray(takes)
        dist[t[:, None] == t[None, :]] = np.inf
    nearest = np.argmin(dist, axis=1)
    ok = np.isfinite(dist[np.arange(len(dist)), nearest])
    if not ok.any():
        raise ValueError("natural_diversity needs windows from at least two takes")
    gaps = np.linalg.norm(p[ok] - p[nearest[ok]], axis=-1)  # (n, T, 21)
    return float(gaps.mean())


def motion_quality(
    pose: Any, control: Any, *, fps: float, rule: str = "floor", contact_height: float | None = None
) -> dict[str, float]:
    """The per-motion metrics for one set of motions (N, T, 63) with controls (N, T, 3):
    foot sliding (m/s), skate ratio, contact rate (contact ``rule``, see
    :func:`foot_contacts`), bone-length std (m), jerk in the world (m/s^3)."""
    contact = {"rule": rule, "contact_height": contact_height}
    return {
        "foot_sliding": foot_sliding(pose, control, fps=fps, **contact),
        "skate_ratio": skate_ratio(pose, control, fps=fps, **contact),
        "contact_rate": contact_rate(pose, **contact),
        "bone_length_std": bone_length_variation(pose),
        "jerk": jerk(pose, fps=fps, control=control),
    }
