"""Fixed-length Glow: exact bijection, exact likelihood, conditioning, and a tiny training run."""

from __future__ import annotations

import dataclasses
import math

import chex
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from flax import nnx

import experiments.glow_fixed as glow_fixed
from motionflows.bijectors import initialize_from_data
from motionflows.data.names import CONTROL_DIM, JOINT_NAMES, POSE_DIM
from motionflows.distributions import Normal, Transformed
from motionflows.models.glow import Glow
from motionflows.nets.conv import ConvNet, TimeConv


def _perturb(model, key, scale=0.1):
    """Add noise to every trainable parameter (zero-init heads included): non-trivial maps.

    Matrices get noise of std scale / sqrt(fan-in) so that the perturbed triangular LU
    factors stay well conditioned.
    """
    graphdef, params, rest = nnx.split(model, nnx.Param, ...)
    leaves, treedef = jax.tree.flatten(params)
    keys = jax.random.split(key, len(leaves))
    leaves = [
        p + scale / math.sqrt(p.shape[-2] if p.ndim >= 2 else 1) * jax.random.normal(k, p.shape)
        for p, k in zip(leaves, keys, strict=True)
    ]
    return nnx.merge(graphdef, jax.tree.unflatten(treedef, leaves), rest)


def _tiny(
    key, *, pose_dim=POSE_DIM, control_dim=CONTROL_DIM, prior="standard", coupling="affine",
    residual=False, residual_decay=1.0,
):  # fmt: skip
    k1, k2 = jax.random.split(key)
    model = Glow(
        pose_dim, levels=2, K=2, hidden=8, control_dim=control_dim, prior=prior,
        coupling=coupling, residual=residual, residual_decay=residual_decay, rngs=nnx.Rngs(k1),
    )  # fmt: skip
    return _perturb(model, k2)


@jax.jit
def encode(model, x, c):
    return model.encode(x, c)


@jax.jit
def decode(model, z, c):
    return model.decode(z, c)


@jax.jit
def log_prob(model, x, c):
    return model.log_prob(x, c)


@pytest.fixture(scope="module")
def conditional():
    """Glow(63, L=2, K=2) with control and the learned prior, perturbed (non-trivial)."""
    return _tiny(jax.random.key(11), prior="learned")


@pytest.fixture(scope="module")
def unconditional():
    return _tiny(jax.random.key(12), control_dim=0)


@pytest.fixture(scope="module")
def additive():
    """Conditional, standard prior, additive couplings; perturbed."""
    return _tiny(jax.random.key(13), coupling="additive")


@pytest.fixture(scope="module")
def residual():
    """Conditional, learned prior, flowing the first frame and the changes; perturbed."""
    return _tiny(jax.random.key(14), prior="learned", residual=True)


@pytest.fixture(scope="module")
def leaky():
    """As ``residual``, with the leaky change u_t = x_t - 0.9 x_{t-1}."""
    return _tiny(jax.random.key(15), prior="learned", residual=True, residual_decay=0.9)


def test_round_trip_and_init(conditional, key):
    model = conditional
    kx, kc, kz = jax.random.split(key, 3)
    x = 1.5 + 2.0 * jax.random.normal(kx, (3, 8, POSE_DIM))
    c = jax.random.normal(kc, (3, 8, CONTROL_DIM))
    fresh = initialize_from_data(model, x, context=c)
    # the first ActNorm on the data -> latent path (last step of level 0) saw squeeze(x)
    first = fresh.flows[0].step(fresh.steps - 1)[2]
    squeezed = np.asarray(x).reshape(3, 4, 2 * POSE_DIM)
    np.testing.assert_allclose(first.bias[...], -squeezed.mean((0, 1)), atol=1e-4)
    assert not np.allclose(model.flows[0].step(fresh.steps - 1)[2].bias[...], first.bias[...])
    for m in (model, fresh):
        z = encode(m, x, c)
        assert z.shape == (3, 8 * POSE_DIM)
        np.testing.assert_allclose(decode(m, z, c), x, atol=2e-4, rtol=1e-4)
        # the other direction, from random latents
        z2 = jax.random.normal(kz, z.shape)
        np.testing.assert_allclose(encode(m, decode(m, z2, c), c), z2, atol=1e-3, rtol=1e-3)
    # the parts cover the latent exactly and have the documented shapes
    parts = model.latent_parts(z)
    assert [p.shape[1:] for p in parts] == [(4, 63), (2, 126)]
    np.testing.assert_array_equal(parts[0][:, :, 0], z[:, 0 : 4 * 63 : 63])


