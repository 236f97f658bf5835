"""MoGlow: sequence pass vs frame stepping, round trips, exact log-dets, dropout, streaming."""

from __future__ import annotations

import dataclasses
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from motionflows.bijectors import coupling_sizes, initialize_from_data
from motionflows.models.moglow import MoGlow, build_conditions
from tests.params import perturbed

D, C, TAU, K, H = 6, 2, 3, 2, 8


def _model(conditioner="lstm", seed=0, layers=1, **kw) -> MoGlow:
    m = MoGlow(
        D,
        C,
        tau=TAU,
        K=K,
        hidden=H,
        num_layers=layers,
        conditioner=conditioner,
        rngs=jax.random.key(seed),
        **kw,
    )
    return perturbed(m, jax.random.key(seed + 100))


def _data(b=3, t=9, seed=1):
    k1, k2 = jax.random.split(jax.random.key(seed))
    return jax.random.normal(k1, (b, t, D)), jax.random.normal(k2, (b, t, C))


@pytest.mark.parametrize(
    ("conditioner", "residual", "embedding"),
    [("lstm", False, 0), ("ff", False, 0), ("lstm", True, 0), ("lstm", True, 4)],
)
def test_sequence_pass_equals_frame_by_frame(conditioner, residual, embedding):
    """Training/scoring (sequence), per-frame scoring and the sampler run the same bijectors."""
    model = _model(conditioner, layers=2, residual=residual, cond_embedding=embedding)
    pose, control = _data()
    z_seq, ld_seq = jax.jit(lambda m, x, c: m.inverse_and_log_det(x, context=c, scope="window"))(
        model, pose, control
    )
    targets, cond = build_conditions(pose, control, TAU, scope="window")
    carry = model.initial_carry(pose.shape[0])
    step = jax.jit(lambda m, x, c, s: m._frame_to_latent(x, c, s))
    zs, total = [], 0.0
    for t in range(targets.shape[1]):
        z_t, ld_t, carry = step(model, targets[:, t], cond[:, t], carry)
        zs.append(z_t)
        total = total + ld_t
    np.testing.assert_allclose(np.stack(zs, 1), z_seq, atol=1e-5)
    np.testing.assert_allclose(total, ld_seq, atol=1e-4, rtol=1e-5)
    # and the sampler, fed the same latents, rebuilds the data frame by frame
    x_gen = jax.jit(lambda m, z, c: m.generate(z, c))(model, z_seq, control)
    np.testing.assert_allclose(x_gen, pose, atol=1e-5)


def test_official_scope_round_trip_with_seed_history():
    model = _model()
    pose, control = _data(t=10)
    z, ld = model.inverse_and_log_det(pose, context=control)
    assert z.shape == (3, 10 - TAU, D) and ld.shape == (3,)
    # sequence forward (teacher-forced condition) inverts the sequence inverse
    targets, cond = build_conditions(pose, control, TAU)
    x_back, ld_fwd = model.flow.forward_and_log_det(z, context=cond)
    np.testing.assert_allclose(x_back, targets, atol=1e-5)
    np.testing.assert_allclose(ld_fwd, -ld, rtol=1e-5, atol=1e-4)
    # the frame sampler seeded with the first tau frames and controls regenerates the rest
    x_gen = model.generate(
        z, control[:, TAU:], seed_history=pose[:, :TAU], seed_control=control[:, :TAU]
    )
    np.testing.assert_allclose(x_gen, targets, atol=1e-5)
    with pytest.raises(ValueError, match=r"z must be \(B, T, 6\) with the control's"):
        model.generate(z[:, :-1], control[:, TAU:])  # was a raw lax.scan length error


def test_the_experiments_sampler_passes_the_seed_controls():
    """experiments.moglow.sample could seed the history poses but not their controls (the
    first tau conditions then paired real poses with the mean control)."""
    import experiments.moglow as exp

    model = _model()
    pose, control = _data(t=10)
    seeded = dict(seed_history=pose[:, :TAU], temperature=0.0)
    key = jax.random.key(0)
    with_controls = exp.sample(
        model, key, control[:, TAU:], seed_control=control[:, :TAU], **seeded
    )
    direct = model.sample(key, control[:, TAU:], seed_control=control[:, :TAU], **seeded)
    np.testing.assert_allclose(with_controls, direct, atol=1e-5)
    assert (
        float(jnp.abs(with_controls - exp.sample(model, key, control[:, TAU:], **seeded)).max())
        > 1e-3
    )


