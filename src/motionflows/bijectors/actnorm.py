"""Activation normalisation (Glow's ActNorm) and the explicit data-dependent initialisation."""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from flax import nnx

from motionflows.bijectors.base import Bijector, check_event, data_init_mode, is_initializing

Array = jax.Array

__all__ = ["ActNorm", "initialize_from_data"]

ACTNORM_STD_EPS = 1e-6


class ActNorm(Bijector):
    """Per-channel affine normalisation of a sequence (..., T, D).

    data -> latent (``inverse``):  z = (x + bias) * exp(logs),  log|det dz/dx| = T * sum(logs)
    latent -> data (``forward``):  x = z * exp(-logs) - bias,   log|det dx/dz| = -T * sum(logs)

    ``bias`` and ``logs`` (both (D,), ``nnx.Param``) start at zero (the identity). Set them
    from data with :func:`initialize_from_data`; that never happens implicitly.
    """

    frame_constant_log_det = True  # the same log-det on every frame

    def __init__(self, num_channels: int, *, rngs: nnx.Rngs | None = None):
        del rngs  # accepted for a uniform constructor signature; ActNorm draws nothing
        if int(num_channels) < 1:
            raise ValueError(f"ActNorm needs num_channels >= 1, got {num_channels}")
        self.num_channels = int(num_channels)
        self.bias = nnx.Param(jnp.zeros((self.num_channels,), jnp.float32))
        self.logs = nnx.Param(jnp.zeros((self.num_channels,), jnp.float32))

    def _log_det(self, x: Array) -> Array:
        ld = x.shape[-2] * jnp.sum(self.logs[...])
        return jnp.broadcast_to(ld, x.shape[:-2])

    def forward_and_log_det(self, x, *, context=None):
        check_event(x, self.num_channels, "ActNorm")
        if is_initializing():  # reached through Inverse(...) in a data -> latent pass
            mean, std = self._stats(x)
            self.logs[...] = jnp.log(std + ACTNORM_STD_EPS)
            self.bias[...] = mean / (std + ACTNORM_STD_EPS)
        y = x * jnp.exp(-self.logs[...]) - self.bias[...]
        return y, -self._log_det(x)

    def inverse_and_log_det(self, y, *, context=None):
        check_event(y, self.num_channels, "ActNorm")
        if is_initializing():
            mean, std = self._stats(y)
            self.bias[...] = -mean
            self.logs[...] = jnp.log(1.0 / (std + ACTNORM_STD_EPS))
        z = (y + self.bias[...]) * jnp.exp(self.logs[...])
        return z, self._log_det(y)

    def _stats(self, u: Array) -> tuple[Array, Array]:
        """Per-channel mean and biased std over all leading axes and time (init mode)."""
        if isinstance(u, jax.core.Tracer):
            raise ValueError(
                "initialize_from_data reached an ActNorm inside a JAX transformation "
                "(jax.jit, jax.lax.scan, jax.vmap, ...). Data-dependent initialisation runs "
                "eagerly: call initialize_from_data outside jit, and in model code loop in "
                "Python when motionflows.bijectors.is_initializing() is True (bijectors.Scan "
                "does this by itself)."
            )
        flat = jnp.reshape(u, (-1, self.num_channels)).astype(jnp.float32)
        if flat.shape[0] < 2:  # one value: every channel looks constant (scale 1e6)
            raise ValueError(
                f"ActNorm initialisation got one value per channel (input {tuple(u.shape)}), "
                "so it cannot measure a spread: initialise on a batch of at least 2 windows "
                "(train.batch_size >= 2)"
            )
        mean = jnp.mean(flat, axis=0)
        std = jnp.sqrt(jnp.mean(jnp.square(flat - mean), axis=0))  # biased variance
        return mean, std


def initialize_from_data(model: Any, x: Array, *, context: Array | None = None) -> Any:
    """Data-dependent initialisation: a NEW model whose ActNorms normalise ``x``.

    Pure: ``model`` is left unchanged (the work is done on ``nnx.clone(model)``).

    Mechanism (what model code can rely on): the copy's ``inverse_and_log_det(x,
    context=context)`` (or, for a distribution such as ``Transformed``, its
    ``log_prob(x, context=context)``) is run once, eagerly, inside
    :func:`motionflows.bijectors.data_init_mode`. In that mode every ``ActNorm`` reached in
    the data -> latent pass first sets, from its own input u of shape (..., T, D),

        bias = -mean(u),   logs = log(1 / (std(u) + 1e-6))

    with mean and (biased) std per channel over all leading axes and time, and then applies
    itself, so each ActNorm sees the outputs of the already-initialised layers before it.
    An ActNorm reached in its forward direction (inside an ``Inverse``) instead sets
    logs = log(std(u) + 1e-6), bias = mean(u) / (std(u) + 1e-6), which also makes its output
    zero-mean and unit-std. ``Chain`` and ``Inverse`` need nothing special; ``Scan``
    unrolls its stacked steps eagerly (in either direction) and writes the results back
    into the stack. Any model whose
    ``inverse_and_log_det`` calls these bijectors eagerly is covered; code that wraps
    ActNorms in its own ``jax.jit``/``jax.lax.scan`` must loop in Python while
    :func:`motionflows.bijectors.is_initializing` is True (otherwise a clear ``ValueError``
    is raised). A constant channel gets logs = log(1e6): finite.

    Args:
      model: a bijector or a model with ``inverse_and_log_det`` (or ``log_prob``).
      x: data (..., T, D) as the model's ``inverse_and_log_det`` takes it.
      context: optional conditioning passed through unchanged.
    Returns:
      The initialised copy.
    """
    if not isinstance(model, nnx.Module):
        raise ValueError(
            f"initialize_from_data expects an nnx.Module (a bijector or model), "
            f"got {type(model).__name__}"
        )
    x = jnp.asarray(x)
    if x.size and not bool(jnp.all(jnp.isfinite(x))):
        raise ValueError("initialize_from_data got non-finite data (NaN or inf); clean it first")
    new = nnx.clone(model)
    with data_init_mode():
        if hasattr(new, "inverse_and_log_det"):
            new.inverse_and_log_det(x, context=context)
        elif hasattr(new, "log_prob"):
            new.log_prob(x, context=context)
        else:
            raise ValueError(
                f"initialize_from_data needs a model with inverse_and_log_det or log_prob; "
                f"{type(model).__name__} has neither"
            )
    return new
