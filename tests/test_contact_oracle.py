"""benchmarks/contact_oracle.py: the contact channels are the scoring rule's contacts, and
the oracle MoGlow is trained and sampled with them."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

import experiments.moglow as moglow
from motionflows.data.names import FOOT_JOINTS
from motionflows.data.pipeline import Standardizer, make_windows
from motionflows.data.synthetic import straight_walk
from motionflows.evaluation.motion import foot_contacts, foot_sliding


def _walks():
    cut, _ = make_windows([straight_walk(1.2, 4.0, seed=s) for s in range(2)], 40, 20)
    pose = np.asarray(cut.pose, np.float32).copy()
    # lift the left foot by 3 cm in the second half of the first window: out of contact
    joints = pose.reshape(*pose.shape[:-1], 21, 3)
    joints[0, 20:, list(FOOT_JOINTS[:2]), 1] += 0.03
    return pose, np.asarray(cut.control, np.float32)


def _perturbed(model, scale=0.05):
    """The model with noise on every parameter: at initialisation the couplings' last layers
    are zero, so no output would depend on the control."""
    graphdef, params, rest = nnx.split(model, nnx.Param, ...)
    leaves, tree = jax.tree.flatten(params)
    keys = jax.random.split(jax.random.key(9), len(leaves))
    noisy = [p + scale * jax.random.normal(k, p.shape) for p, k in zip(leaves, keys, strict=True)]
    return nnx.merge(graphdef, jax.tree.unflatten(tree, noisy), rest)


def test_contact_signs_are_the_floor_rule_of_the_motion_metrics(benchmark_script):
    oracle = benchmark_script("contact_oracle")
    pose, _ = _walks()
    truth = foot_contacts(pose)
    assert truth.any() and not truth.all()
    assert not truth[0, 20:, 0].any()  # the lifted foot
    signs = np.asarray(oracle.contact_signs(jnp.asarray(pose)))
    np.testing.assert_array_equal(signs, np.where(truth, 1.0, -1.0))


def test_told_contact_steps_score_the_feet_where_the_truth_stands(benchmark_script):
    told = benchmark_script("contact_oracle").told_contact_steps
    pose, control = _walks()
    real = told(pose, control, pose, 20.0)
    assert real["contact_agreement"] == 1.0
    # on the truth itself: the foot sliding of the motion metrics (the same steps)
    assert abs(real["told_stance_speed"] - foot_sliding(pose, control, fps=20.0)) < 1e-9
    # every frame's feet 1 cm further forward than the last: 0.2 m/s more where they stand
    creep = pose.reshape(*pose.shape[:-1], 21, 3).copy()
    creep[..., list(FOOT_JOINTS), 2] += 0.01 * np.arange(pose.shape[1])[None, :, None]
    moved = told(creep.reshape(pose.shape), control, pose, 20.0)
    assert moved["contact_agreement"] == 1.0  # heights unchanged
    assert moved["told_stance_speed"] > real["told_stance_speed"] + 0.1


def test_the_oracle_experiment_trains_and_samples_with_five_control_channels(benchmark_script):
    oracle = benchmark_script("contact_oracle")
    pose, control = _walks()
    st = Standardizer.fit(pose, control)
    exp = oracle.oracle_experiment(st)
    config = dataclasses.replace(moglow.PRESETS["smoke"], tau=4)
    model = exp.build(config, key=jax.random.key(0))
    assert model.control_dim == 5
    batch = {"pose": st.normalize_pose(pose), "control": st.normalize_control(control)}
    model = _perturbed(exp.initialize(model, batch, key=jax.random.key(1)))
    nll, _ = exp.loss(model, batch, jax.random.key(2))
    assert np.isfinite(float(nll))
    # evaluate sees the true contacts: the same as the model given them by hand
    signs = np.where(foot_contacts(pose), 1.0, -1.0).astype(np.float32)
    given = np.concatenate([batch["control"], signs], axis=-1)
    got = exp.evaluate(model, batch, jax.random.key(3))["official"]
    want = model.log_prob(jnp.asarray(batch["pose"]), jnp.asarray(given))
    np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-6)
    flipped = model.log_prob(jnp.asarray(batch["pose"]), jnp.asarray(given * -1.0))
    assert not np.allclose(np.asarray(flipped), np.asarray(want))
    x = moglow.sample(model, jax.random.key(4), given[:1, :8], temperature=0.5)
    assert x.shape == (1, 8, 63) and np.all(np.isfinite(np.asarray(x)))
    with pytest.raises(ValueError, match=r"control must be \(B, T, 5\)"):
        moglow.sample(model, jax.random.key(4), batch["control"][:1, :8])
