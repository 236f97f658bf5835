"""A per-frame MLP conditioner with a zero-initialised head.

For an input x (..., T, F) and an optional context c (..., T, C) the network acts on each
frame independently:

    h_0 = [x_t, c_t]                      (channel concatenation; c only if context_features)
    h_k = act(h_{k-1} W_k + b_k)          k = 1..depth, ``hidden`` units
    out = h_depth W_out + b_out           W_out = 0, b_out = 0 at initialisation

so a coupling layer built on it starts as a fixed per-channel map. The call signature
``mlp(x, context)`` is the coupling-conditioner interface of ``motionflows.bijectors``.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
from flax import nnx

from motionflows.bijectors.coupling import coupling_sizes

Array = jax.Array

__all__ = ["MLP", "coupling_mlp"]


class MLP(nnx.Module):
    """Per-frame MLP (..., T, in_features) [+ context (..., T, context_features)] -> (..., T, out).

    Args:
      in_features: channels of x.
      out_features: channels of the output.
      hidden: width of each hidden layer.
      depth: number of hidden layers (>= 0; 0 gives a single zero-initialised linear map).
      context_features: channels of the context; 0 means the context is ignored.
      activation: hidden non-linearity (default ``jax.nn.relu``).
      zero_init: start the output layer at exactly zero (default True).
      rngs: ``nnx.Rngs`` for the hidden layers' initialisation.
    """

    def __init__(
        self,
        in_features: int,
        out_features: int,
        *,
        hidden: int = 64,
        depth: int = 2,
        context_features: int = 0,
        activation: Callable[[Array], Array] = jax.nn.relu,
        zero_init: bool = True,
        rngs: nnx.Rngs,
    ):
        if int(depth) < 0 or int(hidden) < 1 or int(out_features) < 1:
            raise ValueError(
                f"MLP needs depth >= 0, hidden >= 1, out_features >= 1; got depth={depth}, "
                f"hidden={hidden}, out_features={out_features}"
            )
        self.in_features = int(in_features)
        self.out_features = int(out_features)
        self.context_features = int(context_features)
        self.activation = activation
        width = self.in_features + self.context_features
        layers = []
        for _ in range(int(depth)):
            layers.append(nnx.Linear(width, int(hidden), rngs=rngs))
            width = int(hidden)
        self.hidden_layers = nnx.List(layers)
        init = nnx.initializers.zeros_init() if zero_init else nnx.initializers.lecun_normal()
        self.head = nnx.Linear(width, self.out_features, kernel_init=init, rngs=rngs)

    def __call__(self, x: Array, context: Array | None = None) -> Array:
        if x.ndim < 1 or x.shape[-1] != self.in_features:
            raise ValueError(
                f"MLP expects (..., {self.in_features}) inputs, got shape {tuple(x.shape)}"
            )
        h = x
        if self.context_features:
            if context is None:
                raise ValueError(
                    f"this MLP was built with context_features={self.context_features}; "
                    f"pass a context (..., T, {self.context_features})"
                )
            if context.shape[-1] != self.context_features:
                raise ValueError(
                    f"MLP expects context (..., {self.context_features}), got shape "
                    f"{tuple(context.shape)}"
                )
            batch = jnp.broadcast_shapes(x.shape[:-1], context.shape[:-1])
            h = jnp.concatenate(
                [
                    jnp.broadcast_to(x, batch + x.shape[-1:]),
                    jnp.broadcast_to(context, batch + context.shape[-1:]).astype(x.dtype),
                ],
                axis=-1,
            )
        for layer in self.hidden_layers:
            h = self.activation(layer(h))
        return self.head(h)


def coupling_mlp(
    num_channels: int,
    *,
    context_features: int = 0,
    hidden: int = 64,
    depth: int = 2,
    additive: bool = False,
    rngs: nnx.Rngs,
) -> MLP:
    """An :class:`MLP` sized as the conditioner of a coupling over ``num_channels`` channels.

    Input floor(D/2) channels (+ context), output 2 * (D - floor(D/2)) for
    ``AffineCoupling`` or D - floor(D/2) for ``AdditiveCoupling`` (``additive=True``).
    """
    na, nb = coupling_sizes(num_channels)
    return MLP(
        na,
        nb if additive else 2 * nb,
        hidden=hidden,
        depth=depth,
        context_features=context_features,
        rngs=rngs,
    )
