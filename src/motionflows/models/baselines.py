"""Two exact baselines that anchor every likelihood table.

* :class:`DiagonalGaussian`: every frame independent, ``x_t ~ N(mu, diag(sigma^2))``.
* :class:`LinearGaussianAR`: ``x_t ~ N(W^T h_t, Sigma)`` with the feature vector
  ``h_t = [x_{t-tau}, ..., x_{t-1}, c_{t-tau}, ..., c_t, 1]`` (poses oldest first, then the
  tau + 1 controls up to and including the current one, then a bias; the MoGlow
  conditioning layout). ``Sigma = L L^T`` is full (lower-triangular ``L`` with a positive
  diagonal) or diagonal.

Both work in standardised space (the models only ever see standardised data), give exact
log-likelihoods in nats and can sample. Window scores: ``log_prob`` scores all T frames;
the AR pads the history before the first frame with zeros (the mean pose and mean control
in standardised space), as MoGlow's whole-window score does, so all models are compared on
identical frames. ``log_prob(..., skip=tau)`` leaves out the first ``skip`` frames (the
official scope: frames tau..T-1 given the true first tau frames).

Both are fitted in closed form from data statistics (:func:`fit_gaussian`,
:func:`fit_linear_ar`, maximum likelihood; the AR's least squares has a small ridge) and
can also be trained by gradient descent on ``-log_prob`` (their parameters are ``nnx.Param``).
"""

from __future__ import annotations

import warnings
from collections.abc import Iterable

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from motionflows.data.names import CONTROL_DIM, POSE_DIM
from motionflows.deprecation import renamed
from motionflows.distributions import Normal
from motionflows.models.validation import check_input, check_temperature


def _check_pose(pose: jax.Array, dim: int, name: str = "pose") -> jax.Array:
    """Shape (..., T, dim), then ``validation.check_input``; returns float32."""
    shape = getattr(pose, "shape", None)
    if shape is None or len(shape) < 2 or shape[-1] != dim:
        raise ValueError(f"{name} must have shape (..., T, {dim}); got {shape}")
    return check_input(pose, name, "baseline")


class DiagonalGaussian(nnx.Module):
    """Per-frame diagonal Gaussian ``x_t ~ N(mean, diag(exp(log_std))^2)``, frames independent.

    Parameters: ``mean`` (D,), ``log_std`` (D,). ``log_prob(pose)`` with pose (..., T, D)
    returns (...,) nats summed over frames. Each frame's density is :meth:`distribution`.
    """

    def __init__(self, pose_dim: int = POSE_DIM):
        self.pose_dim = int(pose_dim)
        self.mean = nnx.Param(jnp.zeros((pose_dim,), jnp.float32))
        self.log_std = nnx.Param(jnp.zeros((pose_dim,), jnp.float32))

    def distribution(self) -> Normal:
        """The density of one frame, ``Normal((D,), loc=mean, log_scale=log_std)``."""
        return Normal((self.pose_dim,), loc=self.mean[...], log_scale=self.log_std[...])

    def frame_log_prob(self, pose: jax.Array) -> jax.Array:
        """Log-density of each frame: pose (..., T, D) -> (..., T)."""
        return self.distribution().log_prob(_check_pose(pose, self.pose_dim))

    def log_prob(self, pose: jax.Array, control: jax.Array | None = None, *, skip: int = 0):
        """Sum of the frame log-densities of frames skip..T-1: (..., T, D) -> (...,)."""
        del control
        return jnp.sum(self.frame_log_prob(pose)[..., skip:], -1)

    def sample(self, key: jax.Array, shape: tuple[int, int], *, temperature: float = 1.0):
        """Draw poses of shape ``shape + (D,)`` = (B, T, D)."""
        check_temperature(temperature, "DiagonalGaussian.sample")
        return self.distribution().sample(key, tuple(shape), temperature=temperature)