@pytest.mark.parametrize("scope", ["official", "window"])
@pytest.mark.parametrize("residual", [False, True])
def test_log_det_matches_jacobian(scope, residual):
    model = _model(seed=3, residual=residual)
    pose, control = _data(b=1, t=6, seed=4)
    skip = TAU if scope == "official" else 0

    def f(flat):
        x = pose.at[0, skip:].set(flat.reshape(-1, D))
        return model.inverse_and_log_det(x, context=control, scope=scope)[0].reshape(-1)

    flat = pose[0, skip:].reshape(-1)
    jac = jax.jacfwd(f)(flat)
    sign, logabs = jnp.linalg.slogdet(jac)
    _, ld = model.inverse_and_log_det(pose, context=control, scope=scope)
    assert sign != 0
    np.testing.assert_allclose(ld[0], logabs, rtol=1e-4, atol=1e-3)
    # causality: a target frame's latent never depends on later frames
    jac = np.asarray(jac).reshape(-1, D, jac.shape[1] // D, D)
    for t in range(jac.shape[0]):
        assert np.all(jac[t, :, t + 1 :] == 0)
    assert np.any(jac[1:, :, 0] != 0)  # ... but does depend on earlier ones (history/LSTM)


def test_history_dropout_rate_and_pattern():
    b, t, rate = 400, 13, 0.7
    pose = jnp.ones((b, t, D)) + jnp.arange(D, dtype=jnp.float32)  # no zeros anywhere in the data
    control = jnp.ones((b, t, C))
    _, cond = build_conditions(pose, control, TAU, dropout=rate, key=jax.random.key(0))
    hist = np.asarray(cond[..., : TAU * D]).reshape(b, t - TAU, TAU, D)
    ctrl = np.asarray(cond[..., TAU * D :])
    dropped = np.all(hist == 0, axis=-1)
    # whole frames are dropped or kept, never single channels; no rescaling of kept frames
    assert np.all(dropped | np.all(hist == np.asarray(pose[0, 0]), axis=-1))
    assert np.all(ctrl == 1.0)  # controls never dropped
    n = dropped.size
    assert abs(dropped.mean() - rate) < 4 * np.sqrt(rate * (1 - rate) / n)
    # independent across history slots and across (window, t)
    d = dropped.reshape(-1, TAU).astype(float)
    corr = np.corrcoef(d.T)
    assert np.max(np.abs(corr - np.eye(TAU))) < 0.08
    per_window = dropped.mean(axis=(1, 2))
    assert per_window.std() > 0.05  # not one mask shared by the whole batch
    assert not np.all(dropped[:, 0] == dropped[:, 1])  # differs between target frames
    # no dropout without a rate; a key is needed with one
    _, clean = build_conditions(pose, control, TAU)
    assert np.all(np.asarray(clean) != 0)
    with pytest.raises(ValueError, match="key"):
        build_conditions(pose, control, TAU, dropout=0.5)


def test_dropout_keeps_last_never_drops_the_previous_frame():
    b, t, rate = 200, 13, 0.9
    pose = jnp.ones((b, t, D)) + jnp.arange(D, dtype=jnp.float32)
    control = jnp.ones((b, t, C))
    key = jax.random.key(0)
    _, cond = build_conditions(pose, control, TAU, dropout=rate, key=key, keep_last=True)
    hist = np.asarray(cond[..., : TAU * D]).reshape(b, t - TAU, TAU, D)
    dropped = np.all(hist == 0, axis=-1)
    assert not dropped[..., -1].any()  # x_{t-1} always there
    assert abs(dropped[..., :-1].mean() - rate) < 0.02  # the older frames at the rate
    # the model passes its option to the training-time conditions: with x_{t-1} kept, the
    # dropout NLL of a residual model changes (the conditioner sees the frame it adds to)
    data = _data()
    kw = dict(residual=True, dropout=0.9)
    base = _model(**kw).log_prob(*data, key=key)
    kept = _model(**kw, dropout_keeps_last=True).log_prob(*data, key=key)
    assert not np.allclose(base, kept)
    np.testing.assert_allclose(  # clean scoring is unaffected
        _model(**kw).log_prob(*data), _model(**kw, dropout_keeps_last=True).log_prob(*data)
    )


def test_history_pose_feeds_the_histories_and_not_the_targets():
    pose, control = _data()
    noisy = pose + 0.3 * jax.random.normal(jax.random.key(5), pose.shape)
    for scope in ("official", "window"):
        targets, cond = build_conditions(pose, control, TAU, scope=scope, history_pose=noisy)
        clean_targets, _ = build_conditions(pose, control, TAU, scope=scope)
        _, noisy_cond = build_conditions(noisy, control, TAU, scope=scope)
        np.testing.assert_array_equal(targets, clean_targets)  # targets: the true poses
        np.testing.assert_array_equal(cond, noisy_cond)  # histories: the given poses


@pytest.mark.parametrize("residual", [False, True])
def test_history_noise_corrupts_the_training_history_only(residual):
    """Training (a key) scores x_t given x~_s = x_s + sigma * eps_s; the residual model adds
    its change to the noisy x~_{t-1}; clean scoring and the zero padding are unaffected."""
    sigma, key = 0.2, jax.random.key(3)
    kw = dict(residual=residual)
    clean, noisy = _model(**kw), _model(**kw, history_noise=sigma)
    pose, control = _data(t=TAU + 1)  # one target frame in the official scope
    np.testing.assert_allclose(clean.log_prob(pose, control), noisy.log_prob(pose, control))
    assert not np.allclose(
        clean.log_prob(pose, control, key=key), noisy.log_prob(pose, control, key=key)
    )
    # official scope, one target: p(x_tau | x~_0..tau-1) is the clean score of the poses with
    # the noisy history in place of the true one (fails if the noise reached x_tau, or if the
    # residual's base were the true x_{tau-1})
    eps = jax.random.normal(jax.random.fold_in(key, 1), pose.shape)
    swapped = jnp.concatenate([pose[:, :TAU] + sigma * eps[:, :TAU], pose[:, TAU:]], axis=1)
    np.testing.assert_allclose(
        noisy.log_prob(pose, control, key=key),
        clean.log_prob(swapped, control),
        rtol=1e-5,
        atol=1e-4,
    )
    # window scope, T = 1: the only history is the zero padding, which stays exact
    one = (pose[:, :1], control[:, :1])
    np.testing.assert_allclose(
        noisy.log_prob(*one, scope="window", key=key), clean.log_prob(*one, scope="window")
    )
    with pytest.raises(ValueError, match="history_noise"):
        _model(history_noise=-0.1)


@pytest.mark.parametrize("residual", [False, True])
def test_own_history_draws_from_the_real_history_and_scores_the_true_targets(residual):
    """Parallel scheduled sampling: at temperature 0 every drawn frame is the model's mode
    given the real history (inverting it with the real conditions gives z = 0); training
    scores the true targets with the drawn frames in the later histories (and, residual,
    as the previous pose); clean scoring is unaffected."""
    from motionflows.models.moglow import previous_frames

    kw = dict(residual=residual, own_history_temperature=0.0)
    clean, own = _model(residual=residual), _model(**kw, own_history=1.0)
    pose, control = _data(t=TAU + 4)
    np.testing.assert_allclose(own.log_prob(pose, control), clean.log_prob(pose, control))
    key = jax.random.key(3)
    for scope in ("official", "window"):
        drawn = own._own_history(pose, control, scope, jax.random.fold_in(key, 2), 1.0)
        offset = TAU if scope == "official" else 0
        np.testing.assert_array_equal(drawn[:, :offset], pose[:, :offset])  # seeds stay real
        _, cond = build_conditions(pose, control, TAU, scope=scope)
        u = drawn[:, offset:]
        if residual:
            u = u - previous_frames(pose, TAU, scope)
        z, _ = own.flow.inverse_and_log_det(u, context=cond)
        np.testing.assert_allclose(z, 0.0, atol=1e-4)
        assert np.abs(np.asarray(drawn - pose)[:, offset:]).min() > 1e-3  # really replaced
    # the training score: true targets, histories (and the residual's base) from the draws
    drawn = own._own_history(pose, control, "official", jax.random.fold_in(key, 2), 1.0)
    targets, cond = build_conditions(pose, control, TAU, history_pose=drawn)
    if residual:
        targets = targets - previous_frames(drawn, TAU)
    z, log_det = own.flow.inverse_and_log_det(targets, context=cond)
    expected = jnp.sum(own.base_log_prob(z), axis=-1) + log_det
    np.testing.assert_allclose(own.log_prob(pose, control, key=key), expected, rtol=1e-5)
    # "change": the true change continued from the drawn previous frame,
    # x_t + x^_{t-1} - x_{t-1} (residual: u_t = x_t - x_{t-1}, the real change)
    carry_on = _model(**kw, own_history=1.0, own_history_target="change")
    targets, cond = build_conditions(pose, control, TAU, history_pose=drawn)
    if residual:
        targets = targets - previous_frames(pose, TAU)
    else:
        targets = targets + previous_frames(drawn - pose, TAU)
    z, log_det = carry_on.flow.inverse_and_log_det(targets, context=cond)
    expected = jnp.sum(carry_on.base_log_prob(z), axis=-1) + log_det
    np.testing.assert_allclose(carry_on.log_prob(pose, control, key=key), expected, rtol=1e-5)


def test_own_history_mixes_frames_and_passes_draw_from_draws():
    pose, control = _data(b=8, t=40)
    model = _model(residual=True, own_history_temperature=0.0, own_history_passes=2)
    key = jax.random.key(4)
    half = model._own_history(pose, control, "official", key, 0.5)
    replaced = np.abs(np.asarray(half - pose)).max(axis=-1) > 0  # (B, T) frames swapped
    assert not replaced[:, :TAU].any()
    assert 0.35 < replaced[:, TAU:].mean() < 0.65  # each frame with probability 0.5
    # two passes: the second draws every frame from the first pass's drawn histories
    one = _model(residual=True, own_history_temperature=0.0)
    first = one._own_history(pose, control, "official", key, 1.0)
    second = model._own_history(pose, control, "official", key, 1.0)
    assert not np.allclose(first, second, atol=1e-4)
    _, cond = build_conditions(pose, control, TAU, history_pose=first)
    u = second[:, TAU:] - first[:, TAU - 1 : -1]
    z, _ = model.flow.inverse_and_log_det(u, context=cond)
    np.testing.assert_allclose(z, 0.0, atol=1e-4)
    for bad in (dict(own_history=1.5), dict(own_history_passes=0),
                dict(own_history_temperature=-1.0), dict(own_history_target="x")):  # fmt: skip
        with pytest.raises(ValueError, match="own_history"):
            _model(**bad)


def test_log_prob_dropout_uses_key():
    model = _model(dropout=0.5)
    pose, control = _data()
    clean = model.log_prob(pose, control)
    a = model.log_prob(pose, control, key=jax.random.key(1))
    b = model.log_prob(pose, control, key=jax.random.key(1))
    c = model.log_prob(pose, control, key=jax.random.key(2))
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, clean) and not np.allclose(a, c)
    np.testing.assert_allclose(
        model.log_prob(pose, control, key=jax.random.key(1), dropout=0.0), clean, rtol=1e-6
    )
    with pytest.raises(ValueError, match="needs a key"):
        model.log_prob(pose, control, dropout=0.7)


