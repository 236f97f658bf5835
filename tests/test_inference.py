"""``inference_copy``: separate step weights for sampling, the same poses bit for bit."""

from __future__ import annotations

import dataclasses
import functools
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from motionflows.bijectors import Chain, Scan
from motionflows.data.names import CONTROL_DIM, POSE_DIM
from motionflows.inference import inference_copy, streaming_model
from motionflows.models.moglow import MoGlow
from tests.params import perturbed

D, C, TAU, K, H = 6, 2, 3, 3, 8


def _model(conditioner="lstm", residual=False, seed=0, dims=(D, C)) -> MoGlow:
    """A MoGlow with every parameter moved off its initial value (non-zero coupling heads,
    so the conditioners' weights decide the samples)."""
    m = MoGlow(*dims, tau=TAU, K=K, hidden=H, num_layers=2, conditioner=conditioner,
               residual=residual, rngs=jax.random.key(seed))  # fmt: skip
    return perturbed(m, jax.random.key(seed + 1))


def _weights(module) -> dict[str, jax.Array]:
    state = nnx.state(module, nnx.Param)
    return {jax.tree_util.keystr(p): leaf for p, leaf in jax.tree_util.tree_leaves_with_path(state)}


@pytest.mark.parametrize(
    ("conditioner", "residual"), [("lstm", False), ("ff", False), ("lstm", True)]
)
def test_copy_holds_each_steps_weights_apart_and_samples_the_same_poses(conditioner, residual):
    model = _model(conditioner, residual)
    copy = inference_copy(model)
    # the K steps are a chain of separate modules: no weight keeps the stacked K axis
    assert isinstance(model.flow, Scan) and isinstance(copy.flow, Chain)
    assert len(copy.flow) == K
    stacked = {p: w.shape for p, w in _weights(model).items() if "conditioner" in p}
    apart = {p: w.shape for p, w in _weights(copy).items() if "conditioner" in p}
    assert len(apart) == K * len(stacked)
    assert sorted({s[1:] for s in stacked.values()}) == sorted(set(apart.values()))
    # ... with step k's values, and the original untouched
    for k in range(K):
        step = _weights(model.flow.step(k))
        mine = _weights(copy.flow[k])
        assert len(step) == len(mine)
        for (p, a), b in zip(sorted(step.items()), [mine[q] for q in sorted(mine)], strict=True):
            np.testing.assert_array_equal(a, b, err_msg=p)
    control = jax.random.normal(jax.random.key(5), (2, 7, C))
    sample = jax.jit(lambda m, key, c: m.sample(key, c, temperature=0.8))
    exact = sample(model, jax.random.key(6), control)
    # the same products: equal up to float32 rounding (bit for bit for the LSTM MoGlows
    # here and the shipped model; XLA may fuse a feed-forward step's ops differently)
    np.testing.assert_allclose(sample(copy, jax.random.key(6), control), exact, atol=1e-5)
    # streaming from the copy's own state, and scoring, are the same maps too (one frame
    # alone: XLA may fuse it differently from inside the scan, so equal to float32 rounding)
    step = jax.jit(lambda m, s, c, key: m.stream_step(s, c, key, temperature=0.8))
    x0, _ = step(copy, copy.init_stream(2), control[:, 0], jax.random.key(6))
    np.testing.assert_allclose(x0, exact[:, 0], atol=1e-6)
    pose = jax.random.normal(jax.random.key(7), (2, 7, D))
    np.testing.assert_allclose(copy.log_prob(pose, control), model.log_prob(pose, control),
                               rtol=1e-6)  # fmt: skip
    np.testing.assert_allclose(copy.inverse_weights(), model.inverse_weights(), atol=1e-6)


def test_experiment_sampler_uses_the_copy_and_returns_the_models_poses(monkeypatch):
    from experiments import moglow as exp

    copies = []
    monkeypatch.setattr(exp, "inference_copy", lambda m: copies.append(m) or inference_copy(m))
    model = _model(dims=(POSE_DIM, CONTROL_DIM))
    control = jax.random.normal(jax.random.key(8), (3, 6, CONTROL_DIM))
    want = model.sample(jax.random.key(9), control, temperature=0.7)
    got = exp.sample(model, jax.random.key(9), control, temperature=0.7)
    np.testing.assert_allclose(got, want, atol=1e-6)
    assert copies == [model]
    # also when the caller jits around it (the bench, pretrained models, run.sample_run)
    jitted = jax.jit(lambda m, key, c: exp.sample(m, key, c, temperature=0.7))
    np.testing.assert_allclose(jitted(model, jax.random.key(9), control), want, atol=1e-6)
    assert isinstance(model.flow, Scan)  # the caller's model is not changed