@pytest.mark.parametrize("which", ["conditional", "unconditional", "additive", "residual", "leaky"])
def test_log_prob_matches_jacobian(which, request, key):
    """log p(x) = log N(f^-1(x)) + log|det J| with J from jax.jacfwd over the flat window.

    The fixtures (learned prior with control; standard prior without; additive couplings
    with control and the standard prior; the learned prior over the plain and the leaky
    changes) have perturbed, non-trivial parameters. D = 63 is odd: the coupling halves of
    the squeezed 126 channels are 63 / 63 and so are the split's kept / factored parts.
    """
    model = request.getfixturevalue(which)
    t, d = 4, POSE_DIM
    kx, kc = jax.random.split(key)
    x = jax.random.normal(kx, (t, d))
    c = jax.random.normal(kc, (t, CONTROL_DIM)) if model.conditional else None

    @jax.jit
    def check(model, x, c):
        def flat_encode(v):
            return model.encode(v.reshape(t, d), c)

        jac = jax.jacfwd(flat_encode)(x.reshape(-1))
        _, logabs = jnp.linalg.slogdet(jac)
        z, log_det = model.inverse_and_log_det(x, context=c)
        x_back, fwd_log_det = model.forward_and_log_det(z, context=c)
        base = -0.5 * jnp.sum(z**2) - 0.5 * t * d * math.log(2 * math.pi)
        return jac, logabs, base, log_det, fwd_log_det, model.log_prob(x, c), x_back

    jac, logabs, base, log_det, fwd_log_det, got, x_back = check(model, x, c)
    assert jac.shape == (t * d, t * d)
    np.testing.assert_allclose(x_back, x, atol=2e-4, rtol=1e-4)  # round trip
    assert abs(float(logabs)) > 1.0  # non-trivial parameters
    np.testing.assert_allclose(got, base + logabs, rtol=1e-4, atol=5e-3)
    np.testing.assert_allclose(log_det, logabs, rtol=1e-4, atol=5e-3)
    np.testing.assert_allclose(fwd_log_det, -log_det, rtol=1e-4, atol=5e-3)


def test_residual_flows_the_first_frame_and_the_changes(residual, key):
    """``residual=True`` is the plain multi-scale flow applied to [a(x_0), b(x_t - x_{t-1})]
    (a, b: its two ActNorms); the log-density gains exactly their log-dets, and decoding
    sums the changes back up."""
    model = residual
    kx, kc, kz = jax.random.split(key, 3)
    x = 1.5 + 2.0 * jax.random.normal(kx, (3, 8, POSE_DIM))
    c = jax.random.normal(kc, (3, 8, CONTROL_DIM))
    a_bias, a_logs = (np.asarray(v[...]) for v in (model.first_norm.bias, model.first_norm.logs))
    b_bias, b_logs = (np.asarray(v[...]) for v in (model.change_norm.bias, model.change_norm.logs))
    assert np.ptp(a_logs) > 0 and np.ptp(b_logs) > 0  # non-trivial

    def normalised(x):
        x = np.asarray(x)
        first = (x[:, :1] + a_bias) * np.exp(a_logs)
        return np.concatenate([first, (np.diff(x, axis=-2) + b_bias) * np.exp(b_logs)], axis=-2)

    plain = nnx.clone(model)
    plain.residual = False  # the same flows, without the change of variables in front
    y = normalised(x)
    np.testing.assert_allclose(encode(model, x, c), encode(plain, y, c), atol=1e-4, rtol=1e-4)
    log_det = np.sum(a_logs) + 7 * np.sum(b_logs)
    np.testing.assert_allclose(
        log_prob(model, x, c), log_prob(plain, y, c) + log_det, rtol=1e-5, atol=1e-3
    )
    z = jax.random.normal(kz, (3, 8 * POSE_DIM))
    np.testing.assert_allclose(
        normalised(decode(model, z, c)), decode(plain, z, c), atol=1e-4, rtol=1e-4
    )