@pytest.mark.parametrize("residual", [False, True])
def test_stream_step_equals_sample(residual):
    model = _model(residual=residual)
    _, control = _data(b=2, t=7)
    key = jax.random.key(5)
    seed = jax.random.normal(jax.random.key(6), (2, 5, D))
    x = jax.jit(lambda m, c, k: m.sample(k, c, seed_history=seed, temperature=0.8))(
        model, control, key
    )
    step = jax.jit(lambda m, s, c, k: m.stream_step(s, c, k, temperature=0.8))
    state = model.init_stream(2, seed)
    frames = []
    for t in range(control.shape[1]):
        x_t, state = step(model, state, control[:, t], key)
        frames.append(x_t)
    np.testing.assert_allclose(np.stack(frames, 1), x, atol=1e-6)
    assert int(state.t) == control.shape[1]
    np.testing.assert_allclose(state.poses, x[:, -TAU:], atol=0)
    # temperature 0 is exact: the decoded all-zero latent
    x0 = model.sample(key, control, temperature=0.0)
    np.testing.assert_allclose(x0, model.generate(jnp.zeros((2, 7, D)), control), atol=1e-6)
    # samples follow the key
    assert not np.allclose(model.sample(jax.random.key(7), control), x)


def test_base_density_is_the_distributions_one():
    z = 2.0 * jax.random.normal(jax.random.key(0), (3, 4, D))
    normal = _model()
    np.testing.assert_allclose(
        normal.base_log_prob(z), jax.scipy.stats.norm.logpdf(z).sum(-1), rtol=1e-5
    )
    student = _model(base="studentt", df=3.0)
    np.testing.assert_allclose(
        student.base_log_prob(z), jax.scipy.stats.t.logpdf(z, 3.0).sum(-1), rtol=1e-5
    )
    # the sampler draws its latents from the same density: fold_in(key, t) per frame
    key, control = jax.random.key(4), jnp.zeros((2, 3, C))
    x = student.sample(key, control, temperature=0.5)
    want = 0.5 * student.base_density().sample(jax.random.fold_in(key, 0), (2,))
    np.testing.assert_allclose(x[:, 0], student.generate(want[:, None], control[:, :1])[:, 0],
                               atol=1e-6)  # fmt: skip


