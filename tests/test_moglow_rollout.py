"""motionflows.models.moglow_rollout: the rollouts' stance-foot sliding (a training loss)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from motionflows.data.features import carry_to_next_root
from motionflows.data.names import FOOT_JOINTS, NUM_JOINTS
from motionflows.evaluation.motion import (
    FLOOR_CONTACT_M,
    contact_floor,
    foot_heights,
    foot_sliding,
    to_global,
)
from motionflows.models.moglow import MoGlow
from motionflows.models.moglow_rollout import rollout_sliding, stance_steps
from tests.params import perturbed


def _walk(rng, frames=9, batch=3):
    """Root-frame poses whose feet stand still in the world on the even frames' steps and
    move 1-3 cm on the odd ones (metres), near the floor; controls (m/frame, rad/frame)."""
    control = np.stack([rng.uniform(0.02, 0.06, (batch, frames)),
                        rng.uniform(-0.01, 0.01, (batch, frames)),
                        rng.uniform(-0.05, 0.05, (batch, frames))], axis=-1)  # fmt: skip
    pose = [rng.normal(0.0, 0.2, (batch, 63))]
    for t in range(1, frames):
        moved = carry_to_next_root(pose[-1], control[:, t - 1])
        if t % 2:
            moved = moved + rng.normal(0.0, 0.01, moved.shape)
        pose.append(moved)
    pose = np.stack(pose, axis=1)
    joints = pose.reshape(batch, frames, NUM_JOINTS, 3)
    joints[..., list(FOOT_JOINTS), 1] = rng.uniform(0.0, 0.03, (batch, frames, 4))
    return pose, control


def test_stance_steps_are_the_bench_foot_sliding():
    """The mean step over contacts, with the floor of the same frames, is the bench's
    ``foot_sliding`` at 1 fps, and a foot that stays put in the world steps 0."""
    rng = np.random.default_rng(0)
    pose, control = _walk(rng)
    floor = contact_floor(foot_heights(pose.reshape(*pose.shape[:-1], NUM_JOINTS, 3)))
    step, contact = stance_steps(
        jnp.asarray(pose, jnp.float32), jnp.asarray(control[:, :-1], jnp.float32),
        jnp.asarray(floor, jnp.float32))  # fmt: skip
    assert 0 < int(contact.sum()) < contact.size
    mean = float(jnp.sum(jnp.where(contact, step, 0.0))) / int(contact.sum())
    np.testing.assert_allclose(mean, foot_sliding(pose, control, fps=1.0), rtol=1e-4, atol=2e-6)
    np.testing.assert_allclose(np.asarray(step)[:, 1::2], 0.0, atol=2e-6)  # t -> t+1, t odd
    assert float(np.min(np.asarray(step)[:, 0::2])) > 1e-3


def test_rollout_sliding_scores_the_models_own_rollouts():
    """rollout_sliding = 100 x the mean world step of the drawn feet (frames placed with
    ``to_global``, contacts against the real window's floor) of ``generate`` from the
    window's first tau frames, with the same latents; differentiable."""
    model = MoGlow(tau=3, K=2, hidden=8, num_layers=1, residual=True, rollout_sliding=1.0,
                   rollout_frames=5, rollout_temperature=0.7, rngs=nnx.Rngs(0))  # fmt: skip
    std = np.full(63, 0.05)
    model = model.with_units(np.zeros(63), std, np.zeros(3), np.full(3, 0.02))
    model = perturbed(model, jax.random.key(4))
    rng = np.random.default_rng(1)
    pose_m, control_m = _walk(rng, frames=10, batch=4)
    pose, control = pose_m / std, control_m / 0.02
    key = jax.random.key(2)
    value = rollout_sliding(model, jnp.asarray(pose), jnp.asarray(control), key)

    z = model.base_density().sample(key, (4, 5), temperature=0.7)
    drawn = model.generate(
        z, control[:, 3:8], seed_history=pose[:, :3], seed_control=control[:, :3]
    )
    chain = np.concatenate([pose_m[:, 2:3], np.asarray(drawn) * std], axis=1)  # frames 2..7
    world = to_global(chain, control_m[:, 2:8]).reshape(4, 6, NUM_JOINTS, 3)
    feet = [0.5 * (world[..., a, :] + world[..., b, :]) for a, b in ((3, 4), (7, 8))]
    steps = np.stack(
        [np.hypot(*np.diff(f, axis=1)[..., [0, 2]].transpose(2, 0, 1)) for f in feet], -1
    )
    floor = contact_floor(foot_heights(pose_m.reshape(4, 10, NUM_JOINTS, 3)))
    low = foot_heights(chain.reshape(4, 6, NUM_JOINTS, 3)) < floor[:, None, None] + FLOOR_CONTACT_M
    both = low[:, :-1] & low[:, 1:]
    assert both.any()
    np.testing.assert_allclose(float(value), 100 * steps[both].mean(), rtol=2e-4)

    grads = nnx.grad(lambda m: rollout_sliding(m, jnp.asarray(pose), jnp.asarray(control), key))(
        model
    )
    norms = [float(jnp.abs(g).sum()) for g in jax.tree.leaves(grads)]
    assert all(np.isfinite(norms)) and sum(norms) > 0