def test_copy_in_bfloat16_stores_the_weights_and_the_old_entry_warns():
    model = _model()
    low = inference_copy(model, "bfloat16")
    dtypes = {p: w.dtype for p, w in _weights(low).items()}
    assert {p for p, dt in dtypes.items() if dt == jnp.bfloat16}
    assert all(w.dtype == jnp.float32 for w in _weights(model).values())
    from motionflows.nets import precision

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        old = precision.inference_copy(model)  # the old default: bfloat16 weights
    assert any(issubclass(w.category, DeprecationWarning) for w in caught)
    assert {p for p, w in _weights(old).items() if w.dtype == jnp.bfloat16} == {
        p for p, dt in dtypes.items() if dt == jnp.bfloat16
    }


def test_play_character_streams_from_the_copy():
    from motionflows.play.character import Character

    class Units:
        def normalize_control(self, c):
            return np.asarray(c, np.float32)

        def denormalize_pose(self, x):
            return np.asarray(x, np.float32)

    model = _model()
    character = Character(model, Units(), fps=20.0)
    assert isinstance(character.model.flow, Chain) and isinstance(model.flow, Scan)
    # bfloat16 matmuls: a lone frame's batch-1 bfloat16 products are slow on XLA:CPU, so
    # the stacked model itself streams (streaming_model)
    low = MoGlow(D, C, tau=TAU, K=K, hidden=H, compute_dtype="bfloat16", rngs=jax.random.key(1))
    assert streaming_model(low) is low
    assert Character(low, Units(), fps=20.0).model is low


def test_copy_of_a_bfloat16_model_stores_its_weights_in_bfloat16_with_the_same_numbers():
    """A model trained with bfloat16 matmuls casts its weights every product; its copy holds
    them cast once (no per-frame conversions) and samples the same poses."""
    model = MoGlow(D, C, tau=TAU, K=K, hidden=H, num_layers=2, compute_dtype="bfloat16",
                   rngs=jax.random.key(3))  # fmt: skip
    graph, params, rest = nnx.split(model, nnx.Param, ...)
    params = jax.tree.map(lambda p: p + 0.1 * jnp.cos(jnp.arange(p.size).reshape(p.shape)), params)
    model = nnx.merge(graph, params, rest)
    copy = inference_copy(model)
    low = {p for p, w in _weights(copy).items() if w.dtype == jnp.bfloat16}
    assert low and all("conditioner" in p for p in low)
    control = jax.random.normal(jax.random.key(4), (2, 6, C))
    sample = jax.jit(lambda m, key, c: m.sample(key, c))
    np.testing.assert_allclose(
        sample(copy, jax.random.key(5), control), sample(model, jax.random.key(5), control),
        atol=1e-5,
    )  # fmt: skip


@pytest.mark.parametrize("dtype", [None, "bfloat16"])
def test_stream_stepper_draws_samples_frames_from_the_module_split_once(dtype):
    """``stream_stepper`` (weights as one flat list of arrays, the module rebuilt only while
    tracing) draws ``sample``'s frames, follows a traced temperature, and a non-Flax model
    streams through it too."""
    from motionflows.inference import stream_stepper

    model = MoGlow(D, C, tau=TAU, K=K, hidden=H, num_layers=2, compute_dtype=dtype,
                   rngs=jax.random.key(6))  # fmt: skip
    model = streaming_model(perturbed(model, jax.random.key(7)))
    control = jax.random.normal(jax.random.key(8), (2, 5, C))
    key = jax.random.key(9)
    step = stream_stepper(model)
    state, frames = model.init_stream(2), []
    for t in range(control.shape[1]):
        pose, state = step(state, control[:, t], key, 0.7)
        frames.append(pose)
    want = model.sample(key, control, temperature=0.7)
    np.testing.assert_allclose(jnp.stack(frames, 1), want, rtol=1e-5, atol=1e-5)
    mode, _ = step(model.init_stream(2), control[:, 0], key, 0.0)
    np.testing.assert_allclose(mode, model.sample(key, control[:, :1], temperature=0.0)[:, 0],
                               rtol=1e-5, atol=1e-5)  # fmt: skip
    assert not np.allclose(mode, frames[0])

    @functools.partial(jax.tree_util.register_dataclass, data_fields=["scale"], meta_fields=[])
    @dataclasses.dataclass
    class Plain:  # a pytree model with the streaming API, not a Flax module
        scale: jax.Array

        def stream_step(self, state, control_t, key, temperature=1.0):
            return self.scale * temperature * control_t, state + 1

    pose, count = stream_stepper(Plain(jnp.float32(3.0)))(jnp.int32(0), control[:, 0], key, 2.0)
    np.testing.assert_allclose(pose, 6.0 * control[:, 0], rtol=1e-6)
    assert int(count) == 1
