"""Foot locking: a post-process that keeps a planted foot where it stands.

A model that samples frame by frame lets a planted foot creep (the foot sliding of
:func:`motionflows.evaluation.motion.foot_sliding`). :func:`foot_lock` is the clean-up that
animation pipelines apply to such motion (footskate clean-up, after Kovar, Schreiner and
Gleicher 2002), done here with one two-bone IK per leg, on poses (..., T, 63) in metres in
the root frame with their controls (..., T, 3) (the layout of :mod:`motionflows.data.names`):

1. **Stances.** A foot stands while the calibrated contact rule
   (:func:`~motionflows.evaluation.motion.foot_contacts`, the rule the sliding is scored
   with) says so; each maximal run of such frames is one stance.
2. **Anchors.** A stance's anchor is the mean horizontal world position (x, z) of the foot
   centre c_t (mean of ankle and toe) over the stance. Each stance frame shifts the ankle
   and the toe horizontally by d_t = anchor - c_t, so the foot centre stays at the anchor;
   heights are not changed.
3. **Blending.** Between stances the shift fades linearly: a frame k frames after a stance
   ending at e and j frames before one starting at s gets ``a d_e + b d_s`` with
   ``a = max(0, 1 - k / (blend + 1))``, ``b = max(0, 1 - j / (blend + 1))``, both divided by
   ``a + b`` where that exceeds 1 (a short swing then interpolates between the two
   anchors).
4. **Leg.** With hip H, knee K and the shifted ankle A', thigh and shin lengths l1, l2 of
   that frame: an A' out of reach is first pulled horizontally towards the hip, at its
   height, until the stretched leg reaches it (the foot then still slides, by what is
   left); ``D = |A' - H|`` (clipped to ``[|l1 - l2|, l1 + l2]``), ``u = (A' - H) / D``, and the knee
   moves to ``H + x u + h n`` with ``x = (l1^2 - l2^2 + D^2) / (2 D)``,
   ``h = sqrt(l1^2 - x^2)`` and n the unit part of ``K - H`` orthogonal to u (the knee keeps
   its bending plane; the root's facing where that part vanishes). The toe moves with the
   ankle, so the foot keeps its shape.

Every bone keeps its length of that frame; the root, the hips and the upper body are not
touched. A post-process changes the model's samples: the bench and the quality targets
score the samples as drawn (``benchmarks/foot_heights.py --foot-lock`` reports locked ones
beside them, never instead).

:class:`StreamingFootLock` does the same one frame at a time, for a stream
(``MoGlow.stream_step``, ``motionflows play --foot-lock``), seeing only the past: a foot
stands while its height is less than 1.5 cm above the 5th percentile of both feet's
heights over the last 2 s (the calibrated rule on a sliding window), a stance's anchor is
where the foot is shown when it lands (its first frame, plus what is left of the last
stance's fading shift: the mean needs the future), so no fade is needed before a stance,
and the shift of its last frame fades out over ``blend`` frames after it.
A foot that creeps further than ``max_shift`` (5 cm) from its anchor drags the anchor along
at that distance: without the future a stance cannot share its correction out, and a
held foot the body has left behind would have to jump when it lifts.
"""

from __future__ import annotations

from collections import deque
from typing import Any

import numpy as np

from motionflows.data.features import integrate_root
from motionflows.data.names import NUM_JOINTS
from motionflows.evaluation.motion import (
    FLOOR_CONTACT_M,
    _check_control,
    _check_pose,
    contact_floor,
    foot_contacts,
    foot_heights,
    to_global,
)

LEGS: tuple[tuple[int, int, int, int], ...] = ((1, 2, 3, 4), (5, 6, 7, 8))
"""(hip, knee, ankle, toe) joint indices of the left and the right leg."""


