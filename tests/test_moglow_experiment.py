"""experiments/moglow.py follows the experiment protocol (tiny config, random windows)."""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from experiments import moglow as exp
from motionflows.config import DataConfig, apply_overrides, from_dict, to_dict
from motionflows.data.names import CONTROL_DIM, POSE_DIM
from tests.params import perturbed


def test_presets_and_config_round_trip():
    assert {"paper", "preferred", "quick"} <= set(exp.PRESETS)
    paper, preferred = exp.PRESETS["paper"], exp.PRESETS["preferred"]
    assert (paper.K, paper.hidden, paper.layers, paper.tau) == (16, 512, 2, 10)
    assert paper.dropout == 0.95 and preferred.dropout == 0.7
    assert paper.train.batch_size == 100 and paper.data.window == 80
    assert (paper.train.clip_value, paper.train.clip_norm) == (5.0, 100.0)
    assert from_dict(exp.Config, to_dict(paper)) == paper
    with pytest.raises(ValueError, match="window"):
        exp.Config(data=DataConfig(window=8), tau=10)
    with pytest.raises(ValueError, match="conditioner"):
        exp.Config(conditioner="rnn")
    assert exp.SCOPES["official"].scored_frames(80, paper) == 70
    assert exp.SCOPES["window"].scored_frames(80, paper) == 80


def test_own_history_reaches_the_model_and_the_loss():
    """``--set own_history=...`` builds a MoGlow that trains on its own draws: the loss
    (with a key) differs from the plain model's with the same parameters and is finite,
    its gradient too; bad values are refused by the config."""
    base = dataclasses.replace(exp.PRESETS["smoke"], data=DataConfig(window=8), tau=3)
    config = apply_overrides(
        base, ["own_history=1", "own_history_target=change", "own_history_passes=2"]
    )
    model = exp.build(config, key=jax.random.key(0))
    assert (model.own_history, model.own_history_target, model.own_history_passes) == (
        1.0, "change", 2)  # fmt: skip
    kp, kc = jax.random.split(jax.random.key(1))
    batch = {"pose": jax.random.normal(kp, (4, 8, POSE_DIM)),
             "control": jax.random.normal(kc, (4, 8, CONTROL_DIM))}  # fmt: skip
    model = exp.initialize(model, batch, key=jax.random.key(0))
    model = perturbed(model, jax.random.key(5))  # non-zero coupling heads: draws matter
    plain = exp.build(base, key=jax.random.key(0))
    nnx.update(plain, nnx.state(model, nnx.Param))
    own_loss, _ = exp.loss(model, batch, jax.random.key(2))
    plain_loss, _ = exp.loss(plain, batch, jax.random.key(2))
    assert np.isfinite(float(own_loss)) and not np.isclose(float(own_loss), float(plain_loss))
    grads = nnx.grad(lambda m: exp.loss(m, batch, jax.random.key(2))[0])(model)
    assert all(np.isfinite(g).all() for g in jax.tree.leaves(grads))
    for bad in ("own_history=2", "own_history_passes=0", "own_history_target=pose2"):
        with pytest.raises(ValueError, match="own_history"):
            apply_overrides(base, [bad])