@pytest.mark.parametrize("residual", [False, True])
def test_window_scope_is_the_sampler_density(residual):
    """log_prob(scope='window') equals base log-density of the latents the sampler used."""
    model = _model(residual=residual)
    _, control = _data(b=2, t=6)
    z = jax.random.normal(jax.random.key(9), (2, 6, D))
    x = model.generate(z, control)
    z_back, ld = model.inverse_and_log_det(x, context=control, scope="window")
    np.testing.assert_allclose(z_back, z, atol=1e-4)
    lp = model.log_prob(x, control, scope="window")
    np.testing.assert_allclose(lp, model.base_log_prob(z).sum(-1) + ld, rtol=1e-5)


def test_initialize_from_data_normalises_first_actnorm():
    model = MoGlow(D, C, tau=TAU, K=2, hidden=H, num_layers=1, rngs=jax.random.key(0))
    pose, control = _data(b=16, t=12)
    pose = 3.0 * pose + 5.0
    init = initialize_from_data(model, pose, context=control)
    targets, _ = build_conditions(pose, control, TAU)
    last = init.flow.step(1)  # the last step of the stack runs first in data -> latent
    an = last.bijectors[2]
    u = (targets + an.bias[...]) * jnp.exp(an.logs[...])
    np.testing.assert_allclose(u.reshape(-1, D).mean(0), 0, atol=1e-4)
    np.testing.assert_allclose(u.reshape(-1, D).std(0), 1, atol=1e-3)
    # the original model is untouched
    assert np.all(model.flow.steps.bijectors[2].logs[...] == 0)