class LinearGaussianAR(nnx.Module):
    """Linear-Gaussian autoregression ``x_t ~ N(W^T h_t, L L^T)`` (see the module docstring).

    Parameters: ``weight`` (F, D) with ``F = tau * D + (tau + 1) * C + 1`` (the last row is
    the bias), ``log_diag`` (D,) = log of the diagonal of ``L``, and for ``covariance="full"``
    ``lower`` (D, D), whose strictly lower triangle is ``L``'s.
    """

    def __init__(
        self,
        tau: int = 10,
        *,
        pose_dim: int = POSE_DIM,
        control_dim: int = CONTROL_DIM,
        covariance: str = "full",
        ridge: float = 1e-4,
    ):
        if covariance not in ("full", "diag"):
            raise ValueError(f"covariance must be 'full' or 'diag', got {covariance!r}")
        if tau < 0:
            raise ValueError(f"tau must be >= 0, got {tau}")
        self.tau = int(tau)
        self.pose_dim = int(pose_dim)
        self.control_dim = int(control_dim)
        self.covariance = covariance
        self.ridge = float(ridge)
        f = self.num_features
        self.weight = nnx.Param(jnp.zeros((f, pose_dim), jnp.float32))
        self.log_diag = nnx.Param(jnp.zeros((pose_dim,), jnp.float32))
        if covariance == "full":
            self.lower = nnx.Param(jnp.zeros((pose_dim, pose_dim), jnp.float32))

    @property
    def num_features(self) -> int:
        return self.tau * self.pose_dim + (self.tau + 1) * self.control_dim + 1

    def cholesky(self) -> jax.Array:
        """The residual covariance's Cholesky factor ``L`` (D, D), lower triangular."""
        diag = jnp.diag(jnp.exp(self.log_diag[...]))
        if self.covariance == "diag":
            return diag
        return jnp.tril(self.lower[...], -1) + diag

    def features(
        self, pose: jax.Array, control: jax.Array, history: jax.Array | None = None
    ) -> jax.Array:
        """Feature vectors ``h_t`` for every frame: pose (B, T, D), control (B, T, C) ->
        (B, T, F). History before frame 0 is ``history`` (B, tau, D) or zeros; controls
        before frame 0 are zeros."""
        pose = _check_pose(pose, self.pose_dim)
        control = _check_pose(control, self.control_dim, "control")
        if control.shape[:2] != pose.shape[:2]:
            raise ValueError(
                f"LinearGaussianAR: pose {tuple(pose.shape)} and control "
                f"{tuple(control.shape)} must share (B, T)"
            )
        b, t = pose.shape[0], pose.shape[1]
        tau = self.tau
        if history is None:
            history = jnp.zeros((b, tau, self.pose_dim), pose.dtype)
        xp = jnp.concatenate([history, pose], axis=1)  # (B, tau + T, D)
        cp = jnp.concatenate([jnp.zeros((b, tau, self.control_dim), control.dtype), control], 1)
        parts = [xp[:, k : k + t] for k in range(tau)]  # x_{t-tau+k}
        parts += [cp[:, k : k + t] for k in range(tau + 1)]  # c_{t-tau+k}, k = tau is c_t
        parts.append(jnp.ones((b, t, 1), pose.dtype))
        return jnp.concatenate(parts, axis=-1)

    def frame_log_prob(self, pose: jax.Array, control: jax.Array) -> jax.Array:
        """Exact log p(x_t | h_t) of every frame with a zero history: -> (B, T).

        The whitened residual y = L^-1 (x_t - W^T h_t) is standard normal, so
        log p(x_t | h_t) = log N(y; 0, I) - sum(log diag L).
        """
        h = self.features(pose, control)
        resid = pose - h @ self.weight[...]
        chol = self.cholesky()
        y = jax.scipy.linalg.solve_triangular(chol, resid[..., None], lower=True)[..., 0]
        return Normal((self.pose_dim,)).log_prob(y) - jnp.sum(self.log_diag[...])

    def log_prob(self, pose: jax.Array, control: jax.Array, *, skip: int = 0) -> jax.Array:
        """Sum of log p(x_t | h_t) over frames skip..T-1: -> (B,). With ``skip=0`` this is
        the whole-window score with a zero (mean-pose) history; with ``skip=tau`` frames
        tau..T-1 given the true first tau frames (their history is then all real)."""
        if not 0 <= skip < pose.shape[1]:
            raise ValueError(
                f"LinearGaussianAR.log_prob: skip must be in [0, T) to score any frame, got "
                f"skip={skip} for T={pose.shape[1]}"
            )
        return jnp.sum(self.frame_log_prob(pose, control)[:, skip:], -1)

    def sample(
        self,
        key: jax.Array,
        control: jax.Array,
        *,
        temperature: float = 1.0,
        seed_history: jax.Array | None = None,
        history: jax.Array | None = None,
    ) -> jax.Array:
        """Sample poses (B, T, D) for control (B, T, C) with ``lax.scan`` over frames.

        ``seed_history`` (B, S, D): the last ``tau`` of these frames seed the history (zeros
        if None or shorter); ``history=`` is its deprecated old name. Controls before frame
        0 are zeros. Window i's draw depends on B for the same key (the residuals are drawn
        (T, B, D)); the bench's numbers were measured so.
        """
        seed_history = renamed(
            "LinearGaussianAR.sample",
            old="history",
            new="seed_history",
            old_value=history,
            new_value=seed_history,
            default=None,
        )
        control = _check_pose(control, self.control_dim, "control")
        check_temperature(temperature, "LinearGaussianAR.sample")
        b, t = control.shape[0], control.shape[1]
        tau, d = self.tau, self.pose_dim
        hist = jnp.zeros((b, tau, d), jnp.float32)
        if seed_history is not None and tau > 0:
            seed_history = _check_pose(seed_history, d, "seed_history")
            s = min(tau, seed_history.shape[1])
            if s > 0:
                hist = hist.at[:, tau - s :].set(seed_history[:, -s:].astype(jnp.float32))
        cp = jnp.concatenate([jnp.zeros((b, tau, self.control_dim), control.dtype), control], 1)
        weight, chol = self.weight[...], self.cholesky()
        eps = Normal((d,)).sample(key, (t, b), temperature=temperature)  # whitened residuals

        def step(hist, inputs):
            i, e = inputs
            cwin = jax.lax.dynamic_slice_in_dim(cp, i, tau + 1, axis=1)  # (B, tau+1, C)
            h = jnp.concatenate(
                [hist.reshape(b, tau * d), cwin.reshape(b, -1), jnp.ones((b, 1))], -1
            )
            x = h @ weight + e @ chol.T
            hist = jnp.concatenate([hist[:, 1:], x[:, None]], 1) if tau > 0 else hist
            return hist, x

        _, xs = jax.lax.scan(step, hist, (jnp.arange(t), eps))
        return jnp.swapaxes(xs, 0, 1)


