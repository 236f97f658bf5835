"""Foot locking: planted feet stay put, bones keep their lengths, nothing else moves."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from motionflows.data.features import integrate_root
from motionflows.data.pipeline import make_windows
from motionflows.data.synthetic import straight_walk
from motionflows.evaluation.motion import bone_lengths, foot_contacts, foot_sliding, to_global
from motionflows.foot_lock import (
    LEGS,
    StreamingFootLock,
    _stance_shift,
    _to_root_frame,
    _two_bone_ik,
    foot_lock,
)

FPS = 20.0
LEG_JOINTS = (2, 3, 4, 6, 7, 8)  # knees, ankles, toes: the only joints foot_lock moves


def _crouch(pose: np.ndarray, depth: float) -> np.ndarray:
    """The walk with the body ``depth`` m lower and the knees bent to keep the feet (and
    every bone length): the synthetic walker stands on nearly straight legs, which leave a
    planted foot no room to be held."""
    j = pose.reshape(pose.shape[:-1] + (21, 3)).copy()
    down = np.array([0.0, depth, 0.0])
    moved_by_ik = [k for leg in LEGS for k in leg[1:]]
    for hip, knee, ankle, _ in LEGS:
        j[..., knee, :], _ = _two_bone_ik(
            j[..., hip, :] - down,
            j[..., knee, :] - down,
            j[..., ankle, :] - down,
            j[..., ankle, :],
            np.zeros(j.shape[:-2]),
        )
    j[..., [k for k in range(21) if k not in moved_by_ik], :] -= down
    return j.reshape(pose.shape)


@pytest.fixture(scope="module")
def walk():
    cut, _ = make_windows([straight_walk(1.2, 6.0, seed=s) for s in range(3)], 80, 20)
    return np.asarray(cut.pose, np.float64), np.asarray(cut.control, np.float64)


@pytest.fixture(scope="module")
def creeping(walk):
    """Crouched synthetic walks whose root travels 10 % faster than their feet step: the
    planted feet slide forward with the body, MoGlow's failure on an unseen performer."""
    pose, control = walk
    return _crouch(pose, 0.05), control * np.array([1.1, 1.0, 1.0])


def test_planted_feet_stop_sliding_and_bones_keep_their_lengths(creeping):
    pose, control = creeping
    before = foot_sliding(pose, control, fps=FPS)
    locked = foot_lock(pose, control)
    assert before > 0.1  # the failure is there to fix
    assert foot_sliding(locked, control, fps=FPS) < 1e-6
    np.testing.assert_allclose(bone_lengths(locked), bone_lengths(pose), atol=1e-6)
    joints, new = pose.reshape(*pose.shape[:-1], 21, 3), locked.reshape(*pose.shape[:-1], 21, 3)
    others = [j for j in range(21) if j not in LEG_JOINTS]
    np.testing.assert_array_equal(new[..., others, :], joints[..., others, :])
    moved = np.abs(new - joints).max()
    assert 0.01 < moved < 0.5  # it did move the legs, by centimetres, not metres
    # heights of the feet are kept, so the contact test sees the same stances
    np.testing.assert_array_equal(foot_contacts(locked), foot_contacts(pose))


def test_a_foot_out_of_reach_keeps_its_height_and_slides_less(walk):
    """Straight legs and 25 % creep: the stance ends are beyond the leg's reach. The foot
    is held as far as the leg reaches, never lifted out of contact."""
    pose, control = walk
    control = control * np.array([1.25, 1.0, 1.0])
    locked = foot_lock(pose, control)
    feet = [3 * k + 1 for k in (3, 4, 7, 8)]  # y of the ankles and toes
    np.testing.assert_allclose(locked[..., feet], pose[..., feet], atol=1e-9)
    before, after = foot_sliding(pose, control, fps=FPS), foot_sliding(locked, control, fps=FPS)
    assert 0 < after < 0.95 * before
    np.testing.assert_allclose(bone_lengths(locked), bone_lengths(pose), atol=1e-6)


