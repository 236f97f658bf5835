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
``compute_dtype`` (e.g. ``"bfloat16"``) runs the matmuls in that dtype with float32
accumulation (``preferred_element_type=float32``); the cell state, gates' nonlinearities and
outputs stay float32.

Carry: a tuple with one ``(h, c)`` pair per layer, each of shape (*batch, hidden), float32.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from flax import nnx

Array = jax.Array
Carry = tuple[tuple[Array, Array], ...]

__all__ = ["LSTM", "LSTMLayer", "matmul"]


def matmul(x: Array, w: Array, compute_dtype: str | None = None) -> Array:
    """``x @ w`` in float32, or in ``compute_dtype`` with float32 accumulation."""
    if compute_dtype is None:
        return jnp.matmul(x, w)
    cd = jnp.dtype(compute_dtype)
    return jnp.matmul(x.astype(cd), w.astype(cd), preferred_element_type=jnp.float32)


def _cell(gates: Array, c: Array) -> tuple[Array, Array]:
    """Gate pre-activations (..., 4H) in order i, f, g, o and cell c -> (h', c')."""
    i, f, g, o = jnp.split(gates, 4, axis=-1)
    c = jax.nn.sigmoid(f) * c + jax.nn.sigmoid(i) * jnp.tanh(g)
    h = jax.nn.sigmoid(o) * jnp.tanh(c)
    return h, c


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

    def input_projection(self, x: Array) -> Array:
        """``x @ W_ih + b_ih + b_hh`` for any leading shape: (..., in) -> (..., 4H) float32."""
        return matmul(x, self.w_ih[...], self.compute_dtype) + (self.b_ih[...] + self.b_hh[...])

    def scan_projected(self, gx: Array, carry: tuple[Array, Array]):
        """Run the recurrence over time-major projected inputs ``gx`` (T, ..., 4H).

        Returns (outputs (T, ..., H), final carry).
        """
        cd = self.compute_dtype
        w_hh = self.w_hh[...]
        if cd is not None:
            w_hh = w_hh.astype(cd)  # cast once, outside the time loop

        def body(state, g_x):
            h, c = state
            if cd is None:
                g = g_x + h @ w_hh
            else:
                g = g_x + jnp.matmul(h.astype(cd), w_hh, preferred_element_type=jnp.float32)
            h, c = _cell(g, c)
            return (h, c), h

        carry, ys = jax.lax.scan(body, carry, gx)
        return ys, carry

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

    def _check(self, x: Array, min_ndim: int) -> None:
        if x.ndim < min_ndim or x.shape[-1] != self.in_features:
            raise ValueError(
                f"LSTM expects input (..., {'T, ' if min_ndim == 2 else ''}{self.in_features}),"
                f" got shape {tuple(x.shape)}"
            )

    def __call__(self, x: Array, carry: Carry | None = None) -> tuple[Array, Carry]:
        self._check(x, 2)
        batch_shape = x.shape[:-2]
        if carry is None:
            carry = self.initial_carry(batch_shape)
        # Time-major once; every layer then works on (T, ..., features).
        h = jnp.moveaxis(x, -2, 0)
        new_carry = []
        for layer, state in zip(self.layers, carry, strict=True):
            h, state = layer.scan_projected(layer.input_projection(h), state)
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
