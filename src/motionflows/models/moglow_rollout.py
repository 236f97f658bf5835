"""Foot sliding of MoGlow's own short rollouts: a training loss for planted feet.

MoGlow's likelihood scores every frame given the *real* history; its samples run on their
own, and the stance foot creeps (docs/readme/moglow_quality.md: about half of the excess
sliding builds up over a rollout). :func:`rollout_sliding` lets the training step see that:
from the start of each training window it draws ``model.rollout_frames`` = k frames with the
sampler's own frame step (:meth:`MoGlow.generate`), seeded with the window's first tau real
poses and following the window's controls, latents z ~ T * N(0, I) held fixed
(reparameterised, so the gradient flows through every drawn frame into the parameters), and
measures how far each planted foot moves in the world from one frame to the next::

    s_t = || P (foot(x^_t) - foot(carry(x^_{t-1}, c_{t-1}))) ||      t = tau .. tau + k - 1

foot = the centre of a foot's ankle and toe, P the horizontal (x, z) part, carry =
:func:`motionflows.data.features.carry_to_next_root` (frame t-1's pose as it reads in frame
t's root frame if every joint stays where it is in the world), x^_{tau-1} the last real
seed pose. A step counts where the drawn foot is in contact at t-1 and at t by the bench's
calibrated floor rule (:func:`motionflows.evaluation.motion.foot_contacts`, the floor taken
from the real window's feet), so the loss is the bench's foot sliding of the rollouts, in
cm per frame (x fps / 100 = m/s). Contacts are a test, not differentiated: the gradient
pulls planted feet to stay, it does not lift feet out of contact.

Shapes: pose (B, T, 63) and control (B, T, 3) standardised, as the model trains on; the
model's ``units`` (:meth:`MoGlow.with_units`) turn them into metres and m/frame, rad/frame.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from motionflows.data.features import carry_to_next_root
from motionflows.data.names import FOOT_JOINTS, NUM_JOINTS
from motionflows.evaluation.motion import FLOOR_CONTACT_M, contact_floor, foot_heights

Array = jax.Array

__all__ = ["rollout_sliding", "stance_steps"]


def _feet(pose: Array) -> tuple[Array, Array]:
    """(horizontal foot centres (..., 2, 2): foot, (x, z); heights (..., 2)) of poses
    (..., 63) in metres."""
    j = pose.reshape(*pose.shape[:-1], NUM_JOINTS, 3)
    left, right = FOOT_JOINTS[:2], FOOT_JOINTS[2:]
    centre = jnp.stack([0.5 * (j[..., a, :] + j[..., b, :]) for a, b in (left, right)], axis=-2)
    return centre[..., ::2], foot_heights(j)


def stance_steps(frames: Array, control: Array, floor: Array) -> tuple[Array, Array]:
    """World steps of the feet between consecutive frames, and where they stand.

    frames (B, S + 1, 63) root-frame poses in metres, control (B, S, 3) = c_t of frames
    0..S-1 (the move t -> t+1, m/frame and rad/frame), floor (B,) metres. Returns
    (step (B, S, 2) the horizontal world distance each foot's centre (ankle and toe)
    moves from frame t to t+1, metres; contact (B, S, 2) bool, the foot within
    ``FLOOR_CONTACT_M`` of the floor at both frames). With ``floor`` from
    :func:`motionflows.evaluation.motion.contact_floor` of the same frames, the mean step
    over contacts x fps is :func:`~motionflows.evaluation.motion.foot_sliding`.
    """
    moved = carry_to_next_root(frames[:, :-1], control)  # frame t as seen from t + 1's root
    before, h_before = _feet(moved)
    after, h_after = _feet(frames[:, 1:])
    step = jnp.sqrt(jnp.sum(jnp.square(after - before), axis=-1) + 1e-12)  # smooth at 0
    level = floor[:, None, None] + FLOOR_CONTACT_M
    return step, (h_before < level) & (h_after < level)


def rollout_sliding(model, pose: Array, control: Array, key: Array) -> Array:
    """Mean stance-foot step (cm per frame, a scalar; 0 without contacts) of the model's
    own rollouts from the start of each window (the module docstring). Differentiable in
    the model's parameters; needs T >= tau + ``model.rollout_frames``."""
    tau, frames = model.tau, model.rollout_frames
    batch, length = pose.shape[0], pose.shape[1]
    if length < tau + frames:
        raise ValueError(
            f"rollout_sliding: windows of {length} frames hold no {frames}-frame rollout after "
            f"the tau={tau} seed frames; use windows of at least {tau + frames} frames or a "
            "smaller rollout_frames"
        )
    z = model.base_density().sample(key, (batch, frames), temperature=model.rollout_temperature)
    drawn = model.generate(
        z,
        control[:, tau : tau + frames],
        seed_history=pose[:, :tau],
        seed_control=control[:, :tau],
    )
    pose_m, control_m = model.in_metres(pose, control)
    drawn_m, _ = model.in_metres(drawn, control[:, :1])
    floor = jax.lax.stop_gradient(contact_floor(_feet(pose_m)[1]))  # the real window's floor
    chain = jnp.concatenate([pose_m[:, tau - 1 : tau], drawn_m], axis=1)  # (B, k + 1, 63)
    step, contact = stance_steps(chain, control_m[:, tau - 1 : tau + frames - 1], floor)
    count = jnp.sum(contact.astype(jnp.float32))
    return 100.0 * jnp.sum(jnp.where(contact, step, 0.0)) / jnp.maximum(count, 1.0)
