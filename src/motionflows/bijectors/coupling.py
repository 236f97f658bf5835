"""Affine and additive coupling layers, and the coupling maths as small public functions.

Channels of an event (..., T, D) are split into a = the first floor(D/2) channels and
b = the remaining D - floor(D/2). A conditioner network sees the whole sequence x_a
(..., T, |a|) and the context, so sequence conditioners (convolutions or LSTMs over time)
work as well as per-frame MLPs:

    h = conditioner(x_a, context)                      # (..., T, 2|b|)   (|b| for additive)
    shift = h[..., 0::2],  scale = sigmoid(h[..., 1::2] + 2) + eps
    data -> latent:   z_b = (x_b + shift) * scale,      log|det dz/dx| = sum_{t,d} log scale
    latent -> data:   x_b = z_b / scale - shift,        log|det dx/dz| = -sum_{t,d} log scale

x_a passes through unchanged. With a zero-initialised last conditioner layer a fresh
step is a fixed per-channel scaling (h = 0: shift = 0, scale = sigmoid(2)).

Frame steps (``forward_step`` / ``inverse_step``, see :mod:`motionflows.bijectors.base`) use
the conditioner's own step when it has one, ``conditioner.step(x_a_t, context_t, carry) ->
(h_t, carry)`` with ``conditioner.initial_carry(batch_shape)`` (a recurrent net's state is the
coupling's carry); a conditioner without ``step`` is taken to be per-frame (h_t a function of
x_a_t and context_t alone, as an MLP) and is called on the one-frame sequence.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp

from motionflows.bijectors.base import (
    Bijector,
    _check_context,
    _one_frame,
    check_event,
    check_frame,
)

Array = jax.Array

__all__ = [
    "AdditiveCoupling",
    "AffineCoupling",
    "affine_params",
    "affine_to_data",
    "affine_to_latent",
    "coupling_sizes",
    "merge_halves",
    "split_halves",
]

DEFAULT_EPS = 1e-6


def coupling_sizes(num_channels: int) -> tuple[int, int]:
    """(|a|, |b|) = (floor(D/2), D - floor(D/2)): conditioning and transformed channels."""
    d = int(num_channels)
    return d // 2, d - d // 2


def split_halves(x: Array) -> tuple[Array, Array]:
    """(x_a, x_b): the first floor(D/2) channels and the rest."""
    na = x.shape[-1] // 2
    return x[..., :na], x[..., na:]


def merge_halves(x_a: Array, x_b: Array) -> Array:
    """Inverse of :func:`split_halves`: concatenation on the channel axis."""
    return jnp.concatenate([x_a, x_b], axis=-1)


def affine_params(h: Array, eps: float = DEFAULT_EPS) -> tuple[Array, Array]:
    """Conditioner output h (..., 2n) -> (shift, scale), each (..., n).

    Even entries are the shift, odd ones the raw scale: scale = sigmoid(raw + 2) + eps,
    so scale lies in (eps, 1 + eps).
    """
    if h.shape[-1] % 2:
        raise ValueError(
            f"affine_params expects an even number of conditioner outputs (..., 2n), "
            f"got shape {tuple(h.shape)}"
        )
    shift = h[..., 0::2]
    scale = jax.nn.sigmoid(h[..., 1::2] + 2.0) + eps
    return shift, scale


def affine_to_latent(x_b: Array, shift: Array, scale: Array) -> tuple[Array, Array]:
    """data -> latent: z_b = (x_b + shift) * scale; also log|det| per frame (...,) = sum log scale.

    The log-det sums over the last (channel) axis only, so for (..., T, n) inputs it is
    (..., T): sum it over time for a sequence.
    """
    z_b = (x_b + shift) * scale
    return z_b, jnp.sum(jnp.log(jnp.broadcast_to(scale, z_b.shape)), axis=-1)


def affine_to_data(z_b: Array, shift: Array, scale: Array) -> tuple[Array, Array]:
    """latent -> data: x_b = z_b / scale - shift; also log|det| per frame = -sum log scale."""
    x_b = z_b / scale - shift
    return x_b, -jnp.sum(jnp.log(jnp.broadcast_to(scale, x_b.shape)), axis=-1)


class _Coupling(Bijector):
    """Shared plumbing: validation and calling the conditioner."""

    _name = "Coupling"
    _outputs_per_channel = 2

    def __init__(self, num_channels: int, conditioner: Callable[..., Array]):
        d = int(num_channels)
        if d < 2:
            raise ValueError(f"{self._name} needs num_channels >= 2 (to split), got {d}")
        if not callable(conditioner):
            raise ValueError(
                f"{self._name} needs a callable conditioner(x_a, context), "
                f"got {type(conditioner).__name__}"
            )
        self.num_channels = d
        self.conditioner = conditioner

    def _condition(self, x: Array, context: Array | None) -> tuple[Array, Array, Array]:
        check_event(x, self.num_channels, self._name)
        _check_context(context, x, self._name)
        x_a, x_b = split_halves(x)
        h = self.conditioner(x_a, context)
        want = self._outputs_per_channel * x_b.shape[-1]
        if h.ndim < 2 or h.shape[-1] != want or h.shape[-2] != x.shape[-2]:
            raise ValueError(
                f"{self._name} conditioner must return (..., T, {want}) = "
                f"(..., {x.shape[-2]}, {self._outputs_per_channel} * {x_b.shape[-1]}) for x_a "
                f"of shape {tuple(x_a.shape)}, got {tuple(h.shape)}"
            )
        h = jnp.broadcast_to(h, x_b.shape[:-1] + (want,))
        return x_a, x_b, h

    def initial_carry(self, batch_shape=()):
        """The conditioner's initial carry (``conditioner.initial_carry``), else ()."""
        init = getattr(self.conditioner, "initial_carry", None)
        return () if init is None else init(tuple(batch_shape))

    def _condition_step(self, x_t: Array, context_t: Array | None, carry):
        """One frame: (x_a_t, x_b_t, h_t, carry), h_t from the conditioner (step or per-frame)."""
        check_frame(x_t, self._name)
        if x_t.shape[-1] != self.num_channels:
            raise ValueError(
                f"{self._name} expects frames (..., {self.num_channels}), got {tuple(x_t.shape)}"
            )
        if carry is None:
            carry = self.initial_carry(x_t.shape[:-1])
        x_a, x_b = split_halves(x_t)
        step = getattr(self.conditioner, "step", None)
        if step is None:
            h = self.conditioner(_one_frame(x_a), _one_frame(context_t))[..., 0, :]
        else:
            h, carry = step(x_a, context_t, carry)
        want = self._outputs_per_channel * x_b.shape[-1]
        if h.shape[-1] != want:
            raise ValueError(
                f"{self._name} conditioner step must return (..., {want}) for x_a_t of shape "
                f"{tuple(x_a.shape)}, got {tuple(h.shape)}"
            )
        return x_a, x_b, jnp.broadcast_to(h, x_b.shape[:-1] + (want,)), carry


