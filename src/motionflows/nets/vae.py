"""Convolutional blocks of the VAE-LSTM (Habibie et al., BMVC 2017): temporal encoders with
max-pooling, and the upsampling decoder.

All arrays are channels last, ``(B, T, C)``. A "conv" is a 1-D convolution over time with
``SAME`` zero padding, so it keeps the length. Pooling and unpooling act on time only.

Shapes through the default model at frame count ``T`` (``T`` divisible by 4)::

    control encoder   (B, T, 3)   -drop-> conv k 3->64, ELU, pool2 -drop-> conv k 64->128,
                                   ELU, pool2                      -> h (B, T/4, 128)
    pose encoder      (B, T, 63)  -drop-> conv k 63->64, ELU, pool2 -drop-> conv k 64->256,
                                   ELU, pool2 (-> linear head)     -> (mu, log_sigma) (B, T/4, 128)
    decoder           (B, T/4, 128) -> up2 -> conv k 128->128, ELU -> up2 -> conv k 128->63
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import nnx


def kernel_for_fps(fps: float, *, kernel_at_60: int = 25) -> int:
    """The temporal kernel width at ``fps``: the paper's 25 frames at 60 fps (about 0.4 s),
    scaled with the frame rate and rounded to the nearest odd integer (odd keeps ``SAME``
    padding symmetric), at least 3.

    ``kernel_for_fps(60) == 25``, ``kernel_for_fps(30) == 13``, ``kernel_for_fps(20) == 9``.
    """
    if not fps > 0:
        raise ValueError(f"fps must be positive, got {fps!r}")
    scaled = kernel_at_60 * float(fps) / 60.0
    return max(3, 2 * int(round((scaled - 1.0) / 2.0)) + 1)


def dropout(x: jax.Array, rate: float, key: jax.Array | None) -> jax.Array:
    """Inverted dropout with an explicit key: zero each entry with probability ``rate`` and
    scale the rest by ``1 / (1 - rate)``. ``key=None`` (evaluation) or ``rate == 0`` is the
    identity."""
    if key is None or rate <= 0.0:
        return x
    keep = jax.random.bernoulli(key, 1.0 - rate, x.shape)
    return jnp.where(keep, x / (1.0 - rate), 0.0).astype(x.dtype)


def max_pool2(x: jax.Array) -> jax.Array:
    """Max over non-overlapping pairs of time steps: (B, T, C) -> (B, T/2, C)."""
    b, t, c = x.shape
    return x.reshape(b, t // 2, 2, c).max(axis=2)


def upsample2(x: jax.Array) -> jax.Array:
    """Deterministic nearest-neighbour upsampling: (B, T, C) -> (B, 2T, C), each step twice."""
    return jnp.repeat(x, 2, axis=1)


def random_unpool2(x: jax.Array, key: jax.Array, *, per_example: bool = True) -> jax.Array:
    """The authors' random unpooling: each value goes to one of its two output steps, chosen
    at random, and the other step gets zero. (B, T, C) -> (B, 2T, C).

    ``per_example=False`` draws one (T, C) mask shared by the batch (used with a fixed key
    at evaluation, so evaluation is deterministic).
    """
    b, t, c = x.shape
    shape = (b, t, c) if per_example else (1, t, c)
    first = jax.random.bernoulli(key, 0.5, shape)
    zeros = jnp.zeros_like(x)
    pair = jnp.stack([jnp.where(first, x, zeros), jnp.where(first, zeros, x)], axis=2)
    return pair.reshape(b, 2 * t, c)


def _conv(cin: int, cout: int, kernel: int, rngs: nnx.Rngs) -> nnx.Conv:
    return nnx.Conv(cin, cout, kernel_size=(kernel,), padding="SAME", rngs=rngs)


class ConvEncoder(nnx.Module):
    """Two blocks of [dropout -> conv over time -> ELU -> max-pool 2]: (B, T, cin) ->
    (B, T/4, cout). Dropout (rate ``dropout``) acts on each block's input when a key is
    given."""

    def __init__(
        self, cin: int, hidden: int, cout: int, kernel: int, *, dropout: float, rngs: nnx.Rngs
    ):
        self.conv1 = _conv(cin, hidden, kernel, rngs)
        self.conv2 = _conv(hidden, cout, kernel, rngs)
        self.rate = float(dropout)

    def __call__(self, x: jax.Array, key: jax.Array | None = None) -> jax.Array:
        k1, k2 = (None, None) if key is None else tuple(jax.random.split(key))
        y = max_pool2(jax.nn.elu(self.conv1(dropout(x, self.rate, k1))))
        return max_pool2(jax.nn.elu(self.conv2(dropout(y, self.rate, k2))))


class ConvDecoder(nnx.Module):
    """Canvas (B, N, cin) -> output (B, 4N, cout): up2 -> conv -> ELU -> up2 -> conv.

    ``random_unpool=True`` replaces both up2 by :func:`random_unpool2`; it then needs a key
    (training draws a fresh mask per example; evaluation passes ``fixed_key`` for one
    mask shared by the batch).
    """

    def __init__(
        self,
        cin: int,
        hidden: int,
        cout: int,
        kernel: int,
        *,
        random_unpool: bool = False,
        rngs: nnx.Rngs,
    ):
        self.conv1 = _conv(cin, hidden, kernel, rngs)
        self.conv2 = _conv(hidden, cout, kernel, rngs)
        self.random_unpool = bool(random_unpool)

    def _up(self, x, key, per_example):
        if not self.random_unpool:
            return upsample2(x)
        return random_unpool2(x, key, per_example=per_example)

    def __call__(self, canvas: jax.Array, key: jax.Array | None = None) -> jax.Array:
        per_example = key is not None
        if key is None:
            key = jax.random.key(1234)  # the fixed evaluation mask (faithful mode only)
        k1, k2 = jax.random.split(key)
        y = jax.nn.elu(self.conv1(self._up(canvas, k1, per_example)))
        return self.conv2(self._up(y, k2, per_example))