def test_residual_init_normalises_the_first_frames_and_the_changes(residual, key):
    """Data-dependent init sets each ActNorm from its own part: the first frames and the
    changes both leave it zero-mean and unit-std per channel, though a change is far
    smaller than a pose."""
    kx, kc = jax.random.split(key)
    steps = jnp.cumsum(0.05 * jax.random.normal(kx, (16, 8, POSE_DIM)), axis=-2)
    x = 3.0 + steps + jnp.linspace(0.0, 2.0, POSE_DIM)
    c = jax.random.normal(kc, (16, 8, CONTROL_DIM))
    fresh = initialize_from_data(residual, x, context=c)
    y, _ = fresh._changes_from_poses(x)
    y = np.asarray(y)
    for part in (y[:, :1], y[:, 1:]):
        flat = part.reshape(-1, POSE_DIM)
        np.testing.assert_allclose(flat.mean(0), 0.0, atol=1e-4)
        np.testing.assert_allclose(flat.std(0), 1.0, atol=1e-3)
    np.testing.assert_allclose(decode(fresh, encode(fresh, x, c), c), x, atol=2e-4, rtol=1e-4)
    # one window gives the first-frame ActNorm one value per channel: every channel looked
    # constant and got a scale of 1e6 (log-likelihoods of -3e13 afterwards), silently
    with pytest.raises(ValueError, match="at least 2 windows"):
        initialize_from_data(residual, x[:1], context=c[:1])


def test_additive_couplings_preserve_volume(additive, key):
    """With additive couplings only ActNorm and the 1x1 maps scale: the flow's log-det is
    the same for every window and control (the affine Glow's is not), and a latent -> data
    pass cannot amplify a latent through a small coupling scale."""
    kx, kc = jax.random.split(key)
    x = jax.random.normal(kx, (4, 8, POSE_DIM)) * jnp.array([0.5, 1.0, 2.0, 4.0])[:, None, None]
    c = jax.random.normal(kc, (4, 8, CONTROL_DIM))

    @jax.jit
    def log_dets(model, x, c):
        return model.inverse_and_log_det(x, context=c)[1]

    ld = np.asarray(log_dets(additive, x, c))
    np.testing.assert_allclose(ld, ld[0], rtol=1e-6, atol=1e-4)
    assert abs(float(ld[0])) > 1.0  # ActNorm / 1x1 are non-trivial
    affine = _tiny(jax.random.key(13), coupling="affine")  # same prior, same draws
    assert np.ptp(np.asarray(log_dets(affine, x, c))) > 1e-2
    couplings = [type(b).__name__ for b in additive.flows[0].step(0).bijectors]
    assert "AdditiveCoupling" in couplings, couplings


def test_glow_is_a_transformed_standard_normal(conditional, key):
    """The model is Transformed(Normal((T * D,)), glow): same log_prob, same samples."""
    kx, kc, ks = jax.random.split(key, 3)
    x = jax.random.normal(kx, (2, 8, POSE_DIM))
    c = jax.random.normal(kc, (2, 8, CONTROL_DIM))
    dist = conditional.distribution(8)
    assert isinstance(dist, Transformed) and isinstance(dist.base, Normal)
    assert dist.event_shape == (8 * POSE_DIM,)
    np.testing.assert_allclose(dist.log_prob(x, context=c), log_prob(conditional, x, c), rtol=1e-6)
    s = dist.sample(ks, (2,), context=c, temperature=0.5)
    chex.assert_shape(s, (2, 8, POSE_DIM))
    chex.assert_trees_all_close(s, conditional.sample(ks, c, temperature=0.5), atol=1e-6)


def test_log_prob_batch_shapes_agree(conditional, key):
    x = jax.random.normal(jax.random.fold_in(key, 1), (2, 3, 8, POSE_DIM))
    c = jax.random.normal(jax.random.fold_in(key, 2), (2, 3, 8, CONTROL_DIM))
    lp = log_prob(conditional, x, c)
    assert lp.shape == (2, 3)
    single = log_prob(conditional, x[1, 2], c[1, 2])
    assert single.shape == ()
    np.testing.assert_allclose(single, lp[1, 2], rtol=1e-5, atol=1e-3)