def test_bfloat16_close_to_float32_and_student_t():
    pose, control = _data()
    a = _model()
    graph, state = nnx.split(a)
    b = MoGlow(
        D,
        C,
        tau=TAU,
        K=K,
        hidden=H,
        num_layers=1,
        compute_dtype="bfloat16",
        rngs=jax.random.key(0),
    )
    nnx.update(b, state)
    la, lb = a.log_prob(pose, control), b.log_prob(pose, control)
    assert lb.dtype == jnp.float32
    diff = float(jnp.max(jnp.abs(la - lb)))
    assert 0 < diff < 0.05 * float(jnp.max(jnp.abs(la)))
    t = _model(base="studentt")
    lt = t.log_prob(pose, control)
    assert np.all(np.isfinite(lt)) and not np.allclose(lt, la)
    assert np.all(np.isfinite(t.sample(jax.random.key(0), control)))
    # the bfloat16 sampler runs the same frame steps: close to the float32 one
    xa, xb = a.sample(jax.random.key(1), control), b.sample(jax.random.key(1), control)
    assert xb.dtype == jnp.float32
    assert 0 < float(jnp.max(jnp.abs(xa - xb))) < 0.1 * float(jnp.max(jnp.abs(xa)))


def test_clear_errors():
    model = _model()
    pose, control = _data()
    with pytest.raises(ValueError, match="control must be"):
        model.log_prob(pose, control[..., :1])
    with pytest.raises(ValueError, match="pose must be"):
        model.log_prob(pose[..., :4], control)
    with pytest.raises(ValueError, match="share"):
        model.log_prob(pose[:, :5], control)
    with pytest.raises(ValueError, match="seed_history"):
        model.sample(jax.random.key(0), control, seed_history=jnp.zeros((3, 2, D + 1)))
    with pytest.raises(ValueError, match="control_t"):
        model.stream_step(model.init_stream(3), jnp.zeros((2, C)), jax.random.key(0))
    with pytest.raises(ValueError, match="conditioner"):
        MoGlow(D, C, conditioner="gru", rngs=jax.random.key(0))
    with pytest.raises(ValueError, match="scope"):
        model.log_prob(pose, control, scope="all")


def test_residual_flows_the_change_of_pose():
    """The residual model's latents are the plain flow's latents of x_t - x_{t-1}: same
    parameters, same log-det, and it samples around the previous pose."""
    plain, res = _model(), _model(residual=True)
    pose, control = _data(b=2, t=8)
    prev = jnp.pad(pose, ((0, 0), (1, 0), (0, 0)))[:, :-1]
    # the plain model on the changes, with the history of the true poses
    from motionflows.models.moglow import build_conditions as bc

    targets, cond = bc(pose, control, TAU, scope="window")
    z_ref, ld_ref = plain.flow.inverse_and_log_det(targets - prev, context=cond)
    z, ld = res.inverse_and_log_det(pose, context=control, scope="window")
    np.testing.assert_allclose(z, z_ref, atol=1e-5)
    np.testing.assert_allclose(ld, ld_ref, rtol=1e-6)
    # streaming: the residual sampler adds each new change to the previous pose
    seed = pose[:, :TAU]
    state = res.init_stream(2, seed)
    x_t, _ = res.stream_step(state, control[:, 0], jax.random.key(1), temperature=0.0)
    change, _ = plain.stream_step(plain.init_stream(2, seed), control[:, 0], jax.random.key(1),
                                  temperature=0.0)  # fmt: skip
    np.testing.assert_allclose(x_t, seed[:, -1] + change, atol=1e-5)


@pytest.mark.parametrize("conditioner", ["lstm", "ff"])
def test_inference_copy_stores_conditioner_weights_in_bfloat16(conditioner):
    from motionflows.inference import inference_copy

    model = _model(conditioner, layers=2)
    lp = inference_copy(model, "bfloat16")
    dtypes = {
        jax.tree_util.keystr(path): leaf.dtype
        for path, leaf in jax.tree_util.tree_leaves_with_path(nnx.state(lp, nnx.Param))
    }
    low = {path for path, dt in dtypes.items() if dt == jnp.bfloat16}
    matrix = re.compile(r"\['conditioner'\].*\['(w_ih|w_hh|w_out|ws)'\](\[\d+\])?\.value$")
    # every conditioner matrix is stored in bfloat16, nothing else (biases, ActNorm, 1x1 maps)
    assert low and low == {p for p in dtypes if matrix.search(p)}
    assert len(dtypes) > len(low)
    assert all(
        leaf.dtype == jnp.float32 for leaf in jax.tree.leaves(nnx.state(model, nnx.Param))
    )  # the original is untouched
    control = jax.random.normal(jax.random.key(7), (2, 12, C))
    exact = model.sample(jax.random.key(8), control)
    approx = lp.sample(jax.random.key(8), control)
    assert approx.dtype == jnp.float32
    rel = float(jnp.linalg.norm(approx - exact) / jnp.linalg.norm(exact))
    assert 0 < rel < 0.05  # bfloat16 weights: close, not equal
    state = lp.init_stream(2)
    x0, _ = lp.stream_step(state, control[:, 0], jax.random.key(8))
    np.testing.assert_allclose(x0, approx[:, 0], rtol=1e-5, atol=1e-5)


