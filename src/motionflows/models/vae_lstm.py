r"""VAE-LSTM: the recurrent variational autoencoder of Habibie et al. (BMVC 2017).

Notation: a window has ``T`` frames (``T`` divisible by 4), ``N = T / 4`` pooled steps,
poses ``x`` (B, T, 63) and controls ``c`` (B, T, 3), both standardised.

**Networks**

* control encoder: ``h = E_c(c)``, (B, N, H) with H = ``control_features`` (128);
* inference network: ``q(z_t | x) = N(mu_t, diag sigma_t^2)``, (B, N, D) with D =
  ``latent_dim`` (128). Default: conv stack 63 -> 64 -> 256 then a linear 1x1 head to
  (mu, log sigma). ``faithful=True``: no head; the 256 ELU outputs are read interleaved
  (even channels mu, odd channels log sigma), so log sigma >= -1, i.e. sigma >= exp(-1);
* modified LSTM cell (paper eqs. 7-9, no output gate, D units)::

      i_t = sigmoid(W_is s + W_ih h_t + b_i)
      f_t = sigmoid(W_fs s + W_fh h_t + b_f)
      c_t = ELU(f_t * (W_cs s) + i_t * (W_ch h_t))

  with ``s = z_t`` in training mode and ``s = c_{t-1}``, ``c_0 = z_1`` in the recurrent
  (test-time) mode. The states ``c_1..c_N`` are the motion canvas (B, N, D);
* decoder: canvas -> up2 -> conv D -> 128, ELU -> up2 -> conv 128 -> 63 = the mean
  ``m(z, c)`` (B, T, 63); ``p(x | z, c) = N(x; m, diag sigma_x^2)`` with a learned
  per-channel ``log sigma_x`` (fixed at 0, unit variance, when ``faithful=True``).

**The generative model that the likelihood bounds refer to.** With the canvas in training
mode, ``c_t`` depends only on ``z_t`` and ``h_t``, so the model is the latent-variable
model ``p(x | c) = \int p(x | z, c) prod_t N(z_t; 0, I) dz`` with one independent standard
normal latent per pooled step. This is exactly the model that the training ELBO is a bound
for, so :meth:`VAELSTM.elbo` and :meth:`VAELSTM.iwae_bound` (q(z|x) over all N pooled
steps, decoder in training mode) are proper lower bounds on ``log p(x | c)`` of this model
(nats per window, standardised space). The sampler of the paper (Algorithm 1, the
recurrent mode) is a *different* generative model, ``z_1 ~ N(0, I)`` and a deterministic
recurrence; its density is not what the bounds measure (see docs/readme/vae_lstm.md).

**Priors.** ``prior="standard"`` (the paper's): p(z) = prod_t N(z_t; 0, I). ``prior="learned"``
(our option, :class:`motionflows.nets.latent_prior.LatentPrior`): p(z | h) = prod_t
N(z_t; mu_t, diag sigma_t^2) with (mu_t, log sigma_t) from an LSTM over z_{<t} and h_{<=t},
so the latents of successive pooled steps, and the gait they decode to, can follow each
other. The KL term of the ELBO is then KL(q(z_t | x) || p(z_t | z_{<t}, h)), analytic per
step at a z_{<t} drawn from q (an unbiased one-sample estimate of KL(q || p)); every bound
above holds with this p(z | h) in place of N(0, I).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from flax import nnx

from motionflows.data.names import CONTROL_DIM, DEFAULT_FPS, POSE_DIM
from motionflows.deprecation import renamed
from motionflows.distributions import Normal
from motionflows.models.validation import check_input, check_length, check_temperature
from motionflows.nets.latent_prior import LatentPrior
from motionflows.nets.vae import ConvDecoder, ConvEncoder, kernel_for_fps

SAMPLERS = ("recurrent", "prior")
"""How :meth:`VAELSTM.sample` draws: the paper's Algorithm 1, or ancestral sampling."""
PRIORS = ("standard", "learned")
"""p(z) of :class:`VAELSTM`: N(0, I) per pooled step (the paper's), or a learned
autoregressive prior (:class:`~motionflows.nets.latent_prior.LatentPrior`)."""


def diag_normal_log_prob(x: jax.Array, mean: jax.Array, log_std: jax.Array) -> jax.Array:
    """Elementwise log N(x; mean, exp(log_std)^2) (sum it yourself)."""
    return Normal((), loc=mean, log_scale=log_std).log_prob(x)


