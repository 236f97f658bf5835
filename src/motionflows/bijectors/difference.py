"""First differences over time: flow the change of a sequence instead of its values."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from motionflows.bijectors.base import Bijector, check_event, check_frame

Array = jax.Array

__all__ = ["Difference"]


class Difference(Bijector):
    """The change from one frame to the next, with a zero frame before frame 0.

    data -> latent (``inverse``):  u_t = x_t - x_{t-1}  (x_{-1} = 0),   log|det| = 0
    latent -> data (``forward``):  x_t = u_0 + ... + u_t (a cumulative sum), log|det| = 0

    (the Jacobian is unit lower block-triangular). Frame steps carry the previous data
    frame x_{t-1} (..., D), zero from ``initial_carry``; start a carry from a known frame
    instead (a seed history) by passing it as ``carry``. No parameters.
    """

    def __init__(self, num_channels: int):
        if int(num_channels) < 1:
            raise ValueError(f"Difference needs num_channels >= 1, got {num_channels}")
        self.num_channels = int(num_channels)

    def _zero(self, x: Array) -> Array:
        return jnp.zeros(x.shape[:-2], jnp.float32)

    def inverse_and_log_det(self, y, *, context=None):
        check_event(y, self.num_channels, "Difference")
        previous = jnp.concatenate([jnp.zeros_like(y[..., :1, :]), y[..., :-1, :]], axis=-2)
        return y - previous, self._zero(y)

    def forward_and_log_det(self, x, *, context=None):
        check_event(x, self.num_channels, "Difference")
        return jnp.cumsum(x, axis=-2), self._zero(x)

    def initial_carry(self, batch_shape=()):
        """The frame before frame 0: zeros (*batch_shape, D)."""
        return jnp.zeros((*batch_shape, self.num_channels), jnp.float32)

    def _check(self, u_t: Array, carry) -> Array:
        check_frame(u_t, "Difference")
        if u_t.shape[-1] != self.num_channels:
            raise ValueError(
                f"Difference expects frames (..., {self.num_channels}), got {tuple(u_t.shape)}"
            )
        return self.initial_carry(u_t.shape[:-1]) if carry is None else carry

    def inverse_step(self, y_t, *, context_t=None, carry=None):
        previous = self._check(y_t, carry)
        return y_t - previous, jnp.zeros(y_t.shape[:-1], jnp.float32), y_t

    def forward_step(self, x_t, *, context_t=None, carry=None):
        y_t = x_t + self._check(x_t, carry)
        return y_t, jnp.zeros(x_t.shape[:-1], jnp.float32), y_t