def _world_model(seed=0, world_joints="all", **options):
    """A residual MoGlow on the real feature sizes (63, 3) with non-trivial units:
    ``residual_world`` unless ``options`` say otherwise (e.g. ``stance_hint=True``)."""
    from motionflows.data.names import CONTROL_DIM, POSE_DIM

    rng = np.random.default_rng(seed)
    options = options or {"residual_world": True, "world_joints": world_joints}
    m = MoGlow(POSE_DIM, CONTROL_DIM, tau=TAU, K=K, hidden=H, num_layers=1, residual=True,
               rngs=jax.random.key(seed), **options)  # fmt: skip
    m = perturbed(m, jax.random.key(seed + 100), scale=0.05)
    return m.with_units(
        rng.normal(0, 0.3, POSE_DIM), rng.uniform(0.05, 0.4, POSE_DIM),
        np.array([0.04, 0.0, 0.0]), np.array([0.03, 0.01, 0.05]),
    )  # fmt: skip


def _world_data(model, b=2, t=8, seed=1):
    """Standardised (pose, control) of a moving, turning root; joints random in metres."""
    from motionflows.data.names import CONTROL_DIM, POSE_DIM

    k1, k2 = jax.random.split(jax.random.key(seed))
    u = np.asarray(model.units[...])
    d = POSE_DIM
    pose = jax.random.normal(k1, (b, t, d))
    control = jax.random.normal(k2, (b, t, CONTROL_DIM))
    return pose, control, (u[:d], u[d : 2 * d], u[2 * d : 2 * d + 3], u[2 * d + 3 :])


@pytest.mark.parametrize("world_joints", ["all", "feet"])
def test_residual_world_is_exact_and_one_map_for_training_and_sampling(world_joints):
    """The world residual is a bijection with the exact log-det (jacfwd), the sequence pass
    equals the frame steps, and the sampler inverts it frame by frame."""
    model = _world_model(world_joints=world_joints)
    pose, control, _ = _world_data(model, b=1, t=5)

    def f(flat):
        return model.inverse_and_log_det(flat.reshape(1, 5, -1), context=control, scope="window")[
            0
        ].reshape(-1)

    jac = jax.jacfwd(f)(pose.reshape(-1))
    _, logabs = jnp.linalg.slogdet(jac)
    z, ld = model.inverse_and_log_det(pose, context=control, scope="window")
    np.testing.assert_allclose(ld[0], logabs, rtol=1e-4, atol=1e-3)
    x_gen = jax.jit(lambda m, z, c: m.generate(z, c))(model, z, control)
    np.testing.assert_allclose(x_gen, pose, atol=1e-4)
    # the sequence pass and the sampler's frame steps see the same residual
    targets, cond = build_conditions(pose, control, TAU, scope="window")
    carry = model.initial_carry(1)
    for t in range(5):
        z_t, _, carry = model._frame_to_latent(targets[:, t], cond[:, t], carry)
        np.testing.assert_allclose(z_t, z[:, t], atol=1e-4)