def kl_to_standard_normal(mean: jax.Array, log_std: jax.Array) -> jax.Array:
    """Elementwise KL(N(mean, sigma^2) || N(0, 1)) = (sigma^2 + mean^2 - 1) / 2 - log sigma."""
    return kl_diag_normal(mean, log_std, 0.0, 0.0)


def kl_diag_normal(
    mean: jax.Array, log_std: jax.Array, p_mean: jax.Array, p_log_std: jax.Array
) -> jax.Array:
    """Elementwise KL(N(m, s^2) || N(m_p, s_p^2)) = log(s_p / s) + (s^2 + (m - m_p)^2) /
    (2 s_p^2) - 1/2."""
    ratio = jnp.exp(2.0 * (log_std - p_log_std))
    return 0.5 * (ratio + jnp.square((mean - p_mean) * jnp.exp(-p_log_std)) - 1.0) + (
        p_log_std - log_std
    )


class ModifiedLSTMCell(nnx.Module):
    """The paper's LSTM variant without output gate (eqs. 7-9); ``units`` = latent size.

    ``__call__(s, h)`` computes one state ``c = ELU(f * W_cs s + i * W_ch h)`` for any
    leading shape: s (..., units), h (..., hidden) -> c (..., units).
    """

    def __init__(self, units: int, hidden: int, *, rngs: nnx.Rngs):
        self.units = int(units)
        self.from_s = nnx.Linear(units, 3 * units, use_bias=False, rngs=rngs)
        self.from_h = nnx.Linear(hidden, 3 * units, use_bias=False, rngs=rngs)
        self.gate_bias = nnx.Param(jnp.zeros((2 * units,), jnp.float32))

    def __call__(self, s: jax.Array, h: jax.Array) -> jax.Array:
        u = self.units
        a, b = self.from_s(s), self.from_h(h)
        gates = jax.nn.sigmoid(a[..., : 2 * u] + b[..., : 2 * u] + self.gate_bias[...])
        i, f = gates[..., :u], gates[..., u:]
        return jax.nn.elu(f * a[..., 2 * u :] + i * b[..., 2 * u :])


