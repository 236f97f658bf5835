"""Per-frame invertible linear maps of the channels: LU (Glow's 1x1), dense, permutations."""

from __future__ import annotations

from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx
from jax.scipy.linalg import lu as _lu
from jax.scipy.linalg import solve_triangular

from motionflows.bijectors.base import Bijector, Fixed, check_event, check_frame

Array = jax.Array

__all__ = ["DenseLinear", "InvertibleLinear", "Permute", "Reverse"]


def _as_key(rngs: nnx.Rngs | Array | None, key: Array | None, name: str) -> Array:
    if key is not None:
        return key
    if rngs is None:
        raise ValueError(f"{name} needs rngs=nnx.Rngs(...) (or key=jax.random.key(...))")
    return rngs.params() if isinstance(rngs, nnx.Rngs) else rngs


def _frames(x: Array) -> Array:
    return jnp.reshape(x, (-1, x.shape[-1]))


class InvertibleLinear(Bijector):
    """Glow's invertible 1x1 map, per frame, LU-parameterised.

        W = P L (U + diag(sign_s * exp(log_s)))

    with P a fixed permutation matrix, L unit lower-triangular (only the strictly lower
    entries of ``lower`` are used), U strictly upper-triangular (only the strictly upper
    entries of ``upper`` are used) and ``sign_s`` fixed. Trained: ``lower``, ``upper``,
    ``log_s`` (``nnx.Param``); fixed: ``P`` (D, D) and ``sign_s`` (D,) (:class:`Fixed`).

    data -> latent (``inverse``):  z_t = W x_t,       log|det| = T * sum(log_s)
    latent -> data (``forward``):  x_t = W^-1 z_t,    log|det| = -T * sum(log_s)

    The latent -> data map of a sequence uses two triangular solves (never a dense inverse).
    Frame steps instead carry ``(W, W^-1)`` (``initial_carry``: W^-1 from two triangular
    solves, once per stream), so each frame is one matrix-vector product either way.
    Initialised from the LU decomposition of a random orthogonal matrix drawn from ``rngs``
    (an ``nnx.Rngs``; a raw ``key=`` works too).
    """

    frame_constant_log_det = True  # the same log-det on every frame

    def __init__(
        self, num_channels: int, *, rngs: nnx.Rngs | Array | None = None, key: Array | None = None
    ):
        d = int(num_channels)
        if d < 1:
            raise ValueError(f"InvertibleLinear needs num_channels >= 1, got {num_channels}")
        self.num_channels = d
        q = jax.random.orthogonal(_as_key(rngs, key, "InvertibleLinear"), d, dtype=jnp.float32)
        p, l, u = _lu(q)
        s = jnp.diag(u)
        self.P = Fixed(p.astype(jnp.float32))
        self.sign_s = Fixed(jnp.sign(s).astype(jnp.float32))
        self.lower = nnx.Param(jnp.tril(l, -1).astype(jnp.float32))
        self.upper = nnx.Param(jnp.triu(u, 1).astype(jnp.float32))
        self.log_s = nnx.Param(jnp.log(jnp.abs(s)).astype(jnp.float32))

    def _factors(self) -> tuple[Array, Array, Array]:
        """(P, L, U') with W = P @ L @ U'."""
        d = self.num_channels
        eye = jnp.eye(d, dtype=jnp.float32)
        p = jax.lax.stop_gradient(self.P[...])
        sign = jax.lax.stop_gradient(self.sign_s[...])
        l = jnp.tril(self.lower[...], -1) + eye
        u = jnp.triu(self.upper[...], 1) + jnp.diag(sign * jnp.exp(self.log_s[...]))
        return p, l, u

    def weight(self) -> Array:
        """The (D, D) matrix W (data -> latent: z_t = W x_t)."""
        p, l, u = self._factors()
        return p @ l @ u

    def inverse_weight(self) -> Array:
        """The (D, D) matrix W^-1 = U^-1 L^-1 P^T (latent -> data: x_t = W^-1 z_t)."""
        p, l, u = self._factors()
        a = solve_triangular(l, p.T, lower=True, unit_diagonal=True)
        return solve_triangular(u, a, lower=False)

    def _log_det(self, x: Array) -> Array:
        return jnp.broadcast_to(x.shape[-2] * jnp.sum(self.log_s[...]), x.shape[:-2])

    def initial_carry(self, batch_shape=()):
        """``(W, W^-1)``, each (D, D): formed once, read by every frame step."""
        del batch_shape
        return self.weight(), self.inverse_weight()

    def _frame_step(self, u_t: Array, carry, *, forward: bool):
        check_frame(u_t, "InvertibleLinear")
        if u_t.shape[-1] != self.num_channels:
            raise ValueError(
                f"InvertibleLinear expects frames (..., {self.num_channels}), "
                f"got {tuple(u_t.shape)}"
            )
        if carry is None:
            carry = self.initial_carry()
        w = carry[1] if forward else carry[0]
        ld = jnp.sum(self.log_s[...])
        ld = jnp.broadcast_to(-ld if forward else ld, u_t.shape[:-1])
        return u_t @ w.T, ld, carry

    def inverse_step(self, y_t, *, context_t=None, carry=None):
        return self._frame_step(y_t, carry, forward=False)

    def forward_step(self, x_t, *, context_t=None, carry=None):
        return self._frame_step(x_t, carry, forward=True)

    def inverse_and_log_det(self, y, *, context=None):
        check_event(y, self.num_channels, "InvertibleLinear")
        z = y @ self.weight().T
        return z, self._log_det(y)

    def forward_and_log_det(self, x, *, context=None):
        check_event(x, self.num_channels, "InvertibleLinear")
        p, l, u = self._factors()
        rows = _frames(x) @ p  # rows of (P^T z)^T
        a = solve_triangular(l, rows.T, lower=True, unit_diagonal=True)
        out = solve_triangular(u, a, lower=False).T
        return jnp.reshape(out, x.shape), -self._log_det(x)