def test_residual_world_flows_zero_for_joints_still_in_the_world():
    """A body standing still in the world while the root moves and turns has world residual
    0 at every frame (frame 0 too: it is the zero history's mean pose carried by the mean
    control); the plain residual flows minus the root's move."""
    from motionflows.data.features import carry_to_next_root

    model = _world_model(seed=2)
    _, _, (p_mean, p_std, c_mean, c_std) = _world_data(model)
    t = 8
    control_m = np.stack([np.full(t, 0.06), np.full(t, 0.01), np.full(t, 0.1)], -1)
    frames = [carry_to_next_root(np.asarray(p_mean, np.float64), np.asarray(c_mean, np.float64))]
    for i in range(1, t):
        frames.append(carry_to_next_root(frames[-1], control_m[i - 1]))
    pose = jnp.asarray(((np.stack(frames) - p_mean) / p_std)[None], jnp.float32)
    control = jnp.asarray(((control_m - c_mean) / c_std)[None], jnp.float32)
    targets, cond = build_conditions(pose, control, TAU, scope="window")
    prev = jnp.pad(pose, ((0, 0), (1, 0), (0, 0)))[:, :-1]
    z, _ = model.inverse_and_log_det(pose, context=control, scope="window")
    z_zero, _ = model.flow.inverse_and_log_det(jnp.zeros_like(targets), context=cond)
    np.testing.assert_allclose(z, z_zero, atol=2e-4)
    z_plain, _ = model.flow.inverse_and_log_det(targets - prev, context=cond)
    assert np.abs(np.asarray(z_plain - z_zero)).max() > 0.1
    # world_joints="feet": the ankles and toes flow 0, every other joint its plain change
    from motionflows.data.names import FOOT_JOINTS

    feet = _world_model(seed=2, world_joints="feet")
    z_feet, _ = feet.inverse_and_log_det(pose, context=control, scope="window")
    is_foot = np.isin(np.arange(63) // 3, FOOT_JOINTS)
    mixed = jnp.where(is_foot, 0.0, targets - prev)
    z_mixed, _ = feet.flow.inverse_and_log_det(mixed, context=cond)
    np.testing.assert_allclose(z_feet, z_mixed, atol=2e-4)
    assert np.abs(np.asarray(z_feet - z_zero)).max() > 0.1


def test_residual_world_needs_its_units_and_the_motion_features():
    with pytest.raises(ValueError, match="world_joints must be one of"):
        MoGlow(63, 3, residual=True, residual_world=True, world_joints="hands",
               rngs=jax.random.key(0))  # fmt: skip
    with pytest.raises(ValueError, match="needs residual_world=True"):  # else silently unused
        MoGlow(63, 3, residual=True, world_joints="feet", rngs=jax.random.key(0))
    import experiments.moglow as E

    with pytest.raises(ValueError, match="needs residual_world=True"):
        E.Config(residual=True, world_joints="feet")
    with pytest.raises(ValueError, match="needs residual=True"):
        MoGlow(63, 3, residual_world=True, rngs=jax.random.key(0))
    with pytest.raises(ValueError, match="pose_dim=63"):
        MoGlow(D, C, residual=True, residual_world=True, rngs=jax.random.key(0))
    with pytest.raises(ValueError, match="residual_world"):
        _model().with_units(np.zeros(D), np.ones(D), np.zeros(C), np.ones(C))
    with pytest.raises(ValueError, match="positive"):
        _world_model().with_units(np.zeros(63), np.zeros(63), np.zeros(3), np.ones(3))


def test_stance_hint_is_the_change_of_a_planted_foot_and_only_a_condition():
    """The hint of a body standing still in the world is exactly its feet's change; the
    model stays an exact bijection (jacfwd) whose sequence pass, frame steps and sampler
    agree, and the hint changes the latents (the conditioner reads it)."""
    from motionflows.data.features import carry_to_next_root
    from motionflows.data.names import FOOT_JOINTS

    model = _world_model(seed=2, stance_hint=True)
    _, _, (p_mean, p_std, c_mean, c_std) = _world_data(model)
    t = 6
    control_m = np.stack([np.full(t, 0.06), np.full(t, 0.01), np.full(t, 0.1)], -1)
    frames = [np.asarray(p_mean, np.float64) + 0.1]
    for i in range(1, t):
        frames.append(carry_to_next_root(frames[-1], control_m[i - 1]))
    pose = jnp.asarray(((np.stack(frames) - p_mean) / p_std)[None], jnp.float32)
    control = jnp.asarray(((control_m - c_mean) / c_std)[None], jnp.float32)
    targets, cond, previous = model.conditions(pose, control, scope="official")
    assert cond.shape[-1] == model.cond_dim == TAU * 63 + (TAU + 1) * 3 + 12
    is_foot = np.isin(np.arange(63) // 3, FOOT_JOINTS)
    np.testing.assert_allclose(cond[..., -12:], (targets - previous)[..., is_foot], atol=1e-4)
    assert np.abs(np.asarray(cond[..., -12:])).max() > 0.1  # the root moved them

    pose, control, _ = _world_data(model, b=1, t=5)

    def f(flat):
        z = model.inverse_and_log_det(flat.reshape(1, 5, -1), context=control, scope="window")
        return z[0].reshape(-1)

    _, logabs = jnp.linalg.slogdet(jax.jacfwd(f)(pose.reshape(-1)))
    z, ld = model.inverse_and_log_det(pose, context=control, scope="window")
    np.testing.assert_allclose(ld[0], logabs, rtol=1e-4, atol=1e-3)
    np.testing.assert_allclose(model.generate(z, control), pose, atol=1e-4)
    targets, cond, _ = model.conditions(pose, control, scope="window")
    carry = model.initial_carry(1)
    for i in range(5):
        z_t, _, carry = model._frame_to_latent(targets[:, i], cond[:, i], carry)
        np.testing.assert_allclose(z_t, z[:, i], atol=1e-4)
    blind = model.flow.inverse_and_log_det(
        targets - jnp.pad(pose, ((0, 0), (1, 0), (0, 0)))[:, :-1],
        context=cond.at[..., -12:].set(0.0),
    )[0]
    assert np.abs(np.asarray(blind - z)).max() > 1e-3


def test_cond_embedding_is_one_linear_map_all_steps_read_and_only_a_condition():
    """With ``cond_embedding`` = E every coupling's conditioner reads e_t = cond_t W (E
    values): the latents are the plain flow's given embed(cond) by hand, the log-det is
    exact (jacfwd; the embedding is not part of the event), and the embedding matters."""
    model = _model(seed=5, residual=True, cond_embedding=4)
    assert model.embed.w_embed.shape == (model.cond_dim, 4)
    lstm = model.flow.steps.bijectors[0].conditioner.lstm.layers[0]
    assert lstm.w_ih.shape[-2] == coupling_sizes(D)[0] + 4  # [x_a, e_t], not [x_a, cond_t]
    pose, control = _data(b=1, t=6, seed=6)
    z, ld = model.inverse_and_log_det(pose, context=control, scope="window")
    targets, cond, previous = model.conditions(pose, control, scope="window")
    by_hand, ld_hand = model.flow.inverse_and_log_det(targets - previous, context=model.embed(cond))
    np.testing.assert_allclose(z, by_hand, atol=1e-6)
    np.testing.assert_allclose(ld, ld_hand, rtol=1e-6)

    def f(flat):
        x = flat.reshape(pose.shape)
        return model.inverse_and_log_det(x, context=control, scope="window")[0].reshape(-1)

    _, logabs = jnp.linalg.slogdet(jax.jacfwd(f)(pose.reshape(-1)))
    np.testing.assert_allclose(ld[0], logabs, rtol=1e-4, atol=1e-3)
    other = nnx.clone(model)
    other.embed.w_embed.set_value(other.embed.w_embed[...] * 2.0)
    moved = other.inverse_and_log_det(pose, context=control, scope="window")[0]
    assert np.abs(np.asarray(moved - z)).max() > 1e-3
    from motionflows.inference import inference_copy  # unrolled steps, the same map

    np.testing.assert_allclose(
        inference_copy(model).sample(jax.random.key(9), control),
        model.sample(jax.random.key(9), control),
        atol=1e-5,
    )
    assert inference_copy(model, "bfloat16").embed.w_embed.dtype == jnp.bfloat16
    with pytest.raises(ValueError, match="cond_embedding must be 0"):
        MoGlow(D, C, cond_embedding=-1, rngs=jax.random.key(0))


def test_stance_hint_needs_the_motion_features_and_its_units():
    import experiments.moglow as E

    with pytest.raises(ValueError, match="stance_hint needs the motion features"):
        MoGlow(D, C, stance_hint=True, rngs=jax.random.key(0))
    model = E.build(dataclasses.replace(E.PRESETS["smoke"], tau=TAU, stance_hint=True),
                    key=jax.random.key(0))  # fmt: skip
    pose, control = jnp.zeros((2, 8, 63)), jnp.zeros((2, 8, 3))
    with pytest.raises(ValueError, match="needs the run's standardizer"):
        E.initialize(model, {"pose": pose, "control": control}, key=jax.random.key(1))


def test_absolute_foot_heights_flow_the_heights_and_stay_exact():
    """With ``absolute_foot_heights`` the ankles' and toes' heights enter the flow as they are
    and every other channel as its change; the log-det is exact (jacfwd), the sampler inverts
    the sequence pass, and the frame steps see the same map."""
    from motionflows.data.names import CONTROL_DIM, FOOT_JOINTS, POSE_DIM

    model = MoGlow(POSE_DIM, CONTROL_DIM, tau=TAU, K=K, hidden=H, num_layers=1, residual=True,
                   absolute_foot_heights=True, rngs=jax.random.key(3))  # fmt: skip
    model = perturbed(model, jax.random.key(103), scale=0.05)
    k1, k2 = jax.random.split(jax.random.key(4))
    pose = jax.random.normal(k1, (1, 5, POSE_DIM))
    control = jax.random.normal(k2, (1, 5, CONTROL_DIM))

    targets, cond = build_conditions(pose, control, TAU, scope="window")
    prev = jnp.pad(pose, ((0, 0), (1, 0), (0, 0)))[:, :-1]
    is_height = np.isin(np.arange(POSE_DIM) // 3, FOOT_JOINTS) & (np.arange(POSE_DIM) % 3 == 1)
    assert is_height.sum() == 4
    z, ld = model.inverse_and_log_det(pose, context=control, scope="window")
    expected, _ = model.flow.inverse_and_log_det(
        jnp.where(is_height, targets, targets - prev), context=cond
    )
    np.testing.assert_allclose(z, expected, atol=1e-5)
    plain = nnx.clone(model)
    plain.absolute_foot_heights = False
    assert (
        np.abs(
            np.asarray(plain.inverse_and_log_det(pose, context=control, scope="window")[0] - z)
        ).max()
        > 0.1
    )

    def f(flat):
        out = model.inverse_and_log_det(flat.reshape(1, 5, -1), context=control, scope="window")
        return out[0].reshape(-1)

    _, logabs = jnp.linalg.slogdet(jax.jacfwd(f)(pose.reshape(-1)))
    np.testing.assert_allclose(ld[0], logabs, rtol=1e-4, atol=1e-3)
    np.testing.assert_allclose(model.generate(z, control), pose, atol=1e-4)
    carry = model.initial_carry(1)
    for t in range(5):
        z_t, _, carry = model._frame_to_latent(targets[:, t], cond[:, t], carry)
        np.testing.assert_allclose(z_t, z[:, t], atol=1e-4)
    with pytest.raises(ValueError, match="needs residual=True"):
        MoGlow(POSE_DIM, CONTROL_DIM, absolute_foot_heights=True, rngs=jax.random.key(0))
    import experiments.moglow as E

    with pytest.raises(ValueError, match="needs residual=True"):
        E.Config(absolute_foot_heights=True)
