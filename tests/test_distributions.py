"""Base densities and Transformed: exact log-densities, sampling, temperature, errors."""

from __future__ import annotations

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from motionflows import bijectors as bj
from motionflows.distributions import Normal, StudentT, Transformed
from motionflows.nets import coupling_mlp

pytestmark = pytest.mark.usefixtures("fast_compilation")

T, D = 3, 2


def close(a, b, tol=1e-5):
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=tol, atol=tol)


def _perturb(module, seed, scale=0.3):
    rng = np.random.default_rng(seed)
    state = nnx.state(module, nnx.Param)
    leaves, treedef = jax.tree.flatten(state)
    new = [jnp.asarray(np.asarray(x) + scale * rng.standard_normal(x.shape)) for x in leaves]
    nnx.update(module, jax.tree.unflatten(treedef, new))
    return module


def _flow(num_channels, *, context_features=0, seed=0):
    """A small non-trivial flow: data -> latent ActNorm, InvertibleLinear, AffineCoupling."""
    rngs = nnx.Rngs(seed)
    cond = coupling_mlp(num_channels, context_features=context_features, hidden=8, rngs=rngs)
    flow = bj.Chain.from_data_to_latent(
        [
            bj.ActNorm(num_channels),
            bj.InvertibleLinear(num_channels, rngs=rngs),
            bj.AffineCoupling(num_channels, cond),
        ]
    )
    return _perturb(flow, seed)


def test_normal_log_prob_standard_and_diagonal():
    x = jax.random.normal(jax.random.key(0), (4, T, D)) * 2.0
    ref = jnp.sum(jax.scipy.stats.norm.logpdf(x), axis=(-2, -1))
    lp = Normal((T, D)).log_prob(x)
    assert lp.shape == (4,)
    close(lp, ref)
    loc, scale = jnp.array([0.5, -1.0]), jnp.array([2.0, 0.3])
    ref = jnp.sum(jax.scipy.stats.norm.logpdf(x, loc, scale), axis=(-2, -1))
    close(Normal((T, D), loc=loc, scale=scale).log_prob(x), ref, 1e-4)
    # without event_shape: any (T, D) for the standard normal; loc/scale's shape otherwise
    close(Normal().log_prob(x), Normal((T, D)).log_prob(x))
    full_loc = jnp.broadcast_to(loc, (T, D))
    close(Normal(loc=full_loc, scale=scale).log_prob(x), ref, 1e-4)
    with pytest.raises(ValueError, match="df"):
        StudentT((T, D))


def test_student_t_log_prob():
    x = jax.random.normal(jax.random.key(1), (4, T, D)) * 3.0
    dist = StudentT((T, D), df=4.0, loc=0.5, scale=1.5)
    ref = jnp.sum(jax.scipy.stats.t.logpdf(x, 4.0, 0.5, 1.5), axis=(-2, -1))
    close(dist.log_prob(x), ref, 1e-4)
    close(StudentT((T, D), 3.0).log_prob(x[0]), jnp.sum(jax.scipy.stats.t.logpdf(x[0], 3.0)))
    with pytest.raises(ValueError, match="df"):
        StudentT((T, D), df=0.0)


@pytest.mark.parametrize("cls", ["normal", "student_t"])
def test_sampling_moments_and_temperature(cls):
    loc, scale = jnp.array([1.0, -2.0]), jnp.array([0.5, 2.0])
    if cls == "normal":
        dist, factor = Normal((T, D), loc=loc, scale=scale), 1.0
    else:
        dist, factor = StudentT((T, D), df=8.0, loc=loc, scale=scale), np.sqrt(8.0 / 6.0)
    key = jax.random.key(2)
    x = dist.sample(key, (4000,))
    assert x.shape == (4000, T, D) and x.dtype == jnp.float32
    flat = np.asarray(x).reshape(-1, D)
    np.testing.assert_allclose(flat.mean(0), loc, atol=0.05)
    np.testing.assert_allclose(flat.std(0), factor * np.asarray(scale), rtol=0.05)
    # temperature scales the standard noise: same key, half the spread around loc
    x_half = dist.sample(key, (4000,), temperature=0.5)
    close(x_half - loc, 0.5 * (x - loc), 1e-5)
    # temperature 0 is exactly the mode
    x0 = dist.sample(key, 3, temperature=0.0)
    assert x0.shape == (3, T, D)
    assert bool(jnp.all(x0 == jnp.broadcast_to(loc, (3, T, D))))


def test_batched_parameters_conditional_prior():
    loc = jax.random.normal(jax.random.key(3), (5, T, D))
    dist = Normal((T, D), loc=loc, scale=0.1)
    assert dist.batch_shape == (5,)
    x = dist.sample(jax.random.key(4), (2,))
    assert x.shape == (2, 5, T, D)
    lp = dist.log_prob(x)
    assert lp.shape == (2, 5)
    # each component scores its own samples above the neighbouring component's samples
    assert float(jnp.min(lp)) > float(jnp.max(dist.log_prob(jnp.roll(x, 1, axis=1))))


def test_shapes_checked_and_wildcard_time():
    with pytest.raises(ValueError, match=r"expects \(\.\.\., 3, 2\)"):
        Normal((T, D)).log_prob(jnp.zeros((4, T, D + 1)))
    with pytest.raises(ValueError, match="broadcast"):
        Normal((T, D), loc=jnp.zeros(D + 1))
    any_t = Normal((None, D))
    assert any_t.log_prob(jnp.zeros((7, D))).shape == ()
    assert any_t.log_prob(jnp.zeros((2, 11, D))).shape == (2,)
    with pytest.raises(ValueError, match="cannot be sampled"):
        any_t.sample(jax.random.key(0))


