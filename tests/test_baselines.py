"""Baselines: exact log-likelihoods, closed-form fits, sampling, experiment protocol."""

import math

import chex
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from flax import nnx

from motionflows.distributions import Normal
from motionflows.models.baselines import (
    DiagonalGaussian,
    LinearGaussianAR,
    fit_gaussian,
    fit_linear_ar,
)

D, C, TAU = 3, 2, 2


def _np_mvn_logpdf(x, mean, cov):
    d = x.shape[-1]
    sign, logdet = np.linalg.slogdet(cov)
    r = x - mean
    return -0.5 * (r @ np.linalg.solve(cov, r) + logdet + d * math.log(2 * math.pi))


def _random_ar(key, covariance="full"):
    m = LinearGaussianAR(TAU, pose_dim=D, control_dim=C, covariance=covariance)
    k1, k2, k3 = jax.random.split(key, 3)
    m.weight[...] = 0.3 * jax.random.normal(k1, m.weight[...].shape)
    m.log_diag[...] = 0.3 * jax.random.normal(k2, (D,)) - 0.5
    if covariance == "full":
        m.lower[...] = 0.5 * jax.random.normal(k3, (D, D))
    return m


def test_gaussian_log_prob_matches_numpy():
    m = DiagonalGaussian(pose_dim=D)
    m.mean[...] = jnp.array([0.5, -1.0, 2.0])
    m.log_std[...] = jnp.array([0.1, -0.3, 0.7])
    x = np.random.default_rng(0).normal(size=(4, 5, D)).astype(np.float32)
    got = np.asarray(m.log_prob(jnp.asarray(x)))
    cov = np.diag(np.exp(2 * np.array([0.1, -0.3, 0.7])))
    want = [
        sum(_np_mvn_logpdf(x[b, t], np.array([0.5, -1.0, 2.0]), cov) for t in range(5))
        for b in range(4)
    ]
    np.testing.assert_allclose(got, want, rtol=1e-5)


def test_gaussian_frames_are_a_normal_distribution():
    m = DiagonalGaussian(pose_dim=D)
    m.mean[...] = jnp.array([0.5, -1.0, 2.0])
    m.log_std[...] = jnp.array([0.1, -0.3, 0.7])
    dist = m.distribution()
    assert isinstance(dist, Normal) and dist.event_shape == (D,)
    x = m.sample(jax.random.key(3), (4, 5))
    chex.assert_shape(x, (4, 5, D))
    chex.assert_trees_all_close(m.frame_log_prob(x), dist.log_prob(x))
    # temperature 0 is the mean, exactly
    chex.assert_trees_all_equal(
        m.sample(jax.random.key(3), (2, 3), temperature=0.0),
        jnp.broadcast_to(m.mean[...], (2, 3, D)),
    )


def test_ar_log_prob_matches_direct_computation():
    m = _random_ar(jax.random.key(1))
    rng = np.random.default_rng(1)
    x = rng.normal(size=(2, 6, D)).astype(np.float32)
    c = rng.normal(size=(2, 6, C)).astype(np.float32)
    w = np.asarray(m.weight[...], np.float64)
    chol = np.asarray(m.cholesky(), np.float64)
    assert np.allclose(chol, np.tril(chol))
    cov = chol @ chol.T
    want_window, want_official = np.zeros(2), np.zeros(2)
    for b in range(2):
        for t in range(6):
            hist = [x[b, t - TAU + k] if t - TAU + k >= 0 else np.zeros(D) for k in range(TAU)]
            ctrl = [c[b, t - TAU + k] if t - TAU + k >= 0 else np.zeros(C) for k in range(TAU + 1)]
            h = np.concatenate(hist + ctrl + [np.ones(1)])
            lp = _np_mvn_logpdf(x[b, t].astype(np.float64), h @ w, cov)
            want_window[b] += lp
            if t >= TAU:
                want_official[b] += lp
    np.testing.assert_allclose(np.asarray(m.log_prob(x, c)), want_window, rtol=1e-4)
    np.testing.assert_allclose(np.asarray(m.log_prob(x, c, skip=TAU)), want_official, rtol=1e-4)


def _ar_data(true, n=64, t=20, seed=0):
    key = jax.random.key(seed)
    control = jax.random.normal(key, (n, t, C))
    pose = true.sample(jax.random.fold_in(key, 1), control)
    return {"pose": pose, "control": control}


def test_ar_temperature_zero_is_the_mean_recursion():
    m = _random_ar(jax.random.key(2))
    control = jax.random.normal(jax.random.key(3), (2, 5, C))
    x = np.asarray(m.sample(jax.random.key(4), control, temperature=0.0))
    # each frame equals W^T h_t computed from the generated history
    h = np.asarray(m.features(jnp.asarray(x), control))
    np.testing.assert_allclose(x, h @ np.asarray(m.weight[...]), atol=1e-5)