class DenseLinear(Bijector):
    """Plain, unconstrained per-frame linear map z_t = W x_t (data -> latent).

    ``weight`` (D, D) is an ``nnx.Param`` initialised to a random orthogonal matrix.
    log|det dz/dx| = T * log|det W| (``slogdet`` per call); latent -> data solves W x = z
    (one LU per call). Cheaper to write, costlier to run than :class:`InvertibleLinear`, and
    nothing keeps W invertible during training.
    """

    frame_constant_log_det = True  # the same log-det on every frame

    def __init__(
        self, num_channels: int, *, rngs: nnx.Rngs | Array | None = None, key: Array | None = None
    ):
        d = int(num_channels)
        if d < 1:
            raise ValueError(f"DenseLinear needs num_channels >= 1, got {num_channels}")
        self.num_channels = d
        w0 = jax.random.orthogonal(_as_key(rngs, key, "DenseLinear"), d, dtype=jnp.float32)
        self.weight = nnx.Param(w0)

    def _log_det(self, x: Array) -> Array:
        _, logabs = jnp.linalg.slogdet(self.weight[...])
        return jnp.broadcast_to(x.shape[-2] * logabs, x.shape[:-2])

    def inverse_and_log_det(self, y, *, context=None):
        check_event(y, self.num_channels, "DenseLinear")
        return y @ self.weight[...].T, self._log_det(y)

    def forward_and_log_det(self, x, *, context=None):
        check_event(x, self.num_channels, "DenseLinear")
        out = jnp.linalg.solve(self.weight[...], _frames(x).T).T
        return jnp.reshape(out, x.shape), -self._log_det(x)


class Permute(Bijector):
    """Fixed channel permutation (zero log-det).

    data -> latent (``inverse``): z[..., i] = x[..., perm[i]];  ``forward`` undoes it.
    ``perm`` is kept as a static tuple (part of the module's structure, not an array).
    """

    frame_constant_log_det = True  # the same log-det on every frame

    def __init__(self, perm: Sequence[int]):
        perm = tuple(int(i) for i in np.asarray(perm).reshape(-1))
        if sorted(perm) != list(range(len(perm))):
            raise ValueError(f"Permute needs a permutation of 0..D-1, got {perm}")
        self.perm = perm
        self.inverse_perm = tuple(int(i) for i in np.argsort(perm))
        self.num_channels = len(perm)

    @classmethod
    def random(cls, num_channels: int, *, key: Array) -> Permute:
        """A uniformly random permutation of ``num_channels`` channels (drawn eagerly)."""
        return cls(np.asarray(jax.random.permutation(key, int(num_channels))))

    def _zero(self, x: Array) -> Array:
        return jnp.zeros(x.shape[:-2], jnp.result_type(x.dtype, jnp.float32))

    def inverse_and_log_det(self, y, *, context=None):
        check_event(y, self.num_channels, type(self).__name__)
        return jnp.take(y, jnp.asarray(self.perm), axis=-1), self._zero(y)

    def forward_and_log_det(self, x, *, context=None):
        check_event(x, self.num_channels, type(self).__name__)
        return jnp.take(x, jnp.asarray(self.inverse_perm), axis=-1), self._zero(x)


class Reverse(Permute):
    """Fixed channel reversal: z[..., i] = x[..., D - 1 - i] (zero log-det, self-inverse)."""

    def __init__(self, num_channels: int):
        if int(num_channels) < 1:
            raise ValueError(f"Reverse needs num_channels >= 1, got {num_channels}")
        super().__init__(tuple(range(int(num_channels) - 1, -1, -1)))