def fit_gaussian(model: DiagonalGaussian, batches: Iterable[dict]) -> DiagonalGaussian:
    """Maximum-likelihood mean and std over all frames of ``batches`` (dicts with "pose").

    Returns a new model; statistics accumulate in float64 numpy.
    """
    n, s1, s2 = 0, 0.0, 0.0
    for batch in batches:
        x = np.asarray(batch["pose"], np.float64).reshape(-1, model.pose_dim)
        n, s1, s2 = n + x.shape[0], s1 + x.sum(0), s2 + (x**2).sum(0)
    if n == 0:
        raise ValueError("fit_gaussian: no frames to fit")
    mean = s1 / n
    var = np.maximum(s2 / n - mean**2, 1e-12)
    out = nnx.clone(model)
    out.mean[...] = jnp.asarray(mean, jnp.float32)
    out.log_std[...] = jnp.asarray(0.5 * np.log(var), jnp.float32)
    return out


@jax.jit
def _ar_stats(model: LinearGaussianAR, pose, control, mask):
    h = model.features(pose, control) * mask[..., None]
    y = pose * mask[..., None]
    h = h.reshape(-1, h.shape[-1])
    y = y.reshape(-1, y.shape[-1])
    return h.T @ h, h.T @ y, y.T @ y


def fit_linear_ar(
    model: LinearGaussianAR, batches: Iterable[dict], *, skip: int = 0
) -> LinearGaussianAR:
    """Closed-form maximum likelihood (ridge least squares) over the frames of ``batches``.

    Scores frames skip..T-1 of each window (``skip=0``: the whole-window objective with a
    zero history, the model's ``log_prob`` default; ``skip=tau``: the official scope).
    With ``n`` frames, ``A = H^T H / n``, ``B = H^T Y / n``:
    ``W = (A + ridge * I')^{-1} B`` (``I'`` leaves the bias unpenalised) and
    ``Sigma = Y^T Y / n - B^T W - W^T B + W^T A W`` (the residual covariance), whose
    Cholesky factor (or its diagonal) becomes ``L``. Accumulated per batch, so the data
    never has to fit in memory at once (per-batch sums in float32, totals in float64).
    """
    f, d = model.num_features, model.pose_dim
    hh, hy, yy, n = np.zeros((f, f)), np.zeros((f, d)), np.zeros((d, d)), 0
    for batch in batches:
        pose = jnp.asarray(batch["pose"], jnp.float32)
        control = jnp.asarray(batch["control"], jnp.float32)
        b, t = pose.shape[:2]
        if skip >= t:
            raise ValueError(f"fit_linear_ar: skip={skip} leaves no frames of {t}")
        mask = jnp.broadcast_to((jnp.arange(t) >= skip).astype(jnp.float32), (b, t))
        a1, a2, a3 = _ar_stats(model, pose, control, mask)
        hh += np.asarray(a1, np.float64)
        hy += np.asarray(a2, np.float64)
        yy += np.asarray(a3, np.float64)
        n += b * (t - skip)
    if n == 0:
        raise ValueError("fit_linear_ar: no frames to fit")
    a, bmat, c = hh / n, hy / n, yy / n
    reg = np.eye(f) * model.ridge
    reg[-1, -1] = 0.0
    w = np.linalg.solve(a + reg, bmat)
    sigma = c - bmat.T @ w - w.T @ bmat + w.T @ a @ w
    sigma = 0.5 * (sigma + sigma.T)
    if n <= f:
        warnings.warn(
            f"fit_linear_ar: {n} frames for {f} features per output: the residual covariance "
            "is degenerate; use more windows, a smaller tau or a larger ridge",
            stacklevel=2,
        )
    # a floor on the eigenvalues keeps Sigma positive definite (degenerate data, rounding)
    evals, evecs = np.linalg.eigh(sigma)
    floor = max(1e-6 * max(float(evals.max()), 1e-12), 1e-10)
    sigma = (evecs * np.maximum(evals, floor)) @ evecs.T
    sigma = 0.5 * (sigma + sigma.T)
    out = nnx.clone(model)
    out.weight[...] = jnp.asarray(w, jnp.float32)
    if model.covariance == "full":
        chol = np.linalg.cholesky(sigma)
        out.log_diag[...] = jnp.asarray(np.log(np.diag(chol)), jnp.float32)
        out.lower[...] = jnp.asarray(np.tril(chol, -1), jnp.float32)
    else:
        out.log_diag[...] = jnp.asarray(0.5 * np.log(np.diag(sigma)), jnp.float32)
    return out
