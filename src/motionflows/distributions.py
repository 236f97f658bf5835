"""Base densities (``Normal``, ``StudentT``) and ``Transformed(base, bijector)``.

Every distribution has an ``event_shape`` (for motion flows usually (T, D)); ``log_prob(x)``
sums over the event axes and returns the leading (batch) shape of ``x``. Sampling takes an
explicit ``jax.random`` key and a ``temperature`` that scales the standard noise:

    Normal:    x = loc + scale * temperature * eps,   eps ~ N(0, 1)
    StudentT:  x = loc + scale * temperature * eps,   eps ~ t(df)

so temperature 0 returns the mode ``loc`` exactly. ``Transformed`` pushes base samples
through ``bijector.forward`` (latent -> data) and scores data with
``log p(x) = log p_base(z) + log|det dz/dx|``, z = ``bijector.inverse(x)``.

The spread is given either as ``scale`` or as ``log_scale`` (what networks and learned
parameters usually produce: ``u = (x - loc) * exp(-log_scale)`` and the log-determinant term
``log_scale`` are then used as given, never through ``log(exp(.))``).

All are Flax NNX modules (pytrees). ``loc`` / ``scale`` / ``log_scale`` / ``df`` are stored as
plain arrays (not ``nnx.Param``), so optimisers over ``nnx.Param`` do not train them; they may
be traced arrays (e.g. a conditional prior built inside a jitted function), so a model builds
its density where it needs it: ``Normal((None, D), loc=mean, log_scale=log_std)``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import jax
import jax.numpy as jnp
from flax import nnx

Array = jax.Array

__all__ = ["Normal", "StudentT", "Transformed"]

_HALF_LOG_2PI = 0.5 * math.log(2.0 * math.pi)


def _event_shape(event_shape: Sequence[int | None] | int) -> tuple[int | None, ...]:
    if isinstance(event_shape, int):
        event_shape = (event_shape,)
    out = tuple(None if d is None else int(d) for d in event_shape)
    if any(d is not None and d < 0 for d in out):
        raise ValueError(f"event_shape must hold non-negative sizes (or None), got {out}")
    return out


def _as_param(value, name: str, event_shape) -> Array | None:
    if value is None:
        return None
    arr = jnp.asarray(value, jnp.float32) if not hasattr(value, "dtype") else jnp.asarray(value)
    k = len(event_shape)
    tail = arr.shape[max(arr.ndim - k, 0) :]
    ev = event_shape[len(event_shape) - len(tail) :]
    for a, e in zip(tail, ev, strict=True):
        if e is not None and a not in (1, e):
            raise ValueError(
                f"{name} of shape {tuple(arr.shape)} does not broadcast to event_shape "
                f"{event_shape}"
            )
    return arr


class _Base(nnx.Module):
    """Shared plumbing of the factorised base densities."""

    _name = "Distribution"

    def __init__(self, event_shape=None, loc=None, scale=None, *, log_scale=None):
        if scale is not None and log_scale is not None:
            raise ValueError(f"{self._name}: pass scale or log_scale, not both")
        if event_shape is None:  # every axis of the parameters is an event axis; else any (T, D)
            given = [jnp.shape(p) for p in (loc, scale, log_scale) if p is not None]
            event_shape = jnp.broadcast_shapes(*given) if given else (None, None)
        self.event_shape = _event_shape(event_shape)
        self.loc = _as_param(loc, f"{self._name} loc", self.event_shape)
        self.scale = _as_param(scale, f"{self._name} scale", self.event_shape)
        self.log_scale = _as_param(log_scale, f"{self._name} log_scale", self.event_shape)

    def _params(self) -> list[Array]:
        return [p for p in (self.loc, self.scale, self.log_scale) if p is not None]

    # -- shapes

    @property
    def batch_shape(self) -> tuple[int, ...]:
        """Leading shape of loc / scale beyond the event (() for unbatched parameters)."""
        k = len(self.event_shape)
        shapes = [p.shape[: max(p.ndim - k, 0)] for p in self._params()]
        return tuple(jnp.broadcast_shapes(*shapes)) if shapes else ()

    def _concrete_event(self) -> tuple[int, ...]:
        if any(d is None for d in self.event_shape):
            raise ValueError(
                f"{self._name} with event_shape {self.event_shape} (None = any size) cannot be "
                f"sampled; build it with concrete sizes, e.g. {self._name}((T, D))"
            )
        return tuple(self.event_shape)  # type: ignore[return-value]

    def _check(self, x: Array) -> None:
        k = len(self.event_shape)
        shape = tuple(getattr(x, "shape", ()))
        ok = len(shape) >= k and all(
            e is None or s == e
            for s, e in zip(shape[len(shape) - k :], self.event_shape, strict=True)
        )
        if not ok:
            want = ", ".join("?" if e is None else str(e) for e in self.event_shape)
            raise ValueError(
                f"{self._name}.log_prob expects (..., {want}) inputs (event_shape "
                f"{self.event_shape}), got shape {shape}"
            )

    def _standardise(self, x: Array) -> tuple[Array, Array | None]:
        """(u, log_scale) with u = (x - loc) / scale; log_scale None for a unit scale."""
        u = x if self.loc is None else x - self.loc
        if self.log_scale is not None:
            return u * jnp.exp(-self.log_scale), self.log_scale
        if self.scale is not None:
            return u / self.scale, jnp.log(self.scale)
        return u, None

    def _event_sum(self, v: Array) -> Array:
        k = len(self.event_shape)
        return jnp.sum(v, axis=tuple(range(v.ndim - k, v.ndim))) if k else v

    def _event_size(self, x: Array) -> int:
        """Number of scalars in one event of ``x`` (the constant terms' multiplicity)."""
        return math.prod(x.shape[x.ndim - len(self.event_shape) :])

    def _spread(self) -> Array | None:
        if self.log_scale is not None:
            return jnp.exp(self.log_scale)
        return self.scale

    def _noise(self, key: Array, shape: tuple[int, ...]) -> Array:
        raise NotImplementedError

    def mode(self) -> Array:
        """The mode (= loc, or zeros) with shape batch_shape + event_shape."""
        shape = self.batch_shape + self._concrete_event()
        return (
            jnp.zeros(shape, jnp.float32) if self.loc is None else jnp.broadcast_to(self.loc, shape)
        )

    def sample(
        self, key: Array, sample_shape: Sequence[int] | int = (), temperature: float = 1.0
    ) -> Array:
        """Draw sample_shape + batch_shape + event_shape values; temperature 0 = the mode."""
        if isinstance(sample_shape, int):
            sample_shape = (sample_shape,)
        shape = tuple(sample_shape) + self.batch_shape + self._concrete_event()
        if isinstance(temperature, (int, float)) and temperature == 0:
            return jnp.broadcast_to(self.mode(), shape)
        eps = self._noise(key, shape) * temperature
        spread = self._spread()
        if spread is not None:
            eps = eps * spread
        if self.loc is not None:
            eps = eps + self.loc
        return eps


class Normal(_Base):
    """Factorised normal over ``event_shape`` (e.g. (T, D)).

    ``Normal(event_shape)`` is the standard normal; ``Normal(event_shape, loc, scale)`` (or
    ``log_scale=`` instead of ``scale``) the diagonal one (loc / scale broadcastable to
    event_shape, optionally with leading batch axes). Without ``event_shape``: ``Normal()``
    is the standard normal over (..., T, D) events of any size (``log_prob`` only; sampling
    needs sizes), and ``Normal(loc=..., scale=...)`` takes every axis of loc / scale as an
    event axis. ``None`` in event_shape matches any size in ``log_prob`` (e.g.
    ``Normal((None, 63))``); ``event_shape=()`` scores every element on its own.

    log p(x) = sum_event [-(x - loc)^2 / (2 scale^2) - log scale] - n log(2 pi) / 2,
    n = the number of scalars in one event.

    Examples:
      >>> import jax, jax.numpy as jnp
      >>> from motionflows.distributions import Normal
      >>> prior = Normal((80, 63))                  # one 4 s window of poses
      >>> x = prior.sample(jax.random.key(0), (2,))
      >>> x.shape, prior.log_prob(x).shape
      ((2, 80, 63), (2,))
      >>> print(f"{float(prior.log_prob(jnp.zeros((80, 63)))):.2f}")  # -5040 log(2 pi) / 2
      -4631.45
      >>> frame = Normal((None, 3), loc=jnp.array([0.0, 1.0, 2.0]), log_scale=jnp.zeros(3))
      >>> frame.log_prob(jnp.ones((5, 7, 3))).shape  # any T: (B, T, 3) -> (B,)
      (5,)
      >>> bool(jnp.all(prior.sample(jax.random.key(1), 3, temperature=0.0) == 0.0))
      True
    """

    _name = "Normal"

    def log_prob(self, x: Array) -> Array:
        """Sum of per-element log densities over the event axes: shape x.shape[:-k]."""
        self._check(x)
        u, log_scale = self._standardise(x)
        v = -0.5 * jnp.square(u)
        if log_scale is not None:
            v = v - log_scale
        # the constant leaves the sum: exact, and one multiply instead of n additions
        return self._event_sum(v) - self._event_size(x) * _HALF_LOG_2PI

    def _noise(self, key, shape):
        return jax.random.normal(key, shape, jnp.float32)


class StudentT(_Base):
    """Factorised Student-t with ``df`` degrees of freedom over ``event_shape`` (None: as
    in :class:`Normal`; ``scale`` or ``log_scale`` as there).

    log p(x) = sum_event [lgamma((df + 1) / 2) - lgamma(df / 2) - log(pi df) / 2 - log scale
                          - (df + 1) / 2 * log(1 + ((x - loc) / scale)^2 / df)].

    Examples:
      >>> import jax, jax.numpy as jnp
      >>> from motionflows.distributions import StudentT
      >>> base = StudentT((None, 63), df=5.0)       # heavy-tailed, any number of frames
      >>> z = jnp.zeros((2, 10, 63))
      >>> base.log_prob(z).shape
      (2,)
      >>> ref = jax.scipy.stats.t.logpdf(0.0, 5.0) * 10 * 63
      >>> bool(jnp.allclose(base.log_prob(z), ref))
      True
    """

    _name = "StudentT"

    def __init__(self, event_shape=None, df=None, loc=None, scale=None, *, log_scale=None):
        if df is None:
            raise ValueError("StudentT needs df (degrees of freedom > 0), e.g. StudentT(df=5.0)")
        super().__init__(event_shape, loc, scale, log_scale=log_scale)
        df_arr = jnp.asarray(df, jnp.float32)
        if not isinstance(df_arr, jax.core.Tracer) and bool(jnp.any(df_arr <= 0)):
            raise ValueError(f"StudentT needs df > 0, got {df}")
        self.df = df_arr

    def log_prob(self, x: Array) -> Array:
        self._check(x)
        u, log_scale = self._standardise(x)
        df = self.df
        const = (
            jax.scipy.special.gammaln(0.5 * (df + 1.0))
            - jax.scipy.special.gammaln(0.5 * df)
            - 0.5 * jnp.log(jnp.pi * df)
        )
        if log_scale is not None:
            const = const - log_scale
        return self._event_sum(const - 0.5 * (df + 1.0) * jnp.log1p(u * u / df))

    def _noise(self, key, shape):
        return jax.random.t(key, self.df, shape, jnp.float32)


class Transformed(nnx.Module):
    """The density of x = bijector.forward(z, context), z ~ base.

    ``log_prob(x, *, context=None)`` = base.log_prob(z) + log|det dz/dx| with
    (z, log|det dz/dx|) = bijector.inverse_and_log_det(x, context=context).
    ``sample(key, sample_shape, *, context=None, temperature=1.0)`` draws z from the base
    at the given temperature and returns bijector.forward(z, context=context); temperature
    0 is exact (the image of the base mode). The context's batch axes must match
    sample_shape (+ the base's batch shape). Any module with the two ``*_and_log_det``
    methods is a bijector here (a whole model such as ``models.glow.Glow`` too).

    Examples:
      >>> import jax, jax.numpy as jnp
      >>> from motionflows import bijectors as bj
      >>> from motionflows.distributions import Normal, Transformed
      >>> flow = bj.ActNorm(3)
      >>> flow.logs[...] = jnp.full((3,), jnp.log(2.0))  # data -> latent: z = 2 x
      >>> dist = Transformed(Normal((4, 3)), flow)
      >>> x = jnp.full((4, 3), 0.5)
      >>> ref = Normal((4, 3)).log_prob(2.0 * x) + 4 * 3 * jnp.log(2.0)  # + log|det dz/dx|
      >>> bool(jnp.allclose(dist.log_prob(x), ref))
      True
      >>> dist.sample(jax.random.key(0), (8,)).shape
      (8, 4, 3)
    """

    def __init__(self, base: _Base | nnx.Module, bijector: nnx.Module):
        for name in ("log_prob", "sample"):
            if not hasattr(base, name):
                raise ValueError(f"Transformed base must have {name}(), got {type(base).__name__}")
        for name in ("forward_and_log_det", "inverse_and_log_det"):
            if not hasattr(bijector, name):
                raise ValueError(
                    f"Transformed bijector must have {name}(), got {type(bijector).__name__}"
                )
        self.base = base
        self.bijector = bijector

    @property
    def event_shape(self):
        return getattr(self.base, "event_shape", None)

    def log_prob(self, x: Array, *, context: Array | None = None) -> Array:
        z, log_det = self.bijector.inverse_and_log_det(x, context=context)
        return self.base.log_prob(z) + log_det

    def sample(
        self,
        key: Array,
        sample_shape: Sequence[int] | int = (),
        *,
        context: Array | None = None,
        temperature: float = 1.0,
    ) -> Array:
        z = self.base.sample(key, sample_shape, temperature=temperature)
        forward = getattr(self.bijector, "forward", None)
        if forward is None:  # a model that only has the *_and_log_det pair
            return self.bijector.forward_and_log_det(z, context=context)[0]
        return forward(z, context=context)

    def sample_and_log_prob(
        self,
        key: Array,
        sample_shape: Sequence[int] | int = (),
        *,
        context: Array | None = None,
        temperature: float = 1.0,
    ) -> tuple[Array, Array]:
        """Samples and their log-density (one forward pass, no inverse)."""
        z = self.base.sample(key, sample_shape, temperature=temperature)
        x, log_det = self.bijector.forward_and_log_det(z, context=context)
        return x, self.base.log_prob(z) - log_det
