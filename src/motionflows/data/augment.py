"""Augmentations of (pose, control) sequences. Mirror and time reversal are involutions
(applied twice = id); tempo replays a take faster or slower.

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
* Foot lock: the take's planted feet held where they stand
  (:func:`motionflows.foot_lock.foot_lock`, the footskate clean-up: each stance of the
  calibrated contact rule anchored at its mean position, the knee re-solved so that every
  bone keeps its length; the control is unchanged). Mocap's own foot sliding is cleaned
  from the training takes this way before the other copies are made.
* Tempo ``r``: the take played r times as fast. Its world joint positions
  (:func:`~motionflows.data.features.world_from_features`) are treated as recorded at
  ``r * fps`` and their features rebuilt at ``fps``
  (:func:`~motionflows.data.features.features_from_positions`: resampled, root smoothed,
  controls taken again): r = 0.8 is the same strides at 0.8 times the cadence and speed,
  (T - 1) / 0.8 frames. r = 1 gives the take back, but for its last frame.
  :func:`augment_clips` replays at ``1 / tempo`` and/or ``tempo`` (``tempo_replay``): a
  slower replay walks the same strides at a lower speed, so at a given speed the training
  set holds longer strides than its performers walked; a faster one, shorter strides.
"""

from __future__ import annotations

import numpy as np

from motionflows.data.features import (
    ROOT_SIGMA_S,
    Clip,
    features_from_positions,
    world_from_features,
)
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


def lock_clip(clip: Clip) -> Clip:
    """The take with its planted feet held (:func:`motionflows.foot_lock.foot_lock` on its
    poses and controls; the controls, name and fps kept; ``meta["foot_locked"]``)."""
    # imported here: motionflows.foot_lock needs motionflows.evaluation, which needs this package
    from motionflows.foot_lock import foot_lock

    pose = foot_lock(clip.pose, clip.control)
    return Clip(pose, clip.control, clip.fps, clip.name, dict(clip.meta, foot_locked=True))


def tempo_clip(clip: Clip, rate: float, *, root_sigma_s: float = ROOT_SIGMA_S) -> Clip:
    """The take played ``rate`` times as fast (see the module docstring); ``root_sigma_s``
    must be the one its features were made with."""
    if not (np.isfinite(rate) and rate > 0):
        raise ValueError(f"tempo rate must be a positive number, got {rate}")
    world = world_from_features(clip.pose, clip.control)
    meta = dict(clip.meta, tempo=float(rate) * float(clip.meta.get("tempo", 1.0)))
    return features_from_positions(
        world, clip.fps * rate, clip.fps, name=clip.name, meta=meta, root_sigma_s=root_sigma_s
    )


TEMPO_REPLAYS: tuple[str, ...] = ("both", "slower", "faster")
"""The values of ``tempo_replay`` (:func:`tempo_rates`)."""


def tempo_rates(tempo: float, replay: str = "both") -> tuple[float, ...]:
    """The replay rates of tempo augmentation: with ``tempo`` = 1.25, ``"both"`` gives
    (0.8, 1.25), ``"slower"`` (0.8,), ``"faster"`` (1.25,); ``tempo`` and ``1 / tempo``
    name the same pair, and ``tempo`` = 1 gives () (off)."""
    if replay not in TEMPO_REPLAYS:
        raise ValueError(f"tempo_replay must be one of {list(TEMPO_REPLAYS)}, got {replay!r}")
    if not (np.isfinite(tempo) and tempo > 0):
        raise ValueError(f"tempo must be a positive number, got {tempo}")
    if tempo == 1.0:
        return ()
    slow, fast = sorted((float(tempo), 1.0 / float(tempo)))
    return {"both": (slow, fast), "slower": (slow,), "faster": (fast,)}[replay]


def augment_clips(
    clips: list[Clip],
    *,
    mirror: bool,
    reverse: bool,
    tempo: float = 1.0,
    tempo_replay: str = "both",
    root_sigma_s: float = ROOT_SIGMA_S,
    foot_lock: bool = False,
) -> list[Clip]:
    """Originals plus mirrored and/or reversed copies and, with ``tempo`` != 1, all of
    those also played at the rates of :func:`tempo_rates` (``1 / tempo`` and/or ``tempo``
    times their speed; same take names: splits stay by take). With ``foot_lock`` the
    originals are foot-locked (:func:`lock_clip`) first, so every copy is too."""
    rates = tempo_rates(tempo, tempo_replay)
    if foot_lock:
        clips = [lock_clip(c) for c in clips]
    out = list(clips)
    if mirror:
        out += [mirror_clip(c) for c in clips]
    if reverse:
        out += [reverse_clip(c) for c in out]
    out += [tempo_clip(c, r, root_sigma_s=root_sigma_s) for r in rates for c in out]
    return out