def foot_lock(
    pose: Any,
    control: Any,
    *,
    blend: int = 3,
    rule: str = "floor",
    contact_height: float | None = None,
) -> np.ndarray:
    """Poses (..., T, 63) whose planted feet stay put (see the module docstring).

    pose (..., T, 63) in metres (root frame), control (..., T, 3) in m/frame and rad/frame;
    ``blend`` frames of fade before and after each stance; ``rule`` and ``contact_height``
    as in :func:`~motionflows.evaluation.motion.foot_contacts`. Returns a numpy array of
    the pose's shape and floating dtype."""
    _check_pose(pose)
    _check_control(control)
    if np.shape(pose)[:-1] != np.shape(control)[:-1]:
        raise ValueError(
            f"pose (..., T, 63) and control (..., T, 3) need the same leading shape, got "
            f"{np.shape(pose)} and {np.shape(control)}"
        )
    if not (isinstance(blend, int | np.integer) and blend >= 0):
        raise ValueError(f"blend must be a number of frames >= 0, got {blend!r}")
    dtype = np.result_type(np.asarray(pose).dtype, np.float32)
    local = np.asarray(pose, np.float64)
    ctrl = np.asarray(control, np.float64)
    if not (np.all(np.isfinite(local)) and np.all(np.isfinite(ctrl))):
        raise ValueError("foot_lock: pose and control must be finite (they hold NaN or inf)")
    if local.shape[-2] < 2:
        return local.astype(dtype)
    shape = local.shape
    world = to_global(local, ctrl).reshape(shape[:-1] + (NUM_JOINTS, 3))
    contact = foot_contacts(local, rule=rule, contact_height=contact_height)  # (..., T, 2)
    yaw = integrate_root(ctrl)[1]
    new = world.copy()
    for side, leg in enumerate(LEGS):
        centre = 0.5 * (world[..., leg[2], :] + world[..., leg[3], :])
        shift = _stance_shift(centre[..., [0, 2]], contact[..., side], blend)
        _shift_leg(new, world, leg, shift, yaw)
    delta = _to_root_frame(new - world, yaw)
    return (local + delta.reshape(shape)).astype(dtype)


class StreamingFootLock:
    """Foot locking of a stream of world frames, one at a time (see the module docstring).

    ``lock.step(joints, yaw)``: world joints (21, 3) in metres of frame t (root frame
    placed by ``p_t + R_y(yaw_t)``, as ``motionflows.play`` and
    :func:`~motionflows.evaluation.motion.to_global` place them) and the root's heading
    yaw_t -> the joints with the planted feet held. ``reset()`` starts a new stream."""

    def __init__(
        self,
        *,
        blend: int = 3,
        fps: float = 20.0,
        floor_seconds: float = 2.0,
        max_shift: float = 0.05,
    ):
        if not (isinstance(blend, int | np.integer) and blend >= 0):
            raise ValueError(f"blend must be a number of frames >= 0, got {blend!r}")
        numbers = {"fps": fps, "floor_seconds": floor_seconds, "max_shift": max_shift}
        bad = {k: v for k, v in numbers.items() if not (np.isfinite(v) and v > 0)}
        if bad:
            raise ValueError(f"StreamingFootLock: {bad} must be finite numbers > 0")
        self.blend, self.max_shift = int(blend), float(max_shift)
        self._window = max(1, int(round(floor_seconds * fps)))  # frames of feet heights
        self.reset()

    def reset(self) -> None:
        self._heights: deque = deque(maxlen=self._window)  # (2,) per frame
        self._anchor: list[np.ndarray | None] = [None, None]
        self._last = np.zeros((2, 2))  # the shift of each foot's latest stance frame
        self._since = [self.blend + 1] * 2  # frames since that stance frame

    def step(self, joints: Any, yaw: float) -> np.ndarray:
        world = np.asarray(joints, np.float64)
        if world.shape != (NUM_JOINTS, 3) or not np.all(np.isfinite(world)):
            raise ValueError(
                f"StreamingFootLock.step: joints must be finite world positions "
                f"({NUM_JOINTS}, 3) in metres, got shape {world.shape}"
            )
        heights = foot_heights(world)  # (2,): left, right
        self._heights.append(heights)
        floor = contact_floor(np.asarray(self._heights))  # the rule's floor over the window
        new = world.copy()
        for side, leg in enumerate(LEGS):
            centre = 0.5 * (world[leg[2], [0, 2]] + world[leg[3], [0, 2]])
            if heights[side] < floor + FLOOR_CONTACT_M:
                if self._anchor[side] is None:  # the foot lands: hold it where it is shown,
                    # the last stance's shift still fading (no jump when it lands again soon)
                    self._anchor[side] = centre + self._faded(side, self._since[side] + 1)
                shift = self._anchor[side] - centre
                size = float(np.hypot(*shift))
                if size > self.max_shift:  # too far to hold: the anchor follows the foot
                    shift = shift * (self.max_shift / size)
                    self._anchor[side] = centre + shift
                self._last[side] = shift
                self._since[side] = 0
            else:
                self._anchor[side] = None
                self._since[side] += 1
                shift = self._faded(side, self._since[side])
            if np.any(shift):
                _shift_leg(new, world, leg, shift, np.float64(yaw))
        return new

    def _faded(self, side: int, since: int) -> np.ndarray:
        """The shift of foot ``side`` ``since`` frames after its latest stance frame: that
        frame's shift faded linearly to 0 over ``blend + 1`` frames."""
        return self._last[side] * max(0.0, 1.0 - since / (self.blend + 1))


