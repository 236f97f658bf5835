"""Convolutional conditioner networks over time (the Glow coupling net).

:class:`ConvNet` is the coupling conditioner of the fixed-length Glow (MoGlow paper, Sec. 3;
Kingma & Dhariwal 2018): with ``h = [x_a, c]`` the channel-wise concatenation of the
coupling's conditioning half and the (optional) context, both shaped (..., T, C),

    h1 = relu(conv_3(h))          kernel 3 over time, ``hidden`` channels
    h2 = relu(conv_1(h1))         kernel 1 (a per-frame dense layer), ``hidden`` channels
    out = conv_3^0(h2)            kernel 3, ``out_features`` channels, zero-initialised

All convolutions use 'SAME' (zero) padding along time, so T is preserved and each output
frame sees a 5-frame receptive field of its input (3 + 1 + 3 kernels). The last layer starts
at exactly zero so a freshly built coupling is the identity map up to its fixed scale.

Precision: parameters are float32. With ``compute_dtype=jnp.bfloat16`` the inputs and
kernels are cast to bfloat16 for each convolution, products are accumulated in float32
(``preferred_element_type``), in the backward pass too (:func:`motionflows.nets.precision.
matmul`; reverse mode only), biases and ReLUs run in float32, and the output is always
float32, so the flow's affine maps and log-dets stay float32 (DESIGN.md "Precision").
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from flax import nnx

from motionflows.nets.precision import matmul

__all__ = ["ConvNet", "TimeConv"]


class TimeConv(nnx.Module):
    """A 1-D convolution over time on (..., T, C_in) -> (..., T, C_out), 'SAME' padding.

    y[..., t, o] = b[o] + sum_{k, i} W[k, i, o] x[..., t + k - (K - 1) // 2, i], with x = 0
    outside [0, T). ``compute_dtype`` casts x and W for the product and accumulates in
    float32; the result is float32.

    Implemented as one matmul of the K time-shifted copies of x, concatenated along channels
    (T, K * C_in), with W reshaped to (K * C_in, C_out): the same sum, but XLA:CPU runs it
    ~15x faster than ``lax.conv_general_dilated`` when differentiated inside a ``lax.scan``
    (the flow steps of a level are a ``Scan``).
    """

    def __init__(
        self,
        in_features: int,
        out_features: int,
        kernel_size: int,
        *,
        zero_init: bool = False,
        compute_dtype: Any = None,
        rngs: nnx.Rngs,
    ):
        if kernel_size < 1 or kernel_size % 2 == 0:
            raise ValueError(f"TimeConv: kernel_size must be odd and >= 1, got {kernel_size}")
        self.in_features = int(in_features)
        self.out_features = int(out_features)
        self.kernel_size = int(kernel_size)
        self.compute_dtype = None if compute_dtype is None else jnp.dtype(compute_dtype).name
        shape = (self.kernel_size, self.in_features, self.out_features)
        if zero_init:
            kernel = jnp.zeros(shape, jnp.float32)
        else:
            kernel = jax.nn.initializers.lecun_normal(in_axis=(0, 1), out_axis=2)(
                rngs.params(), shape, jnp.float32
            )
        self.kernel = nnx.Param(kernel)
        self.bias = nnx.Param(jnp.zeros((self.out_features,), jnp.float32))

    def __call__(self, x: jax.Array) -> jax.Array:
        if x.ndim < 2 or x.shape[-1] != self.in_features:
            raise ValueError(
                f"TimeConv expects input (..., T, {self.in_features}), got shape {x.shape}"
            )
        lead = x.shape[:-2]
        t, c = x.shape[-2:]
        h = x.reshape((-1, t, c))
        k = self.kernel_size
        if k > 1:  # im2col: frames t-p .. t+p side by side, zeros outside [0, T)
            p = (k - 1) // 2
            padded = jnp.pad(h, ((0, 0), (p, p), (0, 0)))
            h = jnp.concatenate([padded[:, j : j + t] for j in range(k)], axis=-1)
        w = self.kernel[...].reshape(k * c, self.out_features)
        y = matmul(h, w, self.compute_dtype) + self.bias[...]
        return y.reshape(lead + (t, self.out_features))


class ConvNet(nnx.Module):
    """Glow coupling conditioner: conv3 -> ReLU -> conv1 -> ReLU -> zero-init conv3.

    Args:
      in_features: channels of x_a (the coupling's conditioning half).
      out_features: output channels (2 * |x_b| for an affine coupling).
      hidden: hidden width (512 in the MoGlow paper).
      context_features: channels of the context concatenated to x_a (0 = no context).
      compute_dtype: None (float32) or e.g. ``jnp.bfloat16`` for the convolutions.

    Call: ``net(x_a, context=None)`` with x_a (..., T, in_features) and context
    (..., T, context_features) -> (..., T, out_features) float32.
    """

    def __init__(
        self,
        in_features: int,
        out_features: int,
        hidden: int = 512,
        *,
        context_features: int = 0,
        kernel_size: int = 3,
        compute_dtype: Any = None,
        rngs: nnx.Rngs,
    ):
        self.in_features = int(in_features)
        self.context_features = int(context_features)
        self.out_features = int(out_features)
        total = self.in_features + self.context_features
        kw = dict(compute_dtype=compute_dtype, rngs=rngs)
        self.conv_in = TimeConv(total, hidden, kernel_size, **kw)
        self.conv_hidden = TimeConv(hidden, hidden, 1, **kw)
        self.conv_out = TimeConv(hidden, out_features, kernel_size, zero_init=True, **kw)

    def __call__(self, x_a: jax.Array, context: jax.Array | None = None) -> jax.Array:
        if self.context_features:
            if context is None:
                raise ValueError(
                    f"ConvNet was built with context_features={self.context_features} but was "
                    "called without a context: pass the (..., T, C) control/context array"
                )
            if context.shape[-1] != self.context_features or context.shape[-2] != x_a.shape[-2]:
                raise ValueError(
                    f"ConvNet: context must be (..., {x_a.shape[-2]}, {self.context_features}) "
                    f"to match x_a {x_a.shape}, got {context.shape}"
                )
            context = jnp.broadcast_to(context, x_a.shape[:-1] + context.shape[-1:])
            h = jnp.concatenate([x_a, context.astype(x_a.dtype)], axis=-1)
        else:
            h = x_a
        h = jax.nn.relu(self.conv_in(h))
        h = jax.nn.relu(self.conv_hidden(h))
        return self.conv_out(h)