def test_mask_padded_trains_on_the_real_frames_only():
    """``mask_padded=true``: the loss and its gradient ignore a padded window's frozen tail
    (whatever it holds) and are the per-frame NLL of the real target frames; windows with no
    padding score as without the mask. Without the mask the tail is trained on."""
    base = dataclasses.replace(exp.PRESETS["smoke"], data=DataConfig(window=10), tau=3)
    masked_config = apply_overrides(base, ["mask_padded=true"])
    model = exp.build(masked_config, key=jax.random.key(0))
    assert model.mask_padded and not exp.build(base, key=jax.random.key(0)).mask_padded
    kp, kc, kt = jax.random.split(jax.random.key(1), 3)
    pose = jax.random.normal(kp, (4, 10, POSE_DIM))
    control = jax.random.normal(kc, (4, 10, CONTROL_DIM))
    valid = jnp.ones((4, 10), bool).at[1, 6:].set(False).at[3, 4:].set(False)
    batch = {"pose": pose, "control": control, "valid": valid}
    model = perturbed(exp.initialize(model, batch, key=jax.random.key(0)), jax.random.key(5))
    other_tail = {
        "pose": jnp.where(valid[..., None], pose, jax.random.normal(kt, pose.shape)),
        "control": jnp.where(valid[..., None], control, 0.0),
        "valid": valid,
    }

    def loss_and_grads(m, b):
        (value, _), grads = nnx.value_and_grad(
            lambda m: exp.loss(m, b, jax.random.key(2)), has_aux=True
        )(m)
        return value, jax.tree.leaves(grads)

    value, grads = loss_and_grads(model, batch)
    value2, grads2 = loss_and_grads(model, other_tail)
    np.testing.assert_allclose(value2, value, rtol=1e-6)
    for g, g2 in zip(grads, grads2, strict=True):
        np.testing.assert_allclose(g2, g, rtol=1e-5, atol=1e-6)
    # the mean over the 7 + 3 + 7 + 1 real target frames (frames 3..9) of the per-frame NLL
    frames = model.log_prob(pose, control, key=jax.random.key(2), per_frame=True)
    assert frames.shape == (4, 7)
    real = jnp.where(valid[:, 3:], frames, 0.0)
    np.testing.assert_allclose(-jnp.sum(real) / 18, value, rtol=1e-5)
    whole = model.log_prob(pose, control, key=jax.random.key(2))
    np.testing.assert_allclose(jnp.sum(frames, axis=1), whole, rtol=1e-5)
    # no padding: the masked loss is the plain one; unmasked, the tail is trained on
    plain = exp.build(base, key=jax.random.key(0))
    nnx.update(plain, nnx.state(model))
    full = {**batch, "valid": jnp.ones_like(valid)}
    np.testing.assert_allclose(exp.loss(model, full, jax.random.key(2))[0],
                               exp.loss(plain, full, jax.random.key(2))[0], rtol=1e-5)  # fmt: skip
    assert not np.isclose(exp.loss(plain, batch, jax.random.key(2))[0],
                          exp.loss(plain, other_tail, jax.random.key(2))[0])  # fmt: skip


def test_protocol_functions():
    config = dataclasses.replace(
        exp.PRESETS["quick"], K=2, hidden=8, tau=3, data=DataConfig(window=8)
    )
    key = jax.random.key(0)
    model = exp.build(config, key=key)
    kp, kc = jax.random.split(jax.random.key(1))
    batch = {
        "pose": jax.random.normal(kp, (4, 8, POSE_DIM)),
        "control": jax.random.normal(kc, (4, 8, CONTROL_DIM)),
    }
    model = exp.initialize(model, batch, key=key)
    value, metrics = exp.loss(model, batch, jax.random.key(2))
    assert np.isfinite(float(value))
    np.testing.assert_allclose(metrics["bits_per_frame"], value / math.log(2), rtol=1e-6)
    ll = exp.evaluate(model, batch, jax.random.key(3))
    assert set(ll) == set(exp.SCOPES)
    for v in ll.values():
        assert v.shape == (4,)
    # the loss is the dropout-scored official NLL per target frame
    np.testing.assert_allclose(
        -jnp.mean(model.log_prob(batch["pose"], batch["control"], key=jax.random.key(2))) / 5,
        value,
        rtol=1e-5,
    )
    # (fresh coupling heads are zero, so dropout cannot change the score yet)
    np.testing.assert_allclose(ll["official"], ll["official_dropout"], rtol=1e-5)
    x = exp.sample(
        model,
        jax.random.key(4),
        batch["control"],
        temperature=0.5,
        seed_history=batch["pose"][:, :3],
    )
    assert x.shape == (4, 8, POSE_DIM) and np.all(np.isfinite(x))
    x0 = exp.sample(model, jax.random.key(4), batch["control"], temperature=0.0)
    x1 = exp.sample(model, jax.random.key(5), batch["control"], temperature=0.0)
    np.testing.assert_allclose(x0, x1, atol=1e-6)
    with pytest.raises(ValueError, match="control"):
        exp.sample(model, key, batch["control"][..., :2])
