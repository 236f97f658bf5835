"""First differences over time: flow the change of a sequence instead of its values."""

from __future__ import annotations

from collections.abc import Callable

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

    ``move(x_prev, context_t) -> (..., D)``, optional: the change is taken from the previous
    frame *moved* by the frame's context, u_t = x_t - move(x_{t-1}, context_t) (MoGlow's
    ``residual_world`` moves the previous pose into the current root frame, so a joint at
    rest in the world has u_t = 0). Any function of x_{t-1} and the context keeps the
    Jacobian unit triangular: log|det| = 0. The latent -> data sequence pass is then a
    ``lax.scan`` over frames instead of a cumulative sum.

    ``decay`` a in (0, 1], optional: u_t = x_t - a * x_{t-1} (a leaky difference; log|det|
    still 0). Summed back, x_t = sum_k a^(t-k) u_k, so an error in one u_k fades with time
    constant 1 / (1 - a) frames instead of staying in every later frame.
    """

    frame_constant_log_det = True  # the same log-det on every frame

    def __init__(
        self,
        num_channels: int,
        move: Callable[[Array, Array], Array] | None = None,
        *,
        decay: float = 1.0,
    ):
        if int(num_channels) < 1:
            raise ValueError(f"Difference needs num_channels >= 1, got {num_channels}")
        if move is not None and not callable(move):
            raise ValueError(f"Difference: move must be callable, got {type(move).__name__}")
        if not 0.0 < float(decay) <= 1.0:
            raise ValueError(f"Difference needs 0 < decay <= 1, got {decay}")
        self.num_channels = int(num_channels)
        self.move = move
        self.decay = float(decay)

    def _require_context(self, context: Array | None) -> Array:
        if context is None:
            raise ValueError(
                "Difference with move needs the context of each frame (context (..., T, C) "
                "for a sequence, context_t (..., C) for a frame step)"
            )
        return context

    def _moved(self, previous: Array, context: Array | None) -> Array:
        if self.move is not None:
            previous = self.move(previous, self._require_context(context))
        return previous if self.decay == 1.0 else self.decay * previous

    def _zero(self, x: Array) -> Array:
        return jnp.zeros(x.shape[:-2], jnp.float32)

    def inverse_and_log_det(self, y, *, context=None):
        check_event(y, self.num_channels, "Difference")
        previous = jnp.concatenate([jnp.zeros_like(y[..., :1, :]), y[..., :-1, :]], axis=-2)
        return y - self._moved(previous, context), self._zero(y)

    def forward_and_log_det(self, x, *, context=None):
        check_event(x, self.num_channels, "Difference")
        if self.move is None and self.decay == 1.0:
            return jnp.cumsum(x, axis=-2), self._zero(x)
        if self.move is not None:
            context = self._require_context(context)
        elif context is None:
            context = jnp.zeros(x.shape[:-1] + (0,), x.dtype)  # nothing to move by

        def body(previous, inputs):
            u_t, c_t = inputs
            y_t = u_t + self._moved(previous, c_t)
            return y_t, y_t

        frames_first = (jnp.moveaxis(x, -2, 0), jnp.moveaxis(context, -2, 0))
        _, y = jax.lax.scan(body, jnp.zeros_like(x[..., 0, :]), frames_first)
        return jnp.moveaxis(y, 0, -2), self._zero(x)

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
        previous = self._moved(self._check(y_t, carry), context_t)
        return y_t - previous, jnp.zeros(y_t.shape[:-1], jnp.float32), y_t

    def forward_step(self, x_t, *, context_t=None, carry=None):
        y_t = x_t + self._moved(self._check(x_t, carry), context_t)
        return y_t, jnp.zeros(x_t.shape[:-1], jnp.float32), y_t