def test_conv_net_is_a_time_convolution(key):
    conv = TimeConv(4, 5, 3, rngs=nnx.Rngs(key))
    x = jax.random.normal(jax.random.fold_in(key, 1), (2, 7, 4))
    w = np.asarray(conv.kernel[...])
    xp = np.pad(np.asarray(x), ((0, 0), (1, 1), (0, 0)))  # SAME = one zero frame each side
    ref = sum(np.einsum("btc,co->bto", xp[:, k : k + 7], w[k]) for k in range(3))
    np.testing.assert_allclose(conv(x), ref, atol=1e-5)
    net = ConvNet(4, 6, 16, context_features=3, rngs=nnx.Rngs(key))
    c = jnp.ones((2, 7, 3))
    assert np.all(np.asarray(net(x, c)) == 0.0)  # zero-initialised head
    net = _perturb(net, key)
    out32 = net(x, c)
    bf = ConvNet(4, 6, 16, context_features=3, compute_dtype=jnp.bfloat16, rngs=nnx.Rngs(key))
    nnx.update(bf, nnx.state(net))
    out16 = bf(x, c)
    assert out16.dtype == jnp.float32 and out16.shape == (2, 7, 6)
    np.testing.assert_allclose(out16, out32, atol=0.1, rtol=0.05)
    assert not np.allclose(out16, out32, atol=1e-7)  # bfloat16 really was used
    with pytest.raises(ValueError, match="context"):
        net(x)


def test_clear_errors(conditional, unconditional, key):
    x = jnp.zeros((2, 8, POSE_DIM))
    c = jnp.zeros((2, 8, CONTROL_DIM))
    with pytest.raises(ValueError, match="multiple of 2\\*\\*2"):
        conditional.log_prob(jnp.zeros((2, 6, POSE_DIM)), jnp.zeros((2, 6, CONTROL_DIM)))
    with pytest.raises(ValueError, match=r"\(\.\.\., T, 63\)"):
        conditional.log_prob(jnp.zeros((2, 8, 60)), c)
    with pytest.raises(ValueError, match="conditional"):
        conditional.log_prob(x)
    with pytest.raises(ValueError, match="control"):
        conditional.log_prob(x, jnp.zeros((2, 4, CONTROL_DIM)))
    with pytest.raises(ValueError, match="non-finite"):
        conditional.log_prob(x.at[0, 0, 0].set(jnp.nan), c)
    with pytest.raises(ValueError, match="flat"):
        conditional.decode(jnp.zeros((2, 8, 62)), c)
    with pytest.raises(ValueError, match="unconditional"):
        unconditional.log_prob(x, c)
    with pytest.raises(ValueError, match="num"):
        unconditional.sample(key)
    with pytest.raises(ValueError, match="window"):
        dataclasses.replace(glow_fixed.PRESETS["quick"], levels=6)
    with pytest.raises(ValueError, match="prior"):
        Glow(levels=1, K=1, hidden=4, prior="laplace", rngs=nnx.Rngs(0))
    with pytest.raises(ValueError, match="coupling must be one of"):
        Glow(levels=1, K=1, hidden=4, coupling="spline", rngs=nnx.Rngs(0))
    with pytest.raises(ValueError, match="coupling must be one of"):
        dataclasses.replace(glow_fixed.PRESETS["quick"], coupling="spline")


def test_unconditional_sampling(unconditional, key):
    sample = jax.jit(lambda m, k: m.sample(k, num=2, length=8, temperature=0.5))
    s = sample(unconditional, key)
    assert s.shape == (2, 8, POSE_DIM) and np.isfinite(np.asarray(s)).all()
    # sampling = decoding temperature * eps with the same key
    eps = 0.5 * jax.random.normal(key, (2, 8 * POSE_DIM))
    np.testing.assert_allclose(s, decode(unconditional, eps, None), atol=1e-5)
    # without length: the model's default window (80 frames = 4 s at 20 fps)
    assert unconditional.sample(key, num=3, temperature=0.0).shape == (3, 80, POSE_DIM)


def test_same_latent_different_controls_give_different_samples(conditional, key):
    c1 = jax.random.normal(jax.random.fold_in(key, 1), (3, 8, CONTROL_DIM))
    c2 = c1.at[:, :, 0].add(1.0)
    z = jax.random.normal(jax.random.fold_in(key, 2), (3, 8 * POSE_DIM))
    s1, s2 = decode(conditional, z, c1), decode(conditional, z, c2)
    assert s1.shape == (3, 8, POSE_DIM)
    assert float(jnp.min(jnp.max(jnp.abs(s1 - s2), axis=(1, 2)))) > 1e-2
    np.testing.assert_allclose(encode(conditional, s2, c2), z, atol=1e-3, rtol=1e-3)


