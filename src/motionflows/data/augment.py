"""Augmentations of (pose, control) sequences; each is an involution (applied twice = id).

Shapes: pose (..., T, 63), control (..., T, 3) with (forward, sideways, turn).

* Mirror (left <-> right): negate x of every joint, swap joints with ``MIRROR_JOINTS``,
  negate ``sideways`` and ``turn``.
* Time reversal: ``pose'[s] = pose[T-1-s]``. For the control of the reversed sequence, the
  step from old frame t to t-1 seen in the root frame of t is, exactly,
  ``rev(c) = (R(-turn) @ (-sideways, -forward), -turn)`` of the old control ``c = c[t-1]``
  (2-D rotation of (x=sideways, z=forward) as ``R_y``). So ``c'[s] = rev(c[T-2-s])`` for
  s < T-1, and the final control, whose old counterpart lies outside the sequence, is
  ``rev(c[T-1])`` (an approximation at one boundary frame that keeps the map an
  involution).
"""

from __future__ import annotations

import numpy as np

from motionflows.data.features import Clip
from motionflows.data.names import MIRROR_JOINTS, NUM_JOINTS


def mirror_pose(pose: np.ndarray) -> np.ndarray:
    pose = np.asarray(pose)
    p = pose.reshape(pose.shape[:-1] + (NUM_JOINTS, 3))[..., list(MIRROR_JOINTS), :].copy()
    p[..., 0] = -p[..., 0]
    return p.reshape(pose.shape)


def mirror_control(control: np.ndarray) -> np.ndarray:
    c = np.array(control, copy=True)
    c[..., 1:] = -c[..., 1:]
    return c


def reverse_step(control: np.ndarray) -> np.ndarray:
    """``rev(c)``: the same root step walked backwards, in the other end's root frame."""
    c = np.asarray(control)
    f, s, a = c[..., 0], c[..., 1], c[..., 2]
    ca, sa = np.cos(-a), np.sin(-a)
    x, z = -s, -f
    out = np.stack([-sa * x + ca * z, ca * x + sa * z, -a], axis=-1)
    return out.astype(c.dtype, copy=False)


def reverse_time(pose: np.ndarray, control: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pose = np.asarray(pose)
    control = np.asarray(control)
    new_pose = pose[..., ::-1, :].copy()
    rc = reverse_step(control)
    new_control = np.concatenate([rc[..., -2::-1, :], rc[..., -1:, :]], axis=-2)
    return new_pose, new_control


def mirror_clip(clip: Clip) -> Clip:
    return Clip(
        mirror_pose(clip.pose),
        mirror_control(clip.control),
        clip.fps,
        clip.name,
        dict(clip.meta, mirrored=not clip.meta.get("mirrored", False)),
    )


def reverse_clip(clip: Clip) -> Clip:
    p, c = reverse_time(clip.pose, clip.control)
    return Clip(
        p, c, clip.fps, clip.name, dict(clip.meta, reversed=not clip.meta.get("reversed", False))
    )


def augment_clips(clips: list[Clip], *, mirror: bool, reverse: bool) -> list[Clip]:
    """Originals plus mirrored and/or reversed copies (same take names: splits stay by take)."""
    out = list(clips)
    if mirror:
        out += [mirror_clip(c) for c in clips]
    if reverse:
        out += [reverse_clip(c) for c in out]
    return out
