"""A stacked LSTM with the semantics of the common (cuDNN / PyTorch) LSTM, run by ``lax.scan``.

One layer, for an input frame ``x_t`` (in_features,) and state ``(h, c)`` (hidden,)::

    g   = x_t @ W_ih + b_ih + h @ W_hh + b_hh          # (4 * hidden,), gate order i, f, g, o
    i, f, o = sigmoid(g_i), sigmoid(g_f), sigmoid(g_o)  # no forget-bias offset
    c'  = f * c + i * tanh(g_g)
    h'  = o * tanh(c')                                  # the layer's output and new state

Layers are stacked: layer ``l + 1`` reads the outputs ``h`` of layer ``l``. Every weight and
bias starts uniform in ``[-1/sqrt(hidden), 1/sqrt(hidden)]`` (the usual default).

Storage is "inputs-first": ``w_ih`` has shape (in_features, 4H) and ``w_hh`` (H, 4H), i.e. the
transposes of PyTorch's ``weight_ih_l{k}`` / ``weight_hh_l{k}`` (4H, in); ``b_ih``/``b_hh``
are stored separately (as there) and summed when used.

Speed: :meth:`LSTM.__call__` computes each layer's input projection ``x @ W_ih + b`` for all
frames at once (one large matmul) and keeps only ``h @ W_hh`` inside the time scan.
``compute_dtype`` (e.g. ``"bfloat16"``) runs every matmul, forward and backward, in that
dtype with float32 accumulation (``preferred_element_type=float32``); the cell state, gates'
nonlinearities, outputs and gradients stay float32 (:func:`matmul` and :func:`recurrence`
carry their own backward passes so that autodiff does not fall back to float32 matmuls;
that mode supports reverse-mode autodiff only). In float32 the recurrence has a custom JVP
whose transpose keeps one matmul per frame in the reverse loop and forms dW_hh over all
frames at once (plain autodiff through ``lax.scan`` multiplies and accumulates a (H, 4H)
gradient every frame): its training step keeps 40 % fewer temporaries (paper MoGlow:
3.9 GB against 6.4 GB) and the quick preset trains ~15-20 % faster
(docs/readme/speed.md).

Carry: a tuple with one ``(h, c)`` pair per layer, each of shape (*batch, hidden), float32.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
from flax import nnx

from motionflows.nets.precision import matmul, outer_sum, product

Array = jax.Array
Carry = tuple[tuple[Array, Array], ...]

__all__ = ["LSTM", "LSTMLayer", "recurrence"]


def _gates(pre: Array) -> tuple[Array, Array, Array, Array]:
    """Pre-activations (..., 4H), order i, f, g, o -> (sigmoid i, sigmoid f, tanh g, sigmoid o)."""
    i, f, g, o = jnp.split(pre, 4, axis=-1)
    return jax.nn.sigmoid(i), jax.nn.sigmoid(f), jnp.tanh(g), jax.nn.sigmoid(o)


def _cell(gates: Array, c: Array) -> tuple[Array, Array]:
    """Gate pre-activations (..., 4H) in order i, f, g, o and cell c -> (h', c')."""
    h, c, _ = _cell_with_gates(gates, c)
    return h, c


def _cell_with_gates(pre: Array, c: Array) -> tuple[Array, Array, Array]:
    """As :func:`_cell`, also returning the activated gates [i, f, g, o] (..., 4H) that the
    backward passes read (so they need no sigmoid or tanh of their own but tanh(c))."""
    i, f, g, o = _gates(pre)
    c = f * c + i * g
    h = o * jnp.tanh(c)
    return h, c, jnp.concatenate([i, f, g, o], axis=-1)


def _recurrence_forward(gx, w_hh, carry, cd, residuals: bool = False):
    """Outputs hs (T, ..., H) and the final carry; with ``residuals`` also the stacked cell
    states cs and activated gates acts (T, ..., 4H) that the backward passes need."""
    w = w_hh if cd is None else w_hh.astype(cd)  # cast once, outside the time loop

    def body(state, g_x):
        h, c = state
        pre = g_x + product(h, w, cd)
        if not residuals:
            h, c = _cell(pre, c)
            return (h, c), h
        h, c, acts = _cell_with_gates(pre, c)
        return (h, c), (h, c, acts)

    carry, ys = jax.lax.scan(body, carry, gx)
    return (ys, carry) if not residuals else (ys[0], carry, ys[1], ys[2])


def recurrence(gx: Array, w_hh: Array, carry: tuple[Array, Array], compute_dtype=None):
    """The LSTM recurrence over time-major projected inputs gx (T, ..., 4H) (``x_t @ W_ih`` plus
    both biases) from state ``carry`` = (h, c) (..., H): returns (outputs h_1..h_T
    (T, ..., H), final (h, c)). One ``lax.scan``; ``compute_dtype`` as in :func:`matmul`.

    float32: a custom JVP (:func:`_recurrence_exact_jvp`), so forward and reverse mode both
    work and the reverse pass forms dW_hh in one matmul over all frames; the values are
    those of plain autodiff through the scan. With ``compute_dtype`` (bfloat16): a custom
    VJP, so that the backward matmuls also run in bfloat16 (autodiff would upcast them to
    float32) and dW_hh is accumulated in float32.
    Its reverse scan carries (dh, dc): dc_t += dh_t o (1 - tanh(c_t)^2), gate cotangents
    dg_t = [dc_t g i(1-i), dc_t c_{t-1} f(1-f), dc_t i (1-g^2), dh_t tanh(c_t) o(1-o)],
    dh_{t-1} = dg_t W_hh^T, dc_{t-1} = dc_t f; then dW_hh = sum_t h_{t-1}^T dg_t is one
    matmul over all frames (not T small ones inside the loop). Reverse mode only
    (``jax.grad``); use float32 for ``jax.jvp`` / ``jax.jacfwd``.
    """
    if compute_dtype is None:
        return _recurrence_exact(gx, w_hh, carry)
    return _recurrence_low(gx, w_hh, carry, jnp.dtype(compute_dtype).name)


def _previous(carry, hs, cs):
    """(h_{t-1}, c_{t-1}) for t = 1..T: the initial state, then the outputs shifted by one."""
    h_prev = jnp.concatenate([carry[0][None], hs[:-1]], axis=0)
    c_prev = jnp.concatenate([carry[1][None], cs[:-1]], axis=0)
    return h_prev, c_prev


@jax.custom_jvp
def _recurrence_exact(gx, w_hh, carry):
    return _recurrence_forward(gx, w_hh, carry, None)


@_recurrence_exact.defjvp
def _recurrence_exact_jvp(primals, tangents):
    """The float32 recurrence's tangent map, written so that its transpose is fast.

    With residuals h_{t-1}, c_{t-1}, c_t and the activated gates from one forward scan:
    a_t = dgx_t + h_{t-1} dW (one matmul over all frames, outside the loop), then the
    linear scan dpre_t = a_t + dh_{t-1} W, dc_t = df' c_{t-1} + f dc_{t-1} + di' g + i dg',
    dh_t = do' tanh(c_t) + o (1 - tanh^2 c_t) dc_t (primes: the gates' derivatives times
    the matching slice of dpre_t). Reverse mode transposes it: the loop carries only
    (dh, dc) and does one matmul per frame (dpre_t W^T); dW = sum_t h_{t-1}^T dpre_t becomes
    one matmul over all frames. The body is rematerialised (``jax.checkpoint``), so it
    stores nothing of its own: it reads the gates (no sigmoid or tanh but tanh(c_t)).
    """
    gx, w, carry = primals
    dgx, dw, (dh0, dc0) = tangents
    hs, final, cs, acts = _recurrence_forward(gx, w, carry, None, residuals=True)
    h_prev, c_prev = _previous(carry, hs, cs)
    a = dgx + jnp.matmul(h_prev, dw)

    @functools.partial(jax.checkpoint, prevent_cse=False)
    def body(state, inputs):
        dh, dc = state
        a_t, act, c_p, c = inputs
        i, f, g, o = jnp.split(act, 4, axis=-1)
        di, df, dg, do = jnp.split(a_t + jnp.matmul(dh, w), 4, axis=-1)
        dc = df * f * (1.0 - f) * c_p + f * dc + di * i * (1.0 - i) * g + i * (1.0 - g * g) * dg
        tc = jnp.tanh(c)
        dh = do * o * (1.0 - o) * tc + o * (1.0 - tc * tc) * dc
        return (dh, dc), dh

    (dh_last, dc_last), dhs = jax.lax.scan(body, (dh0, dc0), (a, acts, c_prev, cs))
    return (hs, final), (dhs, (dh_last, dc_last))


@functools.partial(jax.custom_vjp, nondiff_argnums=(3,))
def _recurrence_low(gx, w_hh, carry, cd):
    return _recurrence_forward(gx, w_hh, carry, cd)


def _recurrence_low_fwd(gx, w_hh, carry, cd):
    hs, final, cs, acts = _recurrence_forward(gx, w_hh, carry, cd, residuals=True)
    h_prev, c_prev = _previous(carry, hs, cs)
    return (hs, final), (w_hh, h_prev, c_prev, cs, acts)


def _recurrence_low_bwd(cd, res, cts):
    w_hh, h_prev, c_prev, cs, acts = res
    d_hs, (dh_last, dc_last) = cts
    w_t = w_hh.astype(cd).T

    def body(state, inputs):
        dh_next, dc_next = state
        d_h, c_p, c, act = inputs
        i, f, g, o = jnp.split(act, 4, axis=-1)
        dh = d_h + dh_next
        tc = jnp.tanh(c)
        dc = dc_next + dh * o * (1.0 - tc * tc)
        d_pre = jnp.concatenate(
            [
                dc * g * i * (1.0 - i),
                dc * c_p * f * (1.0 - f),
                dc * i * (1.0 - g * g),
                dh * tc * o * (1.0 - o),
            ],
            axis=-1,
        )
        return (product(d_pre, w_t, cd), dc * f), d_pre

    (dh0, dc0), d_pres = jax.lax.scan(
        body, (dh_last, dc_last), (d_hs, c_prev, cs, acts), reverse=True
    )
    d_w = outer_sum(h_prev, d_pres, cd).astype(w_hh.dtype)
    return d_pres, d_w, (dh0, dc0)


_recurrence_low.defvjp(_recurrence_low_fwd, _recurrence_low_bwd)


class LSTMLayer(nnx.Module):
    """One LSTM layer: parameters ``w_ih`` (in, 4H), ``w_hh`` (H, 4H), ``b_ih``, ``b_hh`` (4H,)."""

    def __init__(
        self,
        in_features: int,
        hidden: int,
        *,
        rngs: nnx.Rngs,
        compute_dtype: str | None = None,
    ):
        self.in_features = int(in_features)
        self.hidden = int(hidden)
        self.compute_dtype = None if compute_dtype is None else jnp.dtype(compute_dtype).name
        bound = 1.0 / math.sqrt(hidden)

        def uniform(shape):
            return jax.random.uniform(rngs.params(), shape, jnp.float32, -bound, bound)

        self.w_ih = nnx.Param(uniform((in_features, 4 * hidden)))
        self.w_hh = nnx.Param(uniform((hidden, 4 * hidden)))
        self.b_ih = nnx.Param(uniform((4 * hidden,)))
        self.b_hh = nnx.Param(uniform((4 * hidden,)))

    def initial_carry(self, batch_shape: tuple[int, ...] = ()) -> tuple[Array, Array]:
        """Zero state ``(h, c)``, each (*batch_shape, hidden) float32."""
        zeros = jnp.zeros((*batch_shape, self.hidden), jnp.float32)
        return zeros, zeros

    def input_projection(self, x: Array, context: Array | None = None) -> Array:
        """``x @ W_ih + b_ih + b_hh`` for any leading shape: (..., in) -> (..., 4H) float32.

        With ``context`` (..., c), the input is [x, context] (in = x's width + c), computed as
        ``x @ W_ih[:n] + context @ W_ih[n:]``: autodiff then forms no input gradient for a
        context that does not depend on what is differentiated.
        """
        w, b = self.w_ih[...], self.b_ih[...] + self.b_hh[...]
        if context is None:
            return matmul(x, w, self.compute_dtype) + b
        n = x.shape[-1]
        cd = self.compute_dtype
        return matmul(x, w[:n], cd) + matmul(context, w[n:], cd) + b

    def scan_projected(self, gx: Array, carry: tuple[Array, Array]):
        """Run the recurrence over time-major projected inputs ``gx`` (T, ..., 4H).

        Returns (outputs (T, ..., H), final carry). See :func:`recurrence`.
        """
        return recurrence(gx, self.w_hh[...], carry, self.compute_dtype)

    def step(self, x_t: Array, carry: tuple[Array, Array]):
        """One frame: x_t (..., in) -> (h' (..., H), (h', c'))."""
        h, c = carry
        g = self.input_projection(x_t) + matmul(h, self.w_hh[...], self.compute_dtype)
        h, c = _cell(g, c)
        return h, (h, c)


class LSTM(nnx.Module):
    """A stack of ``num_layers`` LSTM layers of ``hidden`` units (see the module docstring).

    ``lstm(x, carry=None) -> (y, carry)`` with x (..., T, in_features), y (..., T, hidden):
    the whole sequence by ``lax.scan`` over time (zero state when ``carry`` is None).
    ``lstm.step(x_t, carry) -> (y_t, carry)`` runs one frame x_t (..., in_features) and equals
    one iteration of the sequence call.
    """

    def __init__(
        self,
        in_features: int,
        hidden: int,
        num_layers: int = 1,
        *,
        rngs: nnx.Rngs,
        compute_dtype: str | None = None,
    ):
        if num_layers < 1 or hidden < 1 or in_features < 1:
            raise ValueError(
                f"LSTM needs in_features, hidden and num_layers >= 1, got "
                f"{in_features}, {hidden}, {num_layers}"
            )
        self.in_features = int(in_features)
        self.hidden = int(hidden)
        self.num_layers = int(num_layers)
        self.compute_dtype = None if compute_dtype is None else jnp.dtype(compute_dtype).name
        self.layers = nnx.List(
            [
                LSTMLayer(
                    in_features if k == 0 else hidden,
                    hidden,
                    rngs=rngs,
                    compute_dtype=compute_dtype,
                )
                for k in range(num_layers)
            ]
        )

    def initial_carry(self, batch_shape: tuple[int, ...] = ()) -> Carry:
        """Zero state: one ``(h, c)`` pair per layer, each (*batch_shape, hidden)."""
        return tuple(layer.initial_carry(batch_shape) for layer in self.layers)

    def _check(self, x: Array, min_ndim: int, extra: int = 0) -> None:
        if x.ndim < min_ndim or x.shape[-1] + extra != self.in_features:
            got = f"{tuple(x.shape)}" + (f" plus {extra} context features" if extra else "")
            raise ValueError(
                f"LSTM expects input (..., {'T, ' if min_ndim == 2 else ''}{self.in_features}),"
                f" got shape {got}"
            )

    def __call__(
        self, x: Array, carry: Carry | None = None, *, context: Array | None = None
    ) -> tuple[Array, Carry]:
        """``context`` (..., T, c): features appended to x's (the same as calling on the
        concatenation), projected separately (see :meth:`LSTMLayer.input_projection`)."""
        if context is not None and context.shape[:-1] != x.shape[:-1]:
            raise ValueError(
                f"LSTM: context {tuple(context.shape)} must share x's leading axes "
                f"{tuple(x.shape[:-1])}"
            )
        self._check(x, 2, 0 if context is None else context.shape[-1])
        batch_shape = x.shape[:-2]
        if carry is None:
            carry = self.initial_carry(batch_shape)
        # Time-major once; every layer then works on (T, ..., features).
        h = jnp.moveaxis(x, -2, 0)
        ctx = None if context is None else jnp.moveaxis(context, -2, 0)
        new_carry = []
        for layer, state in zip(self.layers, carry, strict=True):
            h, state = layer.scan_projected(layer.input_projection(h, ctx), state)
            ctx = None  # only the first layer reads the context
            new_carry.append(state)
        return jnp.moveaxis(h, 0, -2), tuple(new_carry)

    def step(self, x_t: Array, carry: Carry) -> tuple[Array, Carry]:
        self._check(x_t, 1)
        h = x_t
        new_carry = []
        for layer, state in zip(self.layers, carry, strict=True):
            h, state = layer.step(h, state)
            new_carry.append(state)
        return h, tuple(new_carry)