def test_transformed_log_prob_is_change_of_variables():
    flow = _flow(D, seed=1)
    dist = Transformed(Normal((T, D)), flow)
    x = jax.random.normal(jax.random.key(5), (T, D)) * 2.0 + 1.0
    z = flow.inverse(x)
    jac = jax.jacfwd(lambda v: flow.inverse(v.reshape(T, D)).reshape(-1))(x.reshape(-1))
    ref = Normal((T, D)).log_prob(z) + jnp.linalg.slogdet(jac)[1]
    close(dist.log_prob(x), ref, 1e-4)
    xb = jnp.stack([x, x + 1.0])
    assert dist.log_prob(xb).shape == (2,)
    close(jax.jit(lambda d, x: d.log_prob(x))(dist, xb), dist.log_prob(xb), 1e-4)


def test_transformed_density_integrates_to_one():
    """On a one-frame 2-D event the density of a non-trivial flow integrates to 1."""
    flow = _flow(2, seed=2)
    dist = Transformed(Normal((1, 2)), flow)
    g = jnp.linspace(-12.0, 12.0, 301)
    xx, yy = jnp.meshgrid(g, g, indexing="ij")
    pts = jnp.stack([xx, yy], -1).reshape(-1, 1, 2)
    p = jnp.exp(jax.jit(lambda d, x: d.log_prob(x))(dist, pts))
    mass = float(jnp.sum(p) * (g[1] - g[0]) ** 2)
    assert abs(mass - 1.0) < 1e-2, mass


def test_transformed_sampling_temperature_and_context():
    c_dim = 2
    flow = _flow(D, context_features=c_dim, seed=3)
    dist = Transformed(Normal((T, D)), flow)
    ctx = jax.random.normal(jax.random.key(6), (4, T, c_dim))
    key = jax.random.key(7)
    x = dist.sample(key, (4,), context=ctx)
    assert x.shape == (4, T, D)
    close(flow.inverse(x, context=ctx), Normal((T, D)).sample(key, (4,)), 1e-4)
    # temperature 0 is exact: the image of the base mode
    x0 = dist.sample(key, (4,), context=ctx, temperature=0.0)
    close(x0, flow.forward(jnp.zeros((4, T, D)), context=ctx), 0)
    # the context steers the samples
    other = dist.sample(key, (4,), context=ctx + 1.0)
    assert float(jnp.max(jnp.abs(other - x))) > 1e-3
    # sample_and_log_prob agrees with log_prob of the samples
    xs, lp = dist.sample_and_log_prob(key, (4,), context=ctx, temperature=0.7)
    close(lp, dist.log_prob(xs, context=ctx), 1e-4)
    with pytest.raises(ValueError, match="bijector"):
        Transformed(Normal((T, D)), object())


@pytest.mark.parametrize("cls", ["normal", "student_t"])
def test_log_scale_is_the_scale_in_log_space(cls):
    x = jax.random.normal(jax.random.key(8), (4, T, D)) * 2.0
    loc, log_scale = jnp.array([0.5, -1.0]), jnp.array([0.7, -1.2])
    make = Normal if cls == "normal" else (lambda *a, **k: StudentT(*a, df=4.0, **k))
    by_log = make((T, D), loc=loc, log_scale=log_scale)
    by_scale = make((T, D), loc=loc, scale=jnp.exp(log_scale))
    close(by_log.log_prob(x), by_scale.log_prob(x), 1e-4)
    key = jax.random.key(9)
    close(by_log.sample(key, (3,), temperature=0.5), by_scale.sample(key, (3,), temperature=0.5))
    with pytest.raises(ValueError, match="not both"):
        make((T, D), scale=1.0, log_scale=0.0)


def test_empty_event_shape_scores_each_element():
    x = jax.random.normal(jax.random.key(10), (4, T, D))
    loc, log_scale = jnp.array([0.5, -1.0]), jnp.array([0.7, -1.2])
    each = Normal((), loc=loc, log_scale=log_scale).log_prob(x)
    chex.assert_shape(each, (4, T, D))
    close(each, jax.scipy.stats.norm.logpdf(x, loc, jnp.exp(log_scale)))


def test_transformed_samples_a_model_with_only_the_log_det_pair():
    """A model (Glow) is a bijector through its two *_and_log_det methods alone."""

    class Doubling(nnx.Module):
        def forward_and_log_det(self, z, *, context=None):
            return 2.0 * z, jnp.full(z.shape[:-2], z.shape[-2] * z.shape[-1] * jnp.log(2.0))

        def inverse_and_log_det(self, x, *, context=None):
            return 0.5 * x, jnp.full(x.shape[:-2], -x.shape[-2] * x.shape[-1] * jnp.log(2.0))

    dist = Transformed(Normal((T, D)), Doubling())
    key = jax.random.key(11)
    x = dist.sample(key, (5,))
    chex.assert_shape(x, (5, T, D))
    close(x, 2.0 * Normal((T, D)).sample(key, (5,)), 0)
    close(dist.log_prob(x), jnp.sum(jax.scipy.stats.norm.logpdf(x, 0.0, 2.0), axis=(-2, -1)))


def test_this_module_runs_under_strict_dtype_promotion():
    """The suite's strict dtype promotion is in force: float32 + int32 raises, not widens."""
    with pytest.raises(jax.dtypes.TypePromotionError):
        jnp.ones(2, jnp.float32) + jnp.ones(2, jnp.int32)