class AffineCoupling(_Coupling):
    """Affine coupling (Glow / RealNVP) over channel halves; see the module docstring.

    ``AffineCoupling(num_channels, conditioner, eps=1e-6)`` where
    ``conditioner(x_a, context) -> h`` maps (..., T, floor(D/2)) (and the context, or None)
    to (..., T, 2 * (D - floor(D/2))): even entries shift, odd entries raw scale. Any
    callable works (an nnx.Module holds trainable parameters); its last layer should start
    at zero (e.g. :func:`motionflows.nets.coupling_mlp`).

    data -> latent:  z_b = (x_b + shift) * scale,  scale = sigmoid(raw + 2) + eps,
                     log|det dz/dx| = sum over (T, |b|) of log scale.
    """

    _name = "AffineCoupling"
    _outputs_per_channel = 2

    def __init__(self, num_channels: int, conditioner: Callable[..., Array], *, eps=DEFAULT_EPS):
        super().__init__(num_channels, conditioner)
        self.eps = float(eps)

    def inverse_and_log_det(self, y, *, context=None):
        x_a, x_b, h = self._condition(y, context)
        shift, scale = affine_params(h, self.eps)
        z_b, ld = affine_to_latent(x_b, shift, scale)
        return merge_halves(x_a, z_b), jnp.sum(ld, axis=-1)

    def inverse_and_frame_log_det(self, y, *, context=None):
        x_a, x_b, h = self._condition(y, context)
        z_b, ld = affine_to_latent(x_b, *affine_params(h, self.eps))
        return merge_halves(x_a, z_b), ld

    def forward_and_log_det(self, x, *, context=None):
        z_a, z_b, h = self._condition(x, context)
        shift, scale = affine_params(h, self.eps)
        x_b, ld = affine_to_data(z_b, shift, scale)
        return merge_halves(z_a, x_b), jnp.sum(ld, axis=-1)

    def inverse_step(self, y_t, *, context_t=None, carry=None):
        x_a, x_b, h, carry = self._condition_step(y_t, context_t, carry)
        z_b, ld = affine_to_latent(x_b, *affine_params(h, self.eps))
        return merge_halves(x_a, z_b), ld, carry

    def forward_step(self, x_t, *, context_t=None, carry=None):
        z_a, z_b, h, carry = self._condition_step(x_t, context_t, carry)
        x_b, ld = affine_to_data(z_b, *affine_params(h, self.eps))
        return merge_halves(z_a, x_b), ld, carry


class AdditiveCoupling(_Coupling):
    """Additive (volume-preserving, NICE) coupling: z_b = x_b + shift, log-det 0.

    ``conditioner(x_a, context)`` returns the shift (..., T, D - floor(D/2)).
    """

    _name = "AdditiveCoupling"
    _outputs_per_channel = 1
    frame_constant_log_det = True

    def _zero(self, x: Array) -> Array:
        return jnp.zeros(x.shape[:-2], jnp.result_type(x.dtype, jnp.float32))

    def inverse_and_log_det(self, y, *, context=None):
        x_a, x_b, shift = self._condition(y, context)
        return merge_halves(x_a, x_b + shift), self._zero(y)

    def forward_and_log_det(self, x, *, context=None):
        z_a, z_b, shift = self._condition(x, context)
        return merge_halves(z_a, z_b - shift), self._zero(x)

    def inverse_step(self, y_t, *, context_t=None, carry=None):
        x_a, x_b, shift, carry = self._condition_step(y_t, context_t, carry)
        return merge_halves(x_a, x_b + shift), jnp.zeros(y_t.shape[:-1], jnp.float32), carry

    def forward_step(self, x_t, *, context_t=None, carry=None):
        z_a, z_b, shift, carry = self._condition_step(x_t, context_t, carry)
        return merge_halves(z_a, z_b - shift), jnp.zeros(x_t.shape[:-1], jnp.float32), carry
