"""A stance constraint inside a frame-by-frame sampler: a planted foot stays where it stood.

:func:`motionflows.foot_lock.foot_lock` cleans finished samples up. This module instead acts
while MoGlow draws: each drawn frame is corrected before it becomes the history of the
next, so the model carries on from feet that did not slide (the creep of a stance foot is
the model's own one-step error, compounded by running on its own output; see
docs/readme/moglow_quality.md).

For the previous frame x_{t-1} and the drawn frame x_t, both (..., 63) in metres in their
root frames, and the control c_{t-1} (..., 3) that moves the root from t-1 to t:

1. **Contact.** A foot stands at a frame while its lowest joint (ankle or toe) is below
   ``contact_height`` (y = 0 is the features' floor). It is held at t when it stands at
   t-1 and at t: the steps the foot-sliding metric counts.
2. **Hold.** The foot centre c (mean of ankle and toe, horizontal x, z) should stay where
   it was in the world: at x_{t-1}'s centre carried into frame t's root frame,
   ``R_y(-turn) (c_{t-1} - (sideways, forward))``
   (:func:`motionflows.data.features.carry_to_next_root`). The ankle and the toe of x_t move
   horizontally by ``d = carried - c_t``, shortened to ``max_shift`` if longer (the
   sampler's history then holds the rest of the slide; heights are not changed).
3. **Leg.** The knee is re-solved by the two-bone IK of :mod:`motionflows.foot_lock`
   (every bone keeps its length of frame t; an ankle out of reach is pulled towards the
   hip). The root, the hips and the upper body are not touched.

The constraint changes what the model draws: samples drawn with it are a different sampler's
output, reported beside the model's own samples, never instead of them.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax.numpy as jnp

from motionflows.data.features import carry_to_next_root
from motionflows.data.names import NUM_JOINTS
from motionflows.foot_lock import LEGS, _two_bone_ik

CONTACT_HEIGHT_M = 0.03
"""A foot stands while its lowest joint is below 3 cm (the features' floor is y = 0)."""
MAX_SHIFT_M = 0.03
"""The largest horizontal correction of a foot in one frame (3 cm: 0.6 m/s at 20 fps)."""

Array = Any


def hold_planted_feet(
    previous: Array,
    pose: Array,
    control: Array,
    *,
    contact_height: float = CONTACT_HEIGHT_M,
    max_shift: float = MAX_SHIFT_M,
    hold_height: bool = False,
    floor: bool = False,
    strength: float = 1.0,
) -> Array:
    """The drawn frame ``pose`` (..., 63) with its standing feet held (module docstring).

    previous (..., 63): frame t-1 as the sampler holds it; pose (..., 63): frame t as drawn;
    control (..., 3): c_{t-1} (forward, sideways m/frame, turn rad/frame). Metres, root
    frames. jax arrays; jittable."""
    shape = pose.shape
    before = previous.reshape(shape[:-1] + (NUM_JOINTS, 3))
    carried = carry_to_next_root(previous, control).reshape(before.shape)
    joints = pose.reshape(before.shape)
    out = joints
    yaw = jnp.zeros(shape[:-1], pose.dtype)  # the root frame faces +z
    for hip, knee, ankle, toe in LEGS:
        stands = (jnp.minimum(before[..., ankle, 1], before[..., toe, 1]) < contact_height) & (
            jnp.minimum(joints[..., ankle, 1], joints[..., toe, 1]) < contact_height
        )
        then = 0.5 * (carried[..., ankle, :] + carried[..., toe, :])
        now = 0.5 * (joints[..., ankle, :] + joints[..., toe, :])
        shift = strength * (then - now) * jnp.array([1.0, float(hold_height), 1.0], pose.dtype)
        size = jnp.linalg.norm(shift, axis=-1, keepdims=True)
        shift = shift * jnp.minimum(1.0, max_shift / jnp.maximum(size, 1e-12))
        shift = jnp.where(stands[..., None], shift, 0.0)
        if floor:  # a foot below the floor is lifted onto it
            lowest = jnp.minimum(joints[..., ankle, 1], joints[..., toe, 1])
            lift = jnp.maximum(-lowest, 0.0)
            shift = shift + lift[..., None] * jnp.array([0.0, 1.0, 0.0], pose.dtype)
            stands = stands | (lift > 0)
        knee_at, ankle_at = _two_bone_ik(
            joints[..., hip, :], joints[..., knee, :], joints[..., ankle, :],
            joints[..., ankle, :] + shift, yaw,
        )  # fmt: skip
        held = stands[..., None]
        out = out.at[..., knee, :].set(jnp.where(held, knee_at, joints[..., knee, :]))
        out = out.at[..., ankle, :].set(jnp.where(held, ankle_at, joints[..., ankle, :]))
        toe_at = joints[..., toe, :] + (ankle_at - joints[..., ankle, :])
        out = out.at[..., toe, :].set(jnp.where(held, toe_at, joints[..., toe, :]))
    return out.reshape(shape)


def stance_constraint(
    standardizer: Any,
    *,
    contact_height: float = CONTACT_HEIGHT_M,
    max_shift: float = MAX_SHIFT_M,
    hold_height: bool = False,
    floor: bool = False,
    strength: float = 1.0,
) -> Callable[[Array, Array, Array], Array]:
    """:func:`hold_planted_feet` in a model's standardised units, for
    ``MoGlow.sample(..., constraint=...)``: ``(previous (B, 63), drawn (B, 63), control
    (B, 3)) -> held (B, 63)``, every argument standardised by ``standardizer``."""
    p_mean = jnp.asarray(standardizer.pose_mean, jnp.float32)
    p_std = jnp.asarray(standardizer.pose_std, jnp.float32)
    c_mean = jnp.asarray(standardizer.control_mean, jnp.float32)
    c_std = jnp.asarray(standardizer.control_std, jnp.float32)

    def constrain(previous, pose, control):
        held = hold_planted_feet(
            p_mean + p_std * previous,
            p_mean + p_std * pose,
            c_mean + c_std * control,
            contact_height=contact_height,
            max_shift=max_shift,
            hold_height=hold_height,
            floor=floor,
            strength=strength,
        )
        return (held - p_mean) / p_std

    return constrain