# ------------------------------------------------------------------------ tiny training run

WINDOW = 16


@pytest.fixture(scope="module")
def trained():
    """A tiny conditional Glow trained for 250 steps on the synthetic default."""
    from motionflows.data import load_dataset

    ds = load_dataset("synthetic", n_clips=24, seconds=12.0, window=WINDOW, hop=4, cache=False)
    quick = glow_fixed.PRESETS["quick"]
    config = dataclasses.replace(
        quick,
        data=dataclasses.replace(quick.data, window=WINDOW),
        levels=2,
        K=2,
        hidden=32,
    )
    key = jax.random.key(0)
    model = glow_fixed.build(config, key=key)
    model = glow_fixed.initialize(model, ds.batch("train", 32, seed=0, index=0), key=key)
    graphdef, params, rest = nnx.split(model, nnx.Param, ...)
    tx = optax.chain(
        optax.clip_by_global_norm(100.0), optax.adam(optax.linear_schedule(1e-4, 2e-3, 30))
    )
    opt = tx.init(params)

    @jax.jit
    def step(params, opt, batch, key):
        def objective(p):
            return glow_fixed.loss(nnx.merge(graphdef, p, rest), batch, key)[0]

        value, grads = jax.value_and_grad(objective)(params)
        updates, opt = tx.update(grads, opt, params)
        return optax.apply_updates(params, updates), opt, value

    losses = []
    # optax's Adam computes float ** int32 (the standard_dtypes marker's reason); a module
    # fixture runs before the per-test promotion context, under the process default, which
    # is strict in pytest-xdist's workers (they inherit JAX_NUMPY_DTYPE_PROMOTION=strict)
    with jax.numpy_dtype_promotion("standard"):
        for i in range(250):
            batch = ds.batch("train", 32, seed=0, index=i)
            params, opt, value = step(params, opt, batch, jax.random.fold_in(key, i))
            losses.append(float(value))
    return nnx.merge(graphdef, params, rest), ds, losses


def test_training_beats_diagonal_gaussian(trained):
    model, ds, losses = trained
    assert np.isfinite(losses).all()
    assert np.mean(losses[-20:]) < np.mean(losses[:5]) - 30.0
    val = ds.arrays("val")
    ll = jax.jit(glow_fixed.evaluate)(model, val, None)["window"]
    assert ll.shape == (len(val["pose"]),)
    glow_nll = -float(jnp.mean(ll)) / WINDOW
    # per-frame diagonal Gaussian fitted on the (standardised) training frames
    train = ds.arrays("train")["pose"].reshape(-1, POSE_DIM).astype(np.float64)
    mu, sd = train.mean(0), train.std(0)
    z = (np.asarray(val["pose"], np.float64) - mu) / sd
    diag = np.sum(0.5 * z**2 + np.log(sd) + 0.5 * math.log(2 * math.pi), -1)
    diag_nll = float(diag.mean())
    assert glow_nll < diag_nll - 40.0, (glow_nll, diag_nll)


def test_trained_samples_follow_the_control(trained):
    """Faster forward control -> more foot travel (root-frame feet, metres) in samples."""
    model, ds, _ = trained
    std = ds.standardizer
    speeds = ds.arrays("train", standardized=False)["control"][..., 0]
    slow, fast = np.percentile(speeds, [10, 90])
    feet = [3 * JOINT_NAMES.index(j) + 2 for j in ("LeftFoot", "RightFoot")]  # z = forward

    sample = jax.jit(lambda m, k, c: glow_fixed.sample(m, k, c, temperature=0.8))

    def foot_travel(speed):
        c = np.tile(np.array([speed, 0.0, 0.0], np.float32), (96, WINDOW, 1))
        c = jnp.asarray(std.normalize_control(c), jnp.float32)
        x = sample(model, jax.random.key(7), c)
        x = std.denormalize_pose(np.asarray(x))
        return float(np.abs(np.diff(x[:, :, feet], axis=1)).sum(1).mean())

    assert foot_travel(fast) > 1.1 * foot_travel(slow)