class VAELSTM(nnx.Module):
    """The VAE-LSTM model. Build with :meth:`__init__`; all methods are pure JAX.

    Args:
      kernel: temporal conv width (odd); None = ``nets.vae.kernel_for_fps(fps)``, the
        paper's 25 frames at 60 fps (about 0.4 s) scaled to the frame rate (9 at 20 fps).
      fps: frame rate of the data, used only when ``kernel`` is None.
      latent_dim: D, the size of z_t and of the LSTM state (they must match, because the
        test-time recurrence feeds c_{t-1} where training feeds z_t).
      control_hidden / control_features: widths of the control encoder (64, 128).
      pose_hidden / pose_features: widths of the inference network (64, 256); in faithful
        mode ``pose_features`` must be ``2 * latent_dim``.
      decoder_hidden: width of the decoder's hidden conv (128).
      dropout: rate on the encoders' conv inputs during training (0.2).
      faithful: reproduce the authors' code (sigma floor, random unpooling, unit-variance
        output) instead of the defaults.
      learn_variance: learn a per-channel output log-std (default True; ignored if
        faithful, which uses unit variance).
      iwae_samples: the K values that ``experiments.vae_lstm.evaluate`` reports.
      iwae_chunk: how many importance samples run vectorised at once.
      l1_weight: weight of the L1 penalty in the experiment's training loss (0.1).
      elbo_samples: z draws averaged in the experiment's reported ELBO.
      sampler_iwae_samples: the K values of the sampler-model bound that ``evaluate``
        reports (``sampler_iwae_<K>``; empty = none).
      sampler: how :meth:`sample` draws. ``"recurrent"`` (the paper's Algorithm 1): one
        z_1 ~ p(z_1), then the canvas recurs on itself, c_t = cell(c_{t-1}, h_t), so only
        z_1 is random. ``"prior"``: the model that training fits and the ELBO bounds,
        z ~ p(z) (every pooled step) and c_t = cell(z_t, h_t) (ancestral sampling of
        p(z) p(x | z, c), decoder mean).
      prior: p(z): ``"standard"`` (N(0, I) per pooled step, the paper's) or ``"learned"``
        (an LSTM over the earlier latents and the encoded control gives each step's
        N(mu_t, diag sigma_t^2); :class:`~motionflows.nets.latent_prior.LatentPrior`).
      prior_hidden: the learned prior's LSTM units.
      prior_reads_control: whether the learned prior reads the encoded control h (True), or
        only the earlier latents, p(z_t | z_{<t}) (False).
    """

    frame_multiple = 4
    """Every window length T is a multiple of this: the encoders pool time twice by 2."""

    @staticmethod
    def _check_length(length: int) -> None:
        multiple = VAELSTM.frame_multiple
        check_length(
            length,
            multiple,
            f"VAE-LSTM pools time twice by 2, so the window length must be a positive "
            f"multiple of {multiple}",
        )

    def __init__(
        self,
        *,
        kernel: int | None = None,
        fps: float = DEFAULT_FPS,
        latent_dim: int = 128,
        control_hidden: int = 64,
        control_features: int = 128,
        pose_hidden: int = 64,
        pose_features: int = 256,
        decoder_hidden: int = 128,
        dropout: float = 0.2,
        faithful: bool = False,
        learn_variance: bool = True,
        iwae_samples: tuple[int, ...] = (1, 10, 100),
        iwae_chunk: int = 10,
        l1_weight: float = 0.1,
        elbo_samples: int = 1,
        sampler_iwae_samples: tuple[int, ...] = (),
        sampler: str = "recurrent",
        prior: str = "standard",
        prior_hidden: int = 128,
        prior_reads_control: bool = True,
        rngs: nnx.Rngs,
    ):
        if kernel is None:
            kernel = kernel_for_fps(fps)
        if kernel < 1 or kernel % 2 == 0:
            raise ValueError(f"kernel must be a positive odd integer, got {kernel}")
        if faithful and pose_features != 2 * latent_dim:
            raise ValueError(
                f"faithful=True reads the inference network's {pose_features} outputs as "
                f"interleaved (mean, log-std) pairs, so pose_features must be 2 * latent_dim "
                f"= {2 * latent_dim}"
            )
        if not 0.0 <= dropout < 1.0:
            raise ValueError(f"dropout must be in [0, 1), got {dropout}")
        if sampler not in SAMPLERS:
            raise ValueError(f"sampler must be one of {SAMPLERS}, got {sampler!r}")
        if prior not in PRIORS:
            raise ValueError(f"prior must be one of {PRIORS}, got {prior!r}")
        self.sampler = sampler
        self.prior = prior
        self.kernel = int(kernel)
        self.fps = float(fps)
        self.latent_dim = int(latent_dim)
        self.faithful = bool(faithful)
        self.learn_variance = bool(learn_variance) and not faithful
        self.iwae_samples = tuple(int(k) for k in iwae_samples)
        self.iwae_chunk = int(iwae_chunk)
        self.l1_weight = float(l1_weight)
        self.elbo_samples = int(elbo_samples)
        self.sampler_iwae_samples = tuple(int(k) for k in sampler_iwae_samples)
        self.control_encoder = ConvEncoder(
            CONTROL_DIM, control_hidden, control_features, kernel, dropout=dropout, rngs=rngs
        )
        self.pose_encoder = ConvEncoder(
            POSE_DIM, pose_hidden, pose_features, kernel, dropout=dropout, rngs=rngs
        )
        if not faithful:
            self.posterior_head = nnx.Linear(pose_features, 2 * latent_dim, rngs=rngs)
        self.cell = ModifiedLSTMCell(latent_dim, control_features, rngs=rngs)
        self.decoder = ConvDecoder(
            latent_dim, decoder_hidden, POSE_DIM, kernel, random_unpool=faithful, rngs=rngs
        )
        self.out_log_std = nnx.Param(jnp.zeros((POSE_DIM,), jnp.float32))
        if prior == "learned":
            context = control_features if prior_reads_control else 0
            self.latent_prior_net = LatentPrior(latent_dim, context, prior_hidden, rngs=rngs)

    def conv_kernel_sizes(self) -> set[int]:
        """The temporal widths of every conv layer (one value: ``kernel``)."""
        convs = [self.control_encoder.conv1, self.control_encoder.conv2,
                 self.pose_encoder.conv1, self.pose_encoder.conv2,
                 self.decoder.conv1, self.decoder.conv2]  # fmt: skip
        return {int(conv.kernel_shape[0]) for conv in convs}

    # ------------------------------------------------------------------ validation
    @staticmethod
    def _check(
        x: jax.Array | None, c: jax.Array | None, where: str = "VAELSTM"
    ) -> tuple[jax.Array | None, jax.Array | None]:
        """Shape checks with messages for people (shapes are static, so this is jit-safe),
        then dtype, emptiness and finiteness (``validation.check_input``); returns (x, c)
        as float32."""
        for name, a in (("control", c), ("pose", x)):
            if a is not None and getattr(a, "ndim", None) is None:
                raise ValueError(f"{where}: {name} must be an array, got {type(a).__name__}")
        if c is not None:
            if c.ndim != 3 or c.shape[-1] != CONTROL_DIM:
                raise ValueError(
                    f"control must have shape (B, T, {CONTROL_DIM}), got {tuple(c.shape)}"
                )
            VAELSTM._check_length(c.shape[1])
        if x is not None:
            if x.ndim != 3 or x.shape[-1] != POSE_DIM:
                raise ValueError(f"pose must have shape (B, T, {POSE_DIM}), got {tuple(x.shape)}")
            VAELSTM._check_length(x.shape[1])
            if c is not None and x.shape[:2] != c.shape[:2]:
                raise ValueError(
                    f"pose {tuple(x.shape)} and control {tuple(c.shape)} must share (B, T)"
                )
            x = check_input(x, "pose", where)
        if c is not None:
            c = check_input(c, "control", where)
        return x, c

    # ------------------------------------------------------------------ networks
    def encode_control(self, c: jax.Array, key: jax.Array | None = None) -> jax.Array:
        """h = E_c(c): (B, T, 3) -> (B, T/4, control_features). ``key`` enables dropout."""
        return self.control_encoder(c, key)

    def posterior(self, x: jax.Array, key: jax.Array | None = None) -> tuple[jax.Array, jax.Array]:
        """q(z | x): (B, T, 63) -> (mean, log_std), each (B, T/4, latent_dim)."""
        y = self.pose_encoder(x, key)
        if self.faithful:
            return y[..., 0::2], y[..., 1::2]  # after the ELU: log_std >= -1
        out = self.posterior_head(y)
        return out[..., : self.latent_dim], out[..., self.latent_dim :]

    def canvas(self, z: jax.Array, h: jax.Array, *, recurrent: bool = False) -> jax.Array:
        """The motion canvas (B, N, D) from latents z (B, N, D) and encoded control h (B, N, H).

        ``recurrent=False`` (training mode): c_t = cell(s=z_t, h_t) at every step.
        ``recurrent=True`` (test mode, Algorithm 1): c_0 = z_1 and c_t = cell(s=c_{t-1}, h_t),
        a ``lax.scan`` over pooled steps; only z[:, 0] is read.
        """
        if not recurrent:
            return self.cell(z, h)

        def step(prev, h_t):
            c_t = self.cell(prev, h_t)
            return c_t, c_t

        _, cs = jax.lax.scan(step, z[:, 0], jnp.swapaxes(h, 0, 1))
        return jnp.swapaxes(cs, 0, 1)

    def decode(self, canvas: jax.Array, key: jax.Array | None = None) -> jax.Array:
        """Decoder mean m: (B, N, D) -> (B, 4N, 63). ``key`` only matters in faithful mode
        (random unpooling: fresh mask per example; None = the fixed evaluation mask)."""
        return self.decoder(canvas, key)

    def output_log_std(self) -> jax.Array:
        """Per-channel log sigma_x (63,): learned, or zeros (unit variance)."""
        if self.learn_variance:
            return self.out_log_std[...]
        return jnp.zeros((POSE_DIM,), jnp.float32)

    def latent_prior(self, z: jax.Array, h: jax.Array) -> Normal:
        """p(z | h) over the (N, D) latents of a window, evaluated at the latents z (B, N, D)
        with the encoded control h (B, N, H): N(0, I) (``prior="standard"``), or the learned
        prior's N(mu_t, diag sigma_t^2), each step's parameters from z_{<t} and h_{<=t}."""
        if self.prior == "standard":
            return Normal((None, self.latent_dim))
        mean, log_std = self.latent_prior_net(z, h)
        return Normal((None, self.latent_dim), loc=mean, log_scale=log_std)

    def _kl(self, mu, log_std, z, h) -> jax.Array:
        """KL(q(z_t | x) || p(z_t | z_{<t}, h)) summed over steps and latents (B,), at the
        earlier latents z drawn from q (analytic per step)."""
        if self.prior == "standard":
            return kl_to_standard_normal(mu, log_std).sum(axis=(1, 2))
        p_mean, p_log_std = self.latent_prior_net(z, h)
        return kl_diag_normal(mu, log_std, p_mean, p_log_std).sum(axis=(1, 2))

    def _draw_latents(self, key, h, temperature, seed=None) -> jax.Array:
        """z (B, N, D) from the prior (std scaled by ``temperature``); the first S steps are
        ``seed`` (B, S, D) when given."""
        if self.prior == "learned":
            return self.latent_prior_net.sample(key, h, temperature=temperature, seed=seed)
        z = temperature * self._prior_noise(key, *h.shape[:2])
        return z if seed is None else z.at[:, : seed.shape[1]].set(seed)

    def _prior_noise(self, key, b: int, n: int) -> jax.Array:
        """eps (B, N, D): the standard normals :meth:`_draw_latents` draws for pooled step t
        of window i from ``key`` (the learned prior's layout or the standard prior's)."""
        if self.prior == "learned":
            return self.latent_prior_net.noise(key, b, n)
        return jax.random.normal(key, (b, n, self.latent_dim), jnp.float32)

    def log_likelihood(self, x: jax.Array, mean: jax.Array) -> jax.Array:
        """log p(x | z, c) summed over frames and channels: (B, T, 63) -> (B,)."""
        return Normal((None, POSE_DIM), loc=mean, log_scale=self.output_log_std()).log_prob(x)

    # ------------------------------------------------------------------ objectives
    def elbo_terms(
        self, x: jax.Array, c: jax.Array, key: jax.Array, *, train: bool = False
    ) -> dict[str, jax.Array]:
        """One-sample ELBO pieces per window (B,): ``log_lik`` = log p(x|z,c) at z ~ q,
        ``kl`` = sum over pooled steps and latents of KL(q(z_t|x) || p(z_t | z_{<t}, h))
        (analytic per step; N(0, I) with the standard prior),
        ``elbo`` = log_lik - kl. ``train=True`` enables dropout (and fresh unpool masks)."""
        x, c = self._check(x, c, "VAELSTM.elbo")
        kd_c, kd_x, kz, ku = jax.random.split(key, 4)
        if not train:
            kd_c = kd_x = ku = None
        h = self.encode_control(c, kd_c)
        mu, log_std = self.posterior(x, kd_x)
        z = mu + jnp.exp(log_std) * jax.random.normal(kz, mu.shape, mu.dtype)
        mean = self.decode(self.canvas(z, h), ku)
        log_lik = self.log_likelihood(x, mean)
        kl = self._kl(mu, log_std, z, h)
        return {"log_lik": log_lik, "kl": kl, "elbo": log_lik - kl}

    def elbo(
        self, x: jax.Array, c: jax.Array, key: jax.Array | None = None, *, num_samples: int = 1
    ) -> jax.Array:
        """ELBO per window (B,), nats, standardised space, averaged over ``num_samples`` draws
        of z ~ q(z|x) (an unbiased estimate of E_q[log p(x|z,c)] - KL). Evaluation mode.
        ``key`` None uses ``jax.random.key(0)``: a fixed, reproducible draw."""
        if num_samples < 1:
            raise ValueError(f"num_samples must be >= 1, got {num_samples}")
        x, c = self._check(x, c, "VAELSTM.elbo")
        keys = jax.random.split(jax.random.key(0) if key is None else key, num_samples)
        return jax.lax.map(lambda k: self.elbo_terms(x, c, k)["elbo"], keys).mean(axis=0)

    def log_weights(self, x: jax.Array, c: jax.Array, key: jax.Array, num_samples: int):
        """Importance log-weights log p(x|z_k,c) + log p(z_k|h) - log q(z_k|x), z_k ~ q(z|x):
        (num_samples, B). Evaluation mode (no dropout); the decoder is in training mode
        (s = z_t), the model the bounds refer to."""
        x, c = self._check(x, c, "VAELSTM.iwae_bound")
        h = self.encode_control(c)
        mu, log_std = self.posterior(x)
        standard = Normal((None, self.latent_dim))

        def one(k):
            eps = jax.random.normal(k, mu.shape, mu.dtype)
            z = mu + jnp.exp(log_std) * eps
            # q(z | x) through the reparameterisation: log N(eps; 0, I) - sum(log sigma)
            log_q = standard.log_prob(eps) - log_std.sum(axis=(1, 2))
            log_p = self.latent_prior(z, h).log_prob(z)
            return self.log_likelihood(x, self.decode(self.canvas(z, h))) + log_p - log_q

        keys = jax.random.split(key, num_samples)
        return jax.lax.map(one, keys, batch_size=min(self.iwae_chunk, num_samples))

    def iwae_bound(
        self, x: jax.Array, c: jax.Array, key: jax.Array, *, num_samples: int = 10
    ) -> jax.Array:
        """Importance-weighted bound (Burda et al. 2016) per window (B,), nats, standardised:
        L_K = log (1/K) sum_k w_k <= log p(x | c); E[L_K] rises with K, L_1 = ELBO in
        expectation."""
        if num_samples < 1:
            raise ValueError(f"num_samples must be >= 1, got {num_samples}")
        logw = self.log_weights(x, c, key, num_samples)
        return jax.scipy.special.logsumexp(logw, axis=0) - math.log(num_samples)

    def sampler_log_weights(self, x: jax.Array, c: jax.Array, key: jax.Array, num_samples: int):
        """Importance log-weights for the *sampler's* model (Algorithm 1 plus the output
        noise): p_rec(x | c) = int p(z_1 | h) N(x; m_rec(z_1, c), diag sigma_x^2) dz_1,
        with m_rec the decoder of the recurrent canvas. Proposal: q(z_1 | x), the
        inference network's first pooled step. Returns (num_samples, B).

        With ``sampler="prior"`` the sampler's model is the trained one, so these are the
        weights of :meth:`log_weights` (proposal q(z | x) over all pooled steps)."""
        if self.sampler == "prior":
            return self.log_weights(x, c, key, num_samples)
        x, c = self._check(x, c, "VAELSTM.sampler_iwae_bound")
        h = self.encode_control(c)
        mu, log_std = self.posterior(x)
        mu1, ls1 = mu[:, :1], log_std[:, :1]
        rest = jnp.zeros((x.shape[0], h.shape[1] - 1, self.latent_dim), mu.dtype)
        standard = Normal((None, self.latent_dim))

        def one(k):
            eps = jax.random.normal(k, mu1.shape, mu1.dtype)
            z1 = mu1 + jnp.exp(ls1) * eps
            log_q = standard.log_prob(eps) - ls1.sum(axis=(1, 2))
            log_p = self.latent_prior(z1, h[:, :1]).log_prob(z1)
            canvas = self.canvas(jnp.concatenate([z1, rest], axis=1), h, recurrent=True)
            return self.log_likelihood(x, self.decode(canvas)) + log_p - log_q

        keys = jax.random.split(key, num_samples)
        return jax.lax.map(one, keys, batch_size=min(self.iwae_chunk, num_samples))

    def sampler_iwae_bound(
        self, x: jax.Array, c: jax.Array, key: jax.Array, *, num_samples: int = 10
    ) -> jax.Array:
        """IWAE lower bound (B,) on the density of the sampler's model with the learned
        output noise (see :meth:`sampler_log_weights`: Algorithm 1's p_rec(x | c), or the
        trained model for ``sampler="prior"``). Nats, standardised."""
        if num_samples < 1:
            raise ValueError(f"num_samples must be >= 1, got {num_samples}")
        logw = self.sampler_log_weights(x, c, key, num_samples)
        return jax.scipy.special.logsumexp(logw, axis=0) - math.log(num_samples)

    # ------------------------------------------------------------------ sampling
    def sample(
        self,
        key: jax.Array,
        control: jax.Array,
        *,
        temperature: float = 1.0,
        seed_history: jax.Array | None = None,
        seed_frames: jax.Array | None = None,
    ) -> jax.Array:
        """Poses for a control, by the model's ``sampler``: control (B, T, 3) -> poses
        (B, T, 63), standardised; the output is the decoder mean (no observation noise).

        ``"recurrent"`` (Algorithm 1): z_1 ~ p(z_1 | h) (std scaled by ``temperature``),
        recurrent canvas. ``"prior"``: z ~ p(z | h) at all T/4 pooled steps (the learned
        prior draws them in order; std scaled by ``temperature``), the training-mode canvas
        c_t = cell(z_t, h_t). With ``seed_history`` (B, S, 63)
        (``seed_frames=`` is its deprecated old name), S a positive multiple of 4 and <= T,
        the latents of the first S/4 steps are drawn from the posterior q(z | seed frames)
        (std scaled by ``temperature``; the recurrent sampler reads only z_1); the returned
        frames are all decoded (the seed is not pasted in). Window i's draw depends on B for
        the same key (the learned prior draws its normals (T/4, B, D)); the bench's and the
        shipped model's numbers were measured so, and MoGlow's does not.
        """
        seed_history = renamed(
            "VAELSTM.sample",
            old="seed_frames",
            new="seed_history",
            old_value=seed_frames,
            new_value=seed_history,
            default=None,
        )
        _, control = self._check(None, control, "VAELSTM.sample")
        check_temperature(temperature, "VAELSTM.sample")
        b = control.shape[0]
        h = self.encode_control(control)
        n = h.shape[1]
        if self.sampler == "prior":
            return self._sample_prior(key, h, temperature, seed_history)
        if seed_history is None:
            z1 = self._draw_latents(key, h[:, :1], temperature)
        else:
            eps = jax.random.normal(key, (b, 1, self.latent_dim), jnp.float32)
            mu, log_std = self._seed_posterior(seed_history, b, control.shape[1])
            z1 = mu[:, :1] + temperature * jnp.exp(log_std[:, :1]) * eps
        z = jnp.concatenate([z1, jnp.zeros((b, n - 1, self.latent_dim), z1.dtype)], axis=1)
        return self.decode(self.canvas(z, h, recurrent=True))

    def _seed_posterior(self, seed_history: jax.Array, b: int, frames: int):
        """q(z | seed frames): (mean, log_std), each (B, S/4, D), after checking the seed
        against the batch ``b`` and the control's ``frames``."""
        if seed_history.ndim != 3 or seed_history.shape[0] != b:
            raise ValueError(
                f"seed_history must have shape (B={b}, S, {POSE_DIM}), "
                f"got {tuple(seed_history.shape)}"
            )
        seed_history, _ = self._check(seed_history, None, "VAELSTM.sample")
        if seed_history.shape[1] > frames:
            raise ValueError("seed_history must not be longer than the control")
        return self.posterior(seed_history)

    def _sample_prior(self, key, h, temperature, seed_history) -> jax.Array:
        """The ``"prior"`` sampler: z (B, N, D) ~ p(z | h) (std scaled by ``temperature``),
        the first S/4 steps from q(z | seed) when seeded; training-mode canvas; decoder
        mean."""
        b, n = h.shape[:2]
        seed = None
        if seed_history is not None:
            mu, log_std = self._seed_posterior(seed_history, b, 4 * n)
            # the draws the prior makes for these steps (it then takes the seed's instead), so
            # no drawn step reuses a seed's noise (the learned prior draws in another layout)
            eps = self._prior_noise(key, b, n)[:, : mu.shape[1]]
            seed = mu + jnp.exp(log_std) * (temperature * eps)
        return self.decode(self.canvas(self._draw_latents(key, h, temperature, seed), h))

    def reconstruct(self, x: jax.Array, c: jax.Array) -> jax.Array:
        """Decoder mean at the posterior mean z = mu(x), training-mode canvas: (B, T, 63)."""
        x, c = self._check(x, c, "VAELSTM.reconstruct")
        mu, _ = self.posterior(x)
        return self.decode(self.canvas(mu, self.encode_control(c)))


def l1_penalty(model: nnx.Module) -> jax.Array:
    """sum over weight tensors (conv and linear kernels) of mean |w|. Biases and the output
    log-std are not penalised."""
    total = jnp.zeros((), jnp.float32)
    for path, leaf in jax.tree_util.tree_leaves_with_path(nnx.state(model, nnx.Param)):
        names = [getattr(p, "key", getattr(p, "name", None)) for p in path]
        if "kernel" in names:
            total = total + jnp.mean(jnp.abs(leaf))
    return total
