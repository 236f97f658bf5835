"""MoGlow's coupling conditioners: the networks inside each affine coupling.

For a coupling that passes x_a (..., T, na) and a per-frame condition cond (..., T, C)
(the tau history poses and tau + 1 controls), a conditioner returns the coupling's
parameters h (..., T, out) frame by frame, causally:

* :class:`LSTMConditioner` (the official model): ``h_t = Linear(LSTM([x_a, cond])_t)``,
  the LSTM carrying its state along time;
* :class:`FeedForwardConditioner` (the Markov ablation): ``h_t = MLP([x_a_t, cond_t])``.

Both have zero-initialised heads (a coupling starts as a fixed per-channel map), a
``step(x_a_t, cond_t, carry) -> (h_t, carry)`` frame API with ``initial_carry(batch_shape)``,
and do their matmuls in ``compute_dtype`` with float32 accumulation
(:func:`motionflows.nets.precision.matmul`).

:class:`CondEmbedding` (MoGlow's ``cond_embedding``, not in the official model) maps cond_t
to fewer features once per frame, for all K couplings' conditioners to read.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from flax import nnx

from motionflows.nets.lstm import LSTM
from motionflows.nets.precision import matmul

Array = jax.Array

__all__ = ["CondEmbedding", "FeedForwardConditioner", "LSTMConditioner"]


class CondEmbedding(nnx.Module):
    """A linear map of the condition shared by all K couplings: e_t = cond_t @ W_embed.

    (..., cond) -> (..., width), no bias (each conditioner's first layer has its own).
    Coupling k's first layer then computes e_t @ V_k = cond_t @ (W_embed V_k): its weights on
    the condition are constrained to rank ``width``, in a row space all K steps share, and
    the (cond x 4H) product each coupling did per frame becomes one (cond x width) product
    per frame plus K (width x 4H) ones. ``W_embed`` (cond, width) starts uniform in
    +-1/sqrt(cond), as a first layer's weights do.
    """

    def __init__(
        self,
        in_features: int,
        width: int,
        *,
        compute_dtype: str | None = None,
        rngs: nnx.Rngs,
    ):
        bound = 1.0 / math.sqrt(in_features)
        self.compute_dtype = compute_dtype
        self.w_embed = nnx.Param(
            jax.random.uniform(rngs.params(), (in_features, width), minval=-bound, maxval=bound)
        )

    def __call__(self, cond: Array) -> Array:
        return matmul(cond, self.w_embed[...], self.compute_dtype)


class LSTMConditioner(nnx.Module):
    """The official MoGlow coupling net: ``Linear(LSTM([x_a, cond]))`` with a zero head.

    ``__call__(x_a (..., T, na), context (..., T, cond)) -> h (..., T, out)``: the LSTM runs
    over time from a zero state (causal). ``step(x_a_t, cond_t, carry) -> (h_t, carry)``
    runs one frame with an explicit carry (``initial_carry(batch_shape)``).
    Head: ``w_out`` (hidden, out), ``b_out`` (out,), both zero at initialisation.
    """

    def __init__(
        self,
        in_features: int,
        context_features: int,
        out_features: int,
        *,
        hidden: int = 512,
        num_layers: int = 2,
        compute_dtype: str | None = None,
        rngs: nnx.Rngs,
    ):
        self.in_features = int(in_features)
        self.context_features = int(context_features)
        self.compute_dtype = compute_dtype
        self.lstm = LSTM(
            in_features + context_features,
            hidden,
            num_layers,
            rngs=rngs,
            compute_dtype=compute_dtype,
        )
        self.w_out = nnx.Param(jnp.zeros((hidden, out_features), jnp.float32))
        self.b_out = nnx.Param(jnp.zeros((out_features,), jnp.float32))

    def initial_carry(self, batch_shape: tuple[int, ...] = ()):
        return self.lstm.initial_carry(batch_shape)

    def _head(self, y: Array) -> Array:
        return matmul(y, self.w_out[...], self.compute_dtype) + self.b_out[...]

    def __call__(self, x_a: Array, context: Array) -> Array:
        y, _ = self.lstm(x_a, context=context)  # = on [x_a, context], no d/d context
        return self._head(y)

    def step(self, x_a: Array, context: Array, carry):
        y, carry = self.lstm.step(jnp.concatenate([x_a, context], axis=-1), carry)
        return self._head(y), carry


class FeedForwardConditioner(nnx.Module):
    """The Markov ablation: a per-frame MLP on [x_a, cond_t] (ReLU, zero head), no state.

    Same interface as :class:`LSTMConditioner`; its carry is the empty tuple.
    """

    def __init__(
        self,
        in_features: int,
        context_features: int,
        out_features: int,
        *,
        hidden: int = 512,
        num_layers: int = 2,
        compute_dtype: str | None = None,
        rngs: nnx.Rngs,
    ):
        self.compute_dtype = compute_dtype
        sizes = [in_features + context_features] + [hidden] * num_layers
        ws, bs = [], []
        for fan_in, fan_out in zip(sizes[:-1], sizes[1:], strict=True):
            bound = 1.0 / math.sqrt(fan_in)
            ws.append(
                nnx.Param(
                    jax.random.uniform(
                        rngs.params(), (fan_in, fan_out), minval=-bound, maxval=bound
                    )
                )
            )
            bs.append(nnx.Param(jnp.zeros((fan_out,), jnp.float32)))
        self.ws = nnx.List(ws)
        self.bs = nnx.List(bs)
        self.w_out = nnx.Param(jnp.zeros((sizes[-1], out_features), jnp.float32))
        self.b_out = nnx.Param(jnp.zeros((out_features,), jnp.float32))

    def initial_carry(self, batch_shape: tuple[int, ...] = ()):
        return ()

    def __call__(self, x_a: Array, context: Array) -> Array:
        h = jnp.concatenate([x_a, context], axis=-1)
        for w, b in zip(self.ws, self.bs, strict=True):
            h = jax.nn.relu(matmul(h, w[...], self.compute_dtype) + b[...])
        return matmul(h, self.w_out[...], self.compute_dtype) + self.b_out[...]

    def step(self, x_a: Array, context: Array, carry):
        return self(x_a, context), carry
