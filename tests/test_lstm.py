"""The LSTM stack against an independent numpy LSTM (PyTorch semantics: gates i, f, g, o)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from motionflows.nets.lstm import LSTM


def _sigmoid(x):
    return 1.0 / (1.0 + np.exp(-x))


def numpy_lstm(x, layers):
    """x (B, T, in); layers: list of dicts with PyTorch-layout weight_ih (4H, in), ..."""
    h_in = np.asarray(x, np.float64)
    for p in layers:
        hidden = p["weight_hh"].shape[1]
        b, t = h_in.shape[:2]
        h = np.zeros((b, hidden))
        c = np.zeros((b, hidden))
        out = []
        for s in range(t):
            g = h_in[:, s] @ p["weight_ih"].T + p["bias_ih"] + h @ p["weight_hh"].T + p["bias_hh"]
            i = _sigmoid(g[:, :hidden])
            f = _sigmoid(g[:, hidden : 2 * hidden])
            gg = np.tanh(g[:, 2 * hidden : 3 * hidden])
            o = _sigmoid(g[:, 3 * hidden :])
            c = f * c + i * gg
            h = o * np.tanh(c)
            out.append(h)
        h_in = np.stack(out, 1)
    return h_in


def _torch_layout(lstm):
    return [
        {
            "weight_ih": np.asarray(layer.w_ih[...]).T,
            "weight_hh": np.asarray(layer.w_hh[...]).T,
            "bias_ih": np.asarray(layer.b_ih[...]),
            "bias_hh": np.asarray(layer.b_hh[...]),
        }
        for layer in lstm.layers
    ]


@pytest.fixture(scope="module")
def lstm():
    return LSTM(5, 7, 2, rngs=nnx.Rngs(0))


def test_sequence_matches_numpy_reference(lstm):
    x = jax.random.normal(jax.random.key(1), (3, 6, 5))
    y, carry = jax.jit(lambda m, x: m(x))(lstm, x)
    ref = numpy_lstm(np.asarray(x), _torch_layout(lstm))
    np.testing.assert_allclose(np.asarray(y), ref, atol=2e-6)
    # the last layer's final h is the last output
    np.testing.assert_allclose(np.asarray(carry[-1][0]), ref[:, -1], atol=2e-6)


def test_step_equals_sequence_and_carry_continues(lstm):
    x = jax.random.normal(jax.random.key(2), (2, 8, 5))
    y, carry = lstm(x)
    state = lstm.initial_carry((2,))
    steps = []
    for t in range(8):
        y_t, state = lstm.step(x[:, t], state)
        steps.append(y_t)
    np.testing.assert_allclose(np.stack(steps, 1), y, atol=1e-6)
    # splitting the sequence in two with an explicit carry gives the same outputs
    y1, c1 = lstm(x[:, :3])
    y2, _ = lstm(x[:, 3:], c1)
    np.testing.assert_allclose(np.concatenate([y1, y2], 1), y, atol=1e-6)
    for (h_a, c_a), (h_b, c_b) in zip(state, carry, strict=True):
        np.testing.assert_allclose(h_a, h_b, atol=1e-6)
        np.testing.assert_allclose(c_a, c_b, atol=1e-6)


def test_default_init_is_uniform_in_bound():
    lstm = LSTM(4, 16, 1, rngs=nnx.Rngs(3))
    w = np.asarray(lstm.layers[0].w_hh[...])
    bound = 1 / np.sqrt(16)
    assert np.abs(w).max() <= bound
    assert np.abs(w).max() > 0.9 * bound  # really uses the range
    assert abs(w.mean()) < 0.05 * bound * 4
    assert lstm.layers[0].w_ih.shape == (4, 64)


def test_bfloat16_compute_is_close_and_float32_out():
    key = jax.random.key(4)
    a = LSTM(5, 7, 2, rngs=nnx.Rngs(5))
    b = LSTM(5, 7, 2, rngs=nnx.Rngs(5), compute_dtype="bfloat16")
    x = jax.random.normal(key, (2, 6, 5))
    ya, _ = a(x)
    yb, _ = b(x)
    assert yb.dtype == jnp.float32
    err = float(jnp.max(jnp.abs(ya - yb)))
    assert 0 < err < 3e-2


def test_bad_shape_raises(lstm):
    with pytest.raises(ValueError, match="LSTM expects"):
        lstm(jnp.zeros((2, 6, 4)))
    with pytest.raises(ValueError, match="LSTM expects"):
        lstm.step(jnp.zeros((2, 4)), lstm.initial_carry((2,)))


def _plain_lstm(params, x, carry):
    """The same stack in plain float32 JAX (autodiff through lax.scan): the reference."""
    h_in = jnp.moveaxis(x, -2, 0)
    finals = []
    for p, state in zip(params, carry, strict=True):

        def body(state, x_t, p=p):
            h, c = state
            g = x_t @ p["w_ih"] + p["b_ih"] + h @ p["w_hh"] + p["b_hh"]
            i, f, gg, o = jnp.split(g, 4, axis=-1)
            c = jax.nn.sigmoid(f) * c + jax.nn.sigmoid(i) * jnp.tanh(gg)
            h = jax.nn.sigmoid(o) * jnp.tanh(c)
            return (h, c), h

        state, h_in = jax.lax.scan(body, state, h_in)
        finals.append(state)
    return jnp.moveaxis(h_in, 0, -2), tuple(finals)


@pytest.mark.parametrize("compute_dtype, rtol", [(None, 1e-5), ("bfloat16", 3e-2)])
def test_hand_written_backward_matches_autodiff(compute_dtype, rtol):
    lstm = LSTM(5, 7, 2, rngs=nnx.Rngs(3), compute_dtype=compute_dtype)
    keys = jax.random.split(jax.random.key(4), 4)
    x = jax.random.normal(keys[0], (3, 6, 5))
    carry = tuple(
        (0.5 * jax.random.normal(k, (3, 7)), jax.random.normal(jax.random.fold_in(k, 1), (3, 7)))
        for k in jax.random.split(keys[1], 2)
    )
    w_y = jax.random.normal(keys[2], (3, 6, 7))
    w_c = jax.random.normal(keys[3], (3, 7))
    graphdef, params = nnx.split(lstm)
    plain = [
        {name: getattr(layer, name)[...] for name in ("w_ih", "w_hh", "b_ih", "b_hh")}
        for layer in lstm.layers
    ]

    def score(y, final):  # every output and the final state (h and c) matter
        return jnp.sum(y * w_y) + sum(jnp.sum((h + c) * w_c) for h, c in final)

    def ours(params, x, carry):
        return score(*nnx.merge(graphdef, params)(x, carry))

    def reference(plain, x, carry):
        return score(*_plain_lstm(plain, x, carry))

    g_ours = jax.jit(jax.grad(ours, argnums=(0, 1, 2)))(params, x, carry)
    g_ref = jax.grad(reference, argnums=(0, 1, 2))(plain, x, carry)
    as_plain = [
        {name: getattr(layer, name)[...] for name in ("w_ih", "w_hh", "b_ih", "b_hh")}
        for layer in nnx.merge(graphdef, g_ours[0]).layers
    ]
    for a, b in zip(
        jax.tree.leaves((as_plain, g_ours[1], g_ours[2])),
        jax.tree.leaves((g_ref[0], g_ref[1], g_ref[2])),
        strict=True,
    ):
        assert float(jnp.linalg.norm(a - b)) <= rtol * float(jnp.linalg.norm(b)) + 1e-6


def test_context_equals_concatenated_input():
    lstm = LSTM(5, 7, 2, rngs=nnx.Rngs(5))
    x = jax.random.normal(jax.random.key(6), (2, 4, 5))
    y, carry = lstm(x)
    y2, carry2 = lstm(x[..., :2], context=x[..., 2:])
    np.testing.assert_allclose(y2, y, atol=1e-6)
    with pytest.raises(ValueError, match="plus 2 context features"):
        lstm(x, context=x[..., :2])


def test_forward_mode_matches_reverse_mode():
    lstm = LSTM(5, 7, 2, rngs=nnx.Rngs(8))
    x = jax.random.normal(jax.random.key(9), (2, 4, 5))
    fwd = jax.jacfwd(lambda x: lstm(x)[0])(x)
    rev = jax.jacrev(lambda x: lstm(x)[0])(x)
    np.testing.assert_allclose(fwd, rev, atol=1e-5)
    assert float(jnp.abs(fwd).max()) > 1e-2  # a real dependence


def test_low_precision_matmul_backward_is_low_precision_and_close():
    from motionflows.nets.precision import matmul

    x = jax.random.normal(jax.random.key(10), (3, 5, 16))
    w = jax.random.normal(jax.random.key(11), (16, 8))
    r = jax.random.normal(jax.random.key(12), (3, 5, 8))

    def loss(x, w, cd):
        return jnp.sum(matmul(x, w, cd) * r)

    g32 = jax.grad(loss, argnums=(0, 1))(x, w, None)
    g16 = jax.jit(jax.grad(loss, argnums=(0, 1)), static_argnums=2)(x, w, "bfloat16")
    for a, b in zip(g16, g32, strict=True):
        assert a.dtype == jnp.float32
        assert float(jnp.linalg.norm(a - b)) <= 2e-2 * float(jnp.linalg.norm(b))
    # the backward products take bfloat16 operands, the cotangent r included (plain
    # autodiff would keep r in float32): dx = bf16(r) @ bf16(w)^T, dw = bf16(x)^T bf16(r)
    bf = jnp.bfloat16
    x2, r2 = x.reshape(-1, 16).astype(bf), r.reshape(-1, 8).astype(bf)
    dw = jnp.matmul(x2.T, r2, preferred_element_type=jnp.float32)
    dx = jnp.matmul(r.astype(bf), w.astype(bf).T, preferred_element_type=jnp.float32)
    np.testing.assert_allclose(g16[1], dw, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(g16[0], dx, rtol=1e-5, atol=1e-5)
    # float32: exact, dx = r @ w^T
    np.testing.assert_allclose(g32[0], r @ w.T, rtol=1e-5, atol=1e-5)


def _dots_in_loops(jaxpr, inside=False):
    """Output shapes of the dot_generals of a jaxpr, tagged with whether they sit in a loop."""
    found = []
    for eqn in jaxpr.eqns:
        if eqn.primitive.name == "dot_general":
            found.append((inside, tuple(eqn.outvars[0].aval.shape)))
        loop = eqn.primitive.name in ("scan", "while")
        for value in eqn.params.values():
            for sub in value if isinstance(value, tuple | list) else (value,):
                sub = getattr(sub, "jaxpr", sub)  # ClosedJaxpr -> Jaxpr
                if hasattr(sub, "eqns"):
                    found += _dots_in_loops(sub, inside or loop)
    return found


def test_float32_backward_forms_the_recurrent_weight_gradient_outside_the_time_loop():
    # dW_hh = sum_t h_{t-1}^T dpre_t: one matmul over all frames, not a (H, 4H) product and
    # accumulation per frame inside the reverse scan (plain autodiff through lax.scan does that)
    lstm = LSTM(5, 7, 1, rngs=nnx.Rngs(12))
    x = jax.random.normal(jax.random.key(13), (3, 6, 5))
    graphdef, params = nnx.split(lstm)
    loss = lambda p: jnp.sum(nnx.merge(graphdef, p)(x)[0] ** 2)  # noqa: E731
    dots = _dots_in_loops(jax.make_jaxpr(jax.grad(loss))(params).jaxpr)
    weight_shaped = [inside for inside, shape in dots if sorted(shape) == [7, 28]]
    assert weight_shaped == [False]  # dW_hh (or its transpose), once, outside any loop
    assert any(inside for inside, _ in dots)  # the recurrence itself is still a loop
