r"""A learned, autoregressive prior over a sequence of latents (the VAE-LSTM's ``prior="learned"``).

For latents z (B, N, D), one per pooled step, and per-step conditioning features h (B, N, H)::

    s_t = LSTM(s_{t-1}, [z_{t-1}, h_t])          s_0 = 0, z_0 = 0     (one layer, ``hidden``)
    (mu_t, log sigma_t) = W s_t + b                                  (zero-initialised)
    p(z | h) = prod_t N(z_t; mu_t, diag sigma_t^2)

so step t reads the earlier latents and the control up to t, never z_t or later ones
(``context_dim=0``: the earlier latents only, s_t = LSTM(s_{t-1}, z_{t-1})). The
head starts at zero: an untrained prior is N(0, I) at every step, the paper's. This is the
"learned prior" of sequential VAEs (e.g. Denton & Fergus 2018's SVG-LP), our option, not
Habibie et al.'s: with N(0, I) at every step, ancestral samples draw each 0.2 s of motion
independently of the last, so no gait cycle runs through them
(docs/readme/vae_lstm.md#a-learned-prior).

:meth:`LatentPrior.__call__` gives the parameters of every step at once for given latents
(training, scoring); :meth:`LatentPrior.sample` draws z step by step in one ``lax.scan``,
z_t = mu_t + temperature * sigma_t * eps_t, and at temperature 1 its draws are exactly
distributed as the density ``__call__`` scores.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import nnx

from motionflows.nets.lstm import LSTM

Array = jax.Array

__all__ = ["LatentPrior"]


class LatentPrior(nnx.Module):
    """p(z_t | z_{<t}, h_{<=t}) = N(mu_t, diag sigma_t^2) from an LSTM over pooled steps.

    ``context_dim=0`` leaves h out: p(z_t | z_{<t}), the features are then read only for
    their shape."""

    def __init__(self, latent_dim: int, context_dim: int, hidden: int = 128, *, rngs: nnx.Rngs):
        self.latent_dim = int(latent_dim)
        self.context_dim = int(context_dim)
        self.lstm = LSTM(self.latent_dim + self.context_dim, int(hidden), rngs=rngs)
        zeros = nnx.initializers.zeros_init()
        self.head = nnx.Linear(
            int(hidden), 2 * self.latent_dim, kernel_init=zeros, bias_init=zeros, rngs=rngs
        )

    def _split(self, out: Array) -> tuple[Array, Array]:
        return out[..., : self.latent_dim], out[..., self.latent_dim :]

    def __call__(self, z: Array, h: Array) -> tuple[Array, Array]:
        """(mean, log_std), each (B, N, D), of every step given the latents z (B, N, D) before
        it (teacher forcing) and the features h (B, N, H)."""
        previous = jnp.pad(z, ((0, 0), (1, 0), (0, 0)))[:, :-1]
        y, _ = self.lstm(previous, context=h if self.context_dim else None)
        return self._split(self.head(y))

    def noise(self, key: Array, b: int, n: int) -> Array:
        """eps (B, N, D) ~ N(0, I): the standard normals :meth:`sample` scales for step t
        of window i is ``eps[i, t]`` (drawn (N, B, D), as it always was)."""
        return jnp.swapaxes(jax.random.normal(key, (n, b, self.latent_dim), jnp.float32), 0, 1)

    def sample(
        self,
        key: Array,
        h: Array,
        *,
        temperature: float = 1.0,
        seed: Array | None = None,
    ) -> Array:
        """Ancestral draw z (B, N, D) for features h (B, N, H): z_t = mu_t + temperature *
        sigma_t * eps_t, eps ~ N(0, I), one ``lax.scan`` over the N steps. ``seed`` (B, S, D),
        S <= N: the first S latents are given (the prior's state reads them) and the rest
        are drawn after them."""
        b, n = h.shape[:2]
        d = self.latent_dim
        eps = jnp.swapaxes(self.noise(key, b, n), 0, 1)
        given = jnp.zeros((n, b, d), jnp.float32)
        is_given = jnp.zeros((n,), bool)
        if seed is not None:
            s = seed.shape[1]
            given = given.at[:s].set(jnp.swapaxes(seed, 0, 1))
            is_given = is_given.at[:s].set(True)

        def step(carry, inputs):
            state, previous = carry
            h_t, eps_t, given_t, is_given_t = inputs
            inputs_t = jnp.concatenate([previous, h_t], -1) if self.context_dim else previous
            y, state = self.lstm.step(inputs_t, state)
            mean, log_std = self._split(self.head(y))
            z_t = jnp.where(is_given_t, given_t, mean + temperature * jnp.exp(log_std) * eps_t)
            return (state, z_t), z_t

        carry = (self.lstm.initial_carry((b,)), jnp.zeros((b, d), jnp.float32))
        _, z = jax.lax.scan(step, carry, (jnp.swapaxes(h, 0, 1), eps, given, is_given))
        return jnp.swapaxes(z, 0, 1)