def test_the_streaming_lock_sees_only_the_past_and_holds_feet_within_its_reach(creeping):
    """Frame by frame (each frame's output fixed before the next arrives), on the creeping
    walks: at least half the sliding goes (the 5 cm cap keeps the rest), every bone keeps
    its length, no joint but the legs moves, and no foot is moved further than
    ``max_shift`` from where it was drawn."""
    pose, control = creeping
    locked, moved = [], 0.0
    for p, c in zip(pose, control, strict=True):
        world, yaw = to_global(p, c).reshape(-1, 21, 3), integrate_root(c)[1]
        lock = StreamingFootLock(fps=FPS, max_shift=0.05)
        held = np.stack([lock.step(w, a) for w, a in zip(world, yaw, strict=True)])
        moved = max(moved, np.abs(held[:, [3, 4, 7, 8], :] - world[:, [3, 4, 7, 8], :]).max())
        locked.append(p + _to_root_frame(held - world, yaw).reshape(p.shape))
    locked = np.stack(locked)
    before = foot_sliding(pose, control, fps=FPS)
    assert foot_sliding(locked, control, fps=FPS) < 0.5 * before  # the cap leaves some
    np.testing.assert_allclose(bone_lengths(locked), bone_lengths(pose), atol=1e-6)
    others = [j for j in range(21) if j not in LEG_JOINTS]
    j_new, j_old = locked.reshape(*pose.shape[:-1], 21, 3), pose.reshape(*pose.shape[:-1], 21, 3)
    np.testing.assert_allclose(j_new[..., others, :], j_old[..., others, :], atol=1e-12)
    assert 0.01 < moved <= 0.05 + 1e-9
    with pytest.raises(ValueError, match=r"\(21, 3\)"):
        StreamingFootLock().step(np.zeros(63), 0.0)
    with pytest.raises(ValueError, match="max_shift"):
        StreamingFootLock(max_shift=0.0)


def test_the_streaming_lock_does_not_jump_when_a_foot_lands_again_inside_its_fade(walk):
    """A foot lifted for one frame lands while its last stance's shift is still fading out:
    the new stance must start where the foot is shown, not snap to where it was drawn (it
    jumped by ~(1 - 1 / (blend + 1)) * max_shift, a 0.95 m/s pop in ``play --foot-lock``)."""
    frame = _crouch(walk[0][0], 0.08)[5].reshape(21, 3)
    seq = np.stack([frame + np.array([0.0, 0.0, 0.01 * t]) for t in range(24)])  # 1 cm/frame
    seq[12, [3, 4], 1] += 0.06  # the left ankle and toe off the floor for one frame
    lock = StreamingFootLock(fps=FPS, blend=3, max_shift=0.05)
    held = np.stack([lock.step(w, 0.0) for w in seq])
    _, _, ankle, toe = LEGS[0]
    shown = 0.5 * (held[:, ankle, [0, 2]] + held[:, toe, [0, 2]])
    drawn = 0.5 * (seq[:, ankle, [0, 2]] + seq[:, toe, [0, 2]])
    steps, raw = np.linalg.norm(np.diff(shown, axis=0), axis=-1), 0.01
    assert np.abs(shown - drawn).max() > 0.02  # the stance is held: the test is not vacuous
    # the fade releases at most max_shift / (blend + 1) a frame on top of the foot's own move
    assert steps.max() <= raw + 0.05 / 4 + 1e-9, steps.round(4)


def test_feet_in_the_air_are_left_alone(creeping):
    pose, control = creeping
    lifted = pose + np.tile([0.0, 1.0, 0.0], 21)  # 1 m up: no foot below 5 cm
    out = foot_lock(lifted, control, rule="absolute")
    np.testing.assert_allclose(out, lifted, atol=1e-12)


def test_the_shift_holds_the_anchor_in_a_stance_and_fades_outside():
    contact = np.zeros(12, bool)
    contact[3:6] = True
    centre = np.stack([np.arange(12.0), np.zeros(12)], -1)  # moving 1 per frame along x
    d = _stance_shift(centre[None], contact[None], blend=3)[0, :, 0]
    # anchor = mean of x over the stance = 4: shifts 1, 0, -1; a quarter less per frame away
    np.testing.assert_allclose(d[3:6], [1.0, 0.0, -1.0])
    np.testing.assert_allclose(d[:3], [0.25, 0.5, 0.75])
    np.testing.assert_allclose(d[6:10], [-0.75, -0.5, -0.25, 0.0])
    np.testing.assert_allclose(d[10:], 0.0)
    # a short swing between two stances interpolates their shifts (weights summing to 1)
    contact[7:10] = True
    d = _stance_shift(centre[None], contact[None], blend=3)[0, :, 0]
    np.testing.assert_allclose(d[6], 0.5 * (-1.0) + 0.5 * 1.0)


def test_dtype_jax_input_and_errors(creeping):
    pose, control = creeping
    out = foot_lock(jnp.asarray(pose[:2], jnp.float32), jnp.asarray(control[:2], jnp.float32))
    assert isinstance(out, np.ndarray) and out.dtype == np.float32 and out.shape == pose[:2].shape
    with pytest.raises(ValueError, match="same leading shape"):
        foot_lock(pose[:2], control[:3])
    bad = pose[:2].copy()
    bad[0, 5, 7] = np.nan
    with pytest.raises(ValueError, match="finite"):
        foot_lock(bad, control[:2])
    with pytest.raises(ValueError, match="blend"):
        foot_lock(pose[:2], control[:2], blend=-1)
    with pytest.raises(ValueError, match=r"\(\.\.\., T, 63\)"):
        foot_lock(pose[..., :60], control)
