"""The in-loop stance hold: a foot standing at t-1 and t is put where it stood in the world."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from motionflows.data.features import carry_to_next_root
from motionflows.data.synthetic import straight_walk
from motionflows.evaluation.motion import bone_lengths
from motionflows.foot_lock import LEGS
from motionflows.stance import hold_planted_feet


def test_a_standing_foot_is_held_where_it_stood_and_bones_keep_their_lengths():
    clip = straight_walk(1.2, 2.0)
    prev, pose, ctrl = clip.pose[10].copy(), clip.pose[11].copy(), clip.control[10]
    j = pose.reshape(21, 3)
    hip, knee, ankle, toe = LEGS[0]
    j[[ankle, toe], 1] = 0.005  # the left foot on the floor in both frames
    prev.reshape(21, 3)[[ankle, toe], 1] = 0.005
    j[[ankle, toe], 0] += 0.02  # drawn 2 cm off to the left: a creeping foot
    held = np.asarray(hold_planted_feet(jnp.asarray(prev), jnp.asarray(pose), jnp.asarray(ctrl)))
    want = carry_to_next_root(prev, ctrl).reshape(21, 3)
    h = held.reshape(21, 3)
    centre = 0.5 * (h[ankle] + h[toe])
    np.testing.assert_allclose(centre[[0, 2]], 0.5 * (want[ankle] + want[toe])[[0, 2]], atol=1e-5)
    np.testing.assert_allclose(bone_lengths(held[None]), bone_lengths(pose[None]), atol=1e-5)
    untouched = [k for k in range(21) if k not in (knee, ankle, toe)]
    np.testing.assert_array_equal(h[untouched], j[untouched])