def test_ar_closed_form_recovers_the_sampling_model():
    true = _random_ar(jax.random.key(5))
    data = _ar_data(true, n=256, t=30)
    fitted = fit_linear_ar(LinearGaussianAR(TAU, pose_dim=D, control_dim=C, ridge=0.0), [data])
    np.testing.assert_allclose(fitted.weight[...], true.weight[...], atol=0.08)
    np.testing.assert_allclose(fitted.cholesky(), true.cholesky(), atol=0.05)


def _gradient_fit(init, data, steps=700):
    """Adam on the mean negative log-likelihood, all steps in one jitted fori_loop."""
    graph, params, rest = nnx.split(init, nnx.Param, ...)
    opt = optax.adam(0.05)

    def nll(p):
        return -jnp.mean(nnx.merge(graph, p, rest).log_prob(data["pose"], data["control"]))

    def step(_, carry):
        params, state = carry
        updates, state = opt.update(jax.grad(nll)(params), state, params)
        return optax.apply_updates(params, updates), state

    params, _ = jax.jit(lambda p: jax.lax.fori_loop(0, steps, step, (p, opt.init(p))))(params)
    return nnx.merge(graph, params, rest)


@pytest.mark.standard_dtypes  # optax.adam
def test_closed_form_matches_gradient_fit():
    true = _random_ar(jax.random.key(6))
    data = _ar_data(true, n=32, t=16, seed=1)
    for covariance in ("full", "diag"):
        init = LinearGaussianAR(TAU, pose_dim=D, control_dim=C, covariance=covariance, ridge=0.0)
        closed = fit_linear_ar(init, [data])
        grad_model = _gradient_fit(init, data)
        ll_closed = float(jnp.mean(closed.log_prob(data["pose"], data["control"])))
        ll_grad = float(jnp.mean(grad_model.log_prob(data["pose"], data["control"])))
        # the closed form is the maximum: gradient descent gets close but not above it
        assert ll_grad <= ll_closed + 1e-2
        assert abs(ll_grad - ll_closed) < 0.01, (ll_grad, ll_closed)
        np.testing.assert_allclose(grad_model.weight[...], closed.weight[...], atol=0.01)
        np.testing.assert_allclose(grad_model.cholesky(), closed.cholesky(), atol=0.01)


def test_gaussian_closed_form_is_the_sample_moments_and_beats_perturbations():
    x = np.random.default_rng(3).normal(2.0, 3.0, size=(8, 10, D)).astype(np.float32)
    m = fit_gaussian(DiagonalGaussian(pose_dim=D), [{"pose": x[:4]}, {"pose": x[4:]}])
    flat = x.reshape(-1, D)
    np.testing.assert_allclose(m.mean[...], flat.mean(0), rtol=1e-5)
    np.testing.assert_allclose(np.exp(m.log_std[...]), flat.std(0), rtol=1e-4)
    best = float(jnp.sum(m.log_prob(x)))
    m2 = nnx.clone(m)
    m2.log_std[...] = m.log_std[...] + 0.05
    assert float(jnp.sum(m2.log_prob(x))) < best


def test_bad_shapes_raise_clear_errors():
    m = LinearGaussianAR(TAU, pose_dim=D, control_dim=C)
    try:
        m.log_prob(jnp.zeros((1, 4, D + 1)), jnp.zeros((1, 4, C)))
    except ValueError as err:
        assert "pose must have shape" in str(err)
    else:
        raise AssertionError("no error")
    try:
        LinearGaussianAR(TAU, covariance="banded")
    except ValueError as err:
        assert "covariance" in str(err)
    else:
        raise AssertionError("no error")


def test_ar_refuses_a_control_of_another_length_and_a_skip_that_scores_nothing():
    """A control one frame longer was silently cut to the pose's length, a shorter one or
    another batch gave a raw concatenate error, and skip >= T returned 0 as a likelihood."""
    import pytest

    m = LinearGaussianAR(TAU, pose_dim=D, control_dim=C)
    for control in (jnp.zeros((1, 6, C)), jnp.zeros((1, 4, C)), jnp.zeros((2, 5, C))):
        with pytest.raises(ValueError, match="must share"):
            m.log_prob(jnp.zeros((1, 5, D)), control)
    with pytest.raises(ValueError, match="skip must be in"):
        m.log_prob(jnp.zeros((1, 5, D)), jnp.zeros((1, 5, C)), skip=5)