def _shift_leg(new: np.ndarray, world: np.ndarray, leg, shift: np.ndarray, yaw) -> None:
    """Write into ``new`` (..., 21, 3) the knee, ankle and toe of ``leg`` re-solved so the
    ankle moves horizontally by ``shift`` (..., 2) (x, z) from ``world`` (steps 4 and 5)."""
    hip, knee, ankle, toe = leg
    target = world[..., ankle, :].copy()
    target[..., [0, 2]] += shift
    knee_at, ankle_at = _two_bone_ik(
        world[..., hip, :], world[..., knee, :], world[..., ankle, :], target, yaw
    )
    new[..., knee, :] = knee_at
    new[..., ankle, :] = ankle_at
    new[..., toe, :] = world[..., toe, :] + (ankle_at - world[..., ankle, :])


def _to_root_frame(world_delta: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """World displacements (..., T, J, 3) seen in each frame's root frame (R_y(yaw)^T)."""
    cos, sin = np.cos(yaw)[..., None], np.sin(yaw)[..., None]
    dx, dy, dz = world_delta[..., 0], world_delta[..., 1], world_delta[..., 2]
    return np.stack([dx * cos - dz * sin, dy, dx * sin + dz * cos], axis=-1)


def _stance_shift(centre: np.ndarray, contact: np.ndarray, blend: int) -> np.ndarray:
    """The horizontal shift (..., T, 2) of one foot: anchor - centre in its stances, faded
    between them (steps 2 and 3 of the module docstring). centre (..., T, 2) world (x, z),
    contact (..., T) bool."""
    lead = contact.shape[:-1]
    t = contact.shape[-1]
    c = contact.reshape(-1, t)
    xz = centre.reshape(-1, t, 2)
    rows = np.arange(len(c))[:, None]
    start = c & ~np.concatenate([np.zeros_like(c[:, :1]), c[:, :-1]], axis=1)
    stance = rows * t + np.cumsum(start, axis=1)  # a unique id per (row, stance)
    ids, counts = stance[c], np.bincount(stance[c], minlength=len(c) * t + t)
    anchor = (
        np.stack(
            [np.bincount(ids, weights=xz[..., k][c], minlength=len(counts)) for k in range(2)], -1
        )
        / np.maximum(counts, 1)[:, None]
    )
    d = np.where(c[..., None], anchor[stance] - xz, 0.0)
    frame = np.broadcast_to(np.arange(t), c.shape)
    last = np.maximum.accumulate(np.where(c, frame, -1), axis=1)
    nxt = np.minimum.accumulate(np.where(c, frame, t)[:, ::-1], axis=1)[:, ::-1]
    a = np.where(last >= 0, np.clip(1.0 - (frame - last) / (blend + 1.0), 0.0, 1.0), 0.0)
    b = np.where(nxt < t, np.clip(1.0 - (nxt - frame) / (blend + 1.0), 0.0, 1.0), 0.0)
    norm = np.maximum(a + b, 1.0)
    d_last = d[rows, np.maximum(last, 0)]
    d_next = d[rows, np.minimum(nxt, t - 1)]
    faded = (a[..., None] * d_last + b[..., None] * d_next) / norm[..., None]
    return np.where(c[..., None], d, faded).reshape(lead + (t, 2))


def _two_bone_ik(hip, knee, ankle, target, yaw):
    """(knee', ankle'), each (..., 3): the leg re-solved to put the ankle at ``target``
    (step 4 of the module docstring); thigh and shin keep their lengths."""
    l1 = np.linalg.norm(knee - hip, axis=-1)
    l2 = np.linalg.norm(ankle - knee, axis=-1)
    reach = target - hip
    # out of reach: pull the target horizontally towards the hip, at its height
    level = np.sqrt(np.maximum((1.0 - 1e-6) * (l1 + l2) ** 2 - reach[..., 1] ** 2, 0.0))
    flat = np.hypot(reach[..., 0], reach[..., 2])
    pull = np.minimum(1.0, level / np.maximum(flat, 1e-12))
    reach = reach * np.stack([pull, np.ones_like(pull), pull], axis=-1)
    dist = np.linalg.norm(reach, axis=-1)
    facing = np.stack([np.sin(yaw), np.zeros_like(yaw), np.cos(yaw)], axis=-1)
    u = np.where(dist[..., None] > 1e-9, reach / np.maximum(dist, 1e-9)[..., None], facing)
    dist = np.clip(dist, np.abs(l1 - l2), l1 + l2)
    bend = knee - hip
    n = bend - np.sum(bend * u, -1, keepdims=True) * u
    alt = facing - np.sum(facing * u, -1, keepdims=True) * u
    n = np.where(np.linalg.norm(n, axis=-1, keepdims=True) > 1e-9, n, alt)
    n = n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
    x = (l1**2 - l2**2 + dist**2) / (2.0 * np.maximum(dist, 1e-9))
    h = np.sqrt(np.maximum(l1**2 - x**2, 0.0))
    return hip + x[..., None] * u + h[..., None] * n, hip + dist[..., None] * u
