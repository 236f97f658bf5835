"""Reshaping bijectors for multi-scale flows: time ``Squeeze`` and the channel ``Split``.

Squeeze (data -> latent), factor f (default 2), interleave order:

    (..., T, D) -> (..., T / f, f * D),   out[..., t, :] = concat(x[f t], x[f t + 1], ...)

i.e. the f consecutive frames of each group are concatenated frame by frame (a plain
reshape; channel k of frame f t + j lands at channel j * D + k). Zero log-det.

Split (the multi-scale factor-out): of D channels the first ``D - D // 2`` (= ceil(D/2))
are kept and flow on; the last ``D // 2`` are factored out to a base density.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import nnx

from motionflows.bijectors.base import Bijector, check_event

Array = jax.Array

__all__ = ["Split", "Squeeze", "squeeze_time", "unsqueeze_time"]


def squeeze_time(x: Array, factor: int = 2) -> Array:
    """(..., T, D) -> (..., T / factor, factor * D); out[t] = concat(x[f t], ..., x[f t + f - 1]).

    Raises ``ValueError`` when T is not divisible by ``factor``. Works for contexts too.
    """
    check_event(x, None, "squeeze_time")
    t, d = x.shape[-2], x.shape[-1]
    if t % factor:
        raise ValueError(
            f"squeeze over time by {factor} needs T divisible by {factor}, got T = {t} "
            f"(shape {tuple(x.shape)}); crop or pad the sequence to a multiple of {factor}"
        )
    return jnp.reshape(x, x.shape[:-2] + (t // factor, factor * d))


def unsqueeze_time(x: Array, factor: int = 2) -> Array:
    """Inverse of :func:`squeeze_time`: (..., T', f * D) -> (..., f * T', D)."""
    check_event(x, None, "unsqueeze_time")
    t, d = x.shape[-2], x.shape[-1]
    if d % factor:
        raise ValueError(
            f"unsqueeze over time by {factor} needs D divisible by {factor}, got D = {d} "
            f"(shape {tuple(x.shape)})"
        )
    return jnp.reshape(x, x.shape[:-2] + (t * factor, d // factor))


class Squeeze(Bijector):
    """Time squeeze by ``factor`` (default 2), zero log-det; see the module docstring.

    data -> latent (``inverse``): (..., T, D) -> (..., T / f, f D) (``squeeze_time``);
    latent -> data (``forward``): (..., T', f D) -> (..., f T', D) (``unsqueeze_time``).
    The context is not touched: squeeze it yourself (``squeeze_time(c)``) for later layers.
    """

    def __init__(self, factor: int = 2):
        if int(factor) < 1:
            raise ValueError(f"Squeeze needs factor >= 1, got {factor}")
        self.factor = int(factor)

    def inverse_and_log_det(self, y, *, context=None):
        z = squeeze_time(y, self.factor)
        return z, jnp.zeros(y.shape[:-2], jnp.result_type(y.dtype, jnp.float32))

    def forward_and_log_det(self, x, *, context=None):
        y = unsqueeze_time(x, self.factor)
        return y, jnp.zeros(x.shape[:-2], jnp.result_type(x.dtype, jnp.float32))

    def _no_step(self, *args, **kwargs):
        raise ValueError(
            "Squeeze groups frames over time, so it has no per-frame step (forward_step / "
            "inverse_step); run the sequence maps (forward / inverse) on whole sequences"
        )

    forward_step = inverse_step = _no_step


class Split(nnx.Module):
    """Multi-scale factor-out on the channel axis of (..., T, D) (no parameters).

    ``split(x) -> (kept, factored)``: kept = x[..., :D - D // 2] (the first ceil(D/2)
    channels, which continue through the next flow level), factored = x[..., D - D // 2:]
    (the last floor(D/2) channels, scored by a base density). ``merge(kept, factored)`` is
    the exact inverse. Both are volume-preserving (log-det 0), so
    log p(x) = log p(kept-path) + log p_base(factored).
    """

    def __init__(self, num_channels: int):
        d = int(num_channels)
        if d < 2:
            raise ValueError(f"Split needs num_channels >= 2, got {num_channels}")
        self.num_channels = d
        self.kept_channels = d - d // 2
        self.factored_channels = d // 2

    def split(self, x: Array) -> tuple[Array, Array]:
        """(..., T, D) -> (kept (..., T, ceil(D/2)), factored (..., T, floor(D/2)))."""
        check_event(x, self.num_channels, "Split")
        return x[..., : self.kept_channels], x[..., self.kept_channels :]

    def merge(self, kept: Array, factored: Array) -> Array:
        """Inverse of :meth:`split`: concatenate kept and factored channels."""
        check_event(kept, self.kept_channels, "Split.merge", what="kept channels")
        check_event(factored, self.factored_channels, "Split.merge", what="factored channels")
        if kept.shape[:-1] != factored.shape[:-1]:
            raise ValueError(
                f"Split.merge: kept {tuple(kept.shape)} and factored {tuple(factored.shape)} "
                f"must share their batch and time axes"
            )
        return jnp.concatenate([kept, factored], axis=-1)
