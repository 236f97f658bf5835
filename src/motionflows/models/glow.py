"""Fixed-length Glow over motion windows, unconditional or control-conditioned.

The non-causal reference model of the MoGlow paper (Henter, Alexanderson & Beskow 2020,
Sec. 3): a multi-scale Glow (Kingma & Dhariwal 2018) whose "image" is a whole window of
poses x (B, T, D) (D = 63), with time playing the role of the spatial axis.

Structure, data -> latent (``inverse_and_log_det``/``encode``), for levels l = 0..L-1::

    h = squeeze_time(h)             (T_l, d) -> (T_l / 2, 2 d): frames 2t and 2t+1 side by side
    c = squeeze_time(c)             the control is squeezed alongside (never split)
    h = K x [ActNorm -> LU 1x1 (InvertibleLinear) -> AffineCoupling(ConvNet)]   (a ``Scan``)
    if l < L - 1:  h, z_l = Split(h)   z_l (T_l/2, floor(2d/2)) goes to the base density
    z_L = h  (after the last level)

The coupling net (:class:`motionflows.nets.conv.ConvNet`) sees ``[x_a, c_l]``
concatenated on channels: conv3 -> ReLU -> conv1 -> ReLU -> zero-init conv3 over time.
The split channel counts are exact (``Split`` keeps ceil(d/2), factors out floor(d/2)); no
padding channels exist, so every one of the T * D latent numbers carries probability mass.

Base density. ``prior="standard"`` (the paper): every z_l and z_L is i.i.d. N(0, 1).
``prior="learned"`` (glow-pytorch's ``Split2d``): each factored part gets a conditional
diagonal Gaussian N(mu, exp(logs)^2) with (mu, logs) = zero-init conv3([kept, c_l]) (the
control is included when the model is conditional). We write it as one more affine bijector
eps_l = (z_l - mu) * exp(-logs) (log-det -sum(logs)), so in both cases the *latents* this
class exposes are standard normal and the whole model is one bijection x <-> eps.

Latents. ``encode`` returns one flat array (..., T * D): the factored parts in level order
(each flattened time-major from (T_l, d_l)) followed by the last level's output. Use
:meth:`Glow.latent_parts` to cut it into its (..., T_l, d_l) pieces.

Flowing the change (``residual=True``, our option, not the paper's). Before the first
squeeze the window is taken to its first frame and its frame-to-frame changes,
:class:`motionflows.bijectors.Difference` (u_0 = x_0, u_t = x_t - x_{t-1}, log-det 0), and
each part gets its own ActNorm (``first_norm`` on u_0, ``change_norm`` on u_1..u_{T-1}),
since a change is several times smaller than a pose: log-det sum(logs_first) + (T - 1)
sum(logs_change). The multi-scale flow above then models the normalised changes, and a
sample is their cumulative sum. ``residual_decay`` a < 1 takes the leaky change u_t = x_t -
a x_{t-1} instead (still log-det 0), whose sum x_t = sum_k a^(t-k) u_k forgets a drawn
change's error within ~1 / (1 - a) frames. MoGlow's ``residual`` is the same idea one frame
at a time.

Likelihood: the model is the distribution ``Transformed(Normal((T * D,)), glow)``
(:meth:`Glow.distribution`), so log p(x | c) = log N(eps; 0, I) + log|det d eps / d x| in
the units of x (the model is trained on standardised data, so those are standardised units).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from flax import nnx

from motionflows.bijectors import (
    ActNorm,
    AdditiveCoupling,
    AffineCoupling,
    Chain,
    Difference,
    InvertibleLinear,
    Scan,
    Split,
    squeeze_time,
    unsqueeze_time,
)
from motionflows.data.names import CONTROL_DIM, DEFAULT_WINDOW, POSE_DIM
from motionflows.deprecation import renamed
from motionflows.distributions import Normal, Transformed
from motionflows.models.validation import check_input, check_length, check_temperature
from motionflows.nets.conv import ConvNet, TimeConv
from motionflows.nets.precision import compute_dtype_name

Array = jax.Array

__all__ = ["Glow", "standard_normal_log_prob"]

PRIORS = ("standard", "learned")
COUPLINGS = ("affine", "additive")


def standard_normal_log_prob(z: Array) -> Array:
    """sum over the last axis of log N(z; 0, 1): (..., N) -> (...)."""
    return Normal((None,)).log_prob(z)


class Glow(nnx.Module):
    """Multi-scale Glow over fixed-length windows (..., T, D); see the module docstring.

    Args:
      pose_dim: channels D of a frame (63).
      levels: L, number of squeeze levels; T must be divisible by 2**L.
      K: flow steps per level (run by ``Scan``; 32); ``steps=`` is its deprecated old name.
      hidden: width of the coupling nets' hidden convolutions (512 in the paper).
      control_dim: channels of the control (3); 0 or None = unconditional model.
      conditional: shorthand; False forces control_dim = 0 (None: decided by control_dim).
      prior: "standard" (paper) or "learned" (glow-pytorch's conditional split prior).
      compute_dtype: None/"float32", or "bfloat16" for the coupling nets' convolutions.
      coupling: "affine" (paper: ``AffineCoupling``, whose scale lies in (eps, 1 + eps), so
        the latent -> data direction can only amplify) or "additive" (``AdditiveCoupling``,
        volume-preserving: only ActNorm and the 1x1 maps scale a sample).
      coupling_eps: floor of the affine coupling scale (see ``AffineCoupling``).
      length: the window length T that unconditional ``sample`` draws by default (a
        multiple of 2**levels; None = 80 frames, 4 s at 20 fps); ``log_prob`` accepts any
        such T.
      residual: flow the window's first frame and its frame-to-frame changes, each part
        with its own ActNorm, instead of the poses (module docstring); exact, log-det of
        the ActNorms only.
      residual_decay: with ``residual``, the changes are u_t = x_t - a x_{t-1} with this
        a in (0, 1] (``Difference(decay=a)``): 1 the plain change; below 1 a drawn
        change's error fades with time constant 1 / (1 - a) frames instead of staying.
      rngs: ``nnx.Rngs`` for parameter initialisation.

    Parameters start so that every coupling is a fixed scaling and every learned prior is
    N(0, 1); call :func:`motionflows.bijectors.initialize_from_data` before training.
    """

    def __init__(
        self,
        pose_dim: int = POSE_DIM,
        *,
        levels: int = 4,
        K: int | None = None,
        hidden: int = 512,
        control_dim: int | None = CONTROL_DIM,
        conditional: bool | None = None,
        prior: str = "standard",
        compute_dtype: Any = None,
        coupling: str = "affine",
        coupling_eps: float = 1e-6,
        length: int | None = None,
        residual: bool = False,
        residual_decay: float = 1.0,
        rngs: nnx.Rngs,
        steps: int | None = None,
    ):
        K = renamed("Glow", old="steps", new="K", old_value=steps, new_value=K, default=32)
        if conditional is not None:
            control_dim = (control_dim or CONTROL_DIM) if conditional else 0
        if int(levels) < 1 or int(K) < 1 or int(hidden) < 1:
            raise ValueError(
                f"Glow needs levels >= 1, K >= 1 and hidden >= 1, got levels={levels}, "
                f"K={K}, hidden={hidden}"
            )
        if int(pose_dim) < 1:
            raise ValueError(f"Glow needs pose_dim >= 1, got {pose_dim}")
        if prior not in PRIORS:
            raise ValueError(f"Glow: prior must be one of {PRIORS}, got {prior!r}")
        if coupling not in COUPLINGS:
            raise ValueError(f"Glow: coupling must be one of {COUPLINGS}, got {coupling!r}")
        if float(residual_decay) != 1.0 and not residual:
            raise ValueError("Glow: residual_decay needs residual=True (it shapes the change)")
        self.pose_dim = int(pose_dim)
        self.levels = int(levels)
        self.K = int(K)
        self.hidden = int(hidden)
        self.control_dim = int(control_dim or 0)
        self.prior = prior
        self.compute_dtype = compute_dtype_name(compute_dtype, "Glow")
        self.coupling = coupling
        self.coupling_eps = float(coupling_eps)
        self.length = DEFAULT_WINDOW if length is None else int(length)  # default sample T
        if length is not None:
            self._check_length(self.length)

        flows, splits, priors = [], [], []
        kept = self.pose_dim
        for level in range(self.levels):
            d = 2 * kept
            ctx = self.control_dim * 2 ** (level + 1)
            flows.append(Scan(self._step_factory(d, ctx), self.K, rngs=rngs.params()))
            if level < self.levels - 1:
                split = Split(d)
                splits.append(split)
                kept = split.kept_channels
                if prior == "learned":
                    priors.append(
                        TimeConv(
                            split.kept_channels + ctx,
                            2 * split.factored_channels,
                            3,
                            zero_init=True,
                            rngs=rngs,
                        )
                    )
        self.flows = nnx.List(flows)
        self.splits = nnx.List(splits)
        self.priors = nnx.List(priors)
        self.residual = bool(residual)
        if self.residual:  # built last: they draw nothing, so the flows' draws do not move
            self.difference = Difference(self.pose_dim, decay=residual_decay)
            self.first_norm = ActNorm(self.pose_dim)
            self.change_norm = ActNorm(self.pose_dim)

    def _step_factory(self, channels: int, context_channels: int):
        hidden, eps, dtype = self.hidden, self.coupling_eps, self.compute_dtype
        n_a = channels // 2
        n_b = channels - n_a
        additive = self.coupling == "additive"

        def make(rngs: nnx.Rngs):
            net = ConvNet(
                n_a,
                n_b if additive else 2 * n_b,
                hidden,
                context_features=context_channels,
                compute_dtype=dtype,
                rngs=rngs,
            )
            # Chain order is latent -> data; data -> latent runs ActNorm, 1x1, coupling.
            return Chain.from_data_to_latent(
                [
                    ActNorm(channels),
                    InvertibleLinear(channels, rngs=rngs),
                    AdditiveCoupling(channels, net)
                    if additive
                    else AffineCoupling(channels, net, eps=eps),
                ]
            )

        return make

    # ------------------------------------------------------------------ shapes and checks

    @property
    def conditional(self) -> bool:
        """Whether the model takes a control signal."""
        return self.control_dim > 0

    def latent_shapes(self, length: int) -> list[tuple[int, int]]:
        """(T_l, d_l) of each latent part for windows of ``length`` frames, in latent order."""
        self._check_length(length)
        shapes = []
        t, kept = length, self.pose_dim
        for level in range(self.levels):
            t //= 2
            d = 2 * kept
            if level < self.levels - 1:
                split = self.splits[level]
                shapes.append((t, split.factored_channels))
                kept = split.kept_channels
            else:
                shapes.append((t, d))
        return shapes

    def latent_parts(self, z: Array) -> list[Array]:
        """Cut flat latents (..., T * D) into their parts [(..., T_l, d_l), ...]."""
        length = self._length_from_latent(z)
        parts, start = [], 0
        for t, d in self.latent_shapes(length):
            n = t * d
            parts.append(jnp.reshape(z[..., start : start + n], z.shape[:-1] + (t, d)))
            start += n
        return parts

    @property
    def frame_multiple(self) -> int:
        """Every window length T is a multiple of this: 2**levels (each level squeezes time
        by 2)."""
        return 2**self.levels

    def _check_length(self, length: int) -> None:
        check_length(
            length,
            self.frame_multiple,
            f"Glow with {self.levels} levels needs windows whose length T is a positive "
            f"multiple of 2**{self.levels} = {self.frame_multiple}",
            " (a run's window is data.window), or fewer levels",
        )

    def _length_from_latent(self, z: Array) -> int:
        if getattr(z, "ndim", 0) < 1 or z.shape[-1] % self.pose_dim:
            raise ValueError(
                f"Glow latents must be flat arrays (..., T * {self.pose_dim}), got shape "
                f"{getattr(z, 'shape', type(z))}"
            )
        length = z.shape[-1] // self.pose_dim
        self._check_length(length)
        return length

    def _check_pose(self, x: Any, name: str = "x") -> Array:
        shape = getattr(x, "shape", None)
        if shape is None or len(shape) < 2 or shape[-1] != self.pose_dim:
            raise ValueError(
                f"Glow expects {name} of shape (..., T, {self.pose_dim}) (batch, frames, pose "
                f"channels), got {shape if shape is not None else type(x).__name__}"
            )
        self._check_length(shape[-2])
        return check_input(x, name, "Glow")

    def _check_control(self, control: Any, batch: tuple, length: int) -> Array | None:
        if not self.conditional:
            if control is not None:
                raise ValueError(
                    "This Glow is unconditional (control_dim=0) but a control was passed; "
                    "pass control=None or build the model with control_dim=3"
                )
            return None
        if control is None:
            raise ValueError(
                f"This Glow is conditional: pass a control of shape (..., T, {self.control_dim}) "
                "aligned with the poses"
            )
        shape = getattr(control, "shape", None)
        if shape is None or len(shape) < 2 or tuple(shape[-2:]) != (length, self.control_dim):
            raise ValueError(
                f"Glow expects control of shape (..., {length}, {self.control_dim}) aligned "
                f"with the poses, got {shape if shape is not None else type(control).__name__}"
            )
        try:
            jnp.broadcast_shapes(tuple(shape[:-2]), tuple(batch))
        except ValueError:
            raise ValueError(
                f"Glow: control batch shape {tuple(shape[:-2])} does not match the pose batch "
                f"shape {tuple(batch)}"
            ) from None
        control = check_input(control, "control", "Glow")
        return jnp.broadcast_to(control, tuple(batch) + (length, self.control_dim))

    # ------------------------------------------------------------------ the bijection

    def _prior_params(self, level: int, kept: Array, ctx: Array | None) -> tuple[Array, Array]:
        h = kept if ctx is None else jnp.concatenate([kept, ctx], axis=-1)
        out = self.priors[level](h)
        return out[..., 0::2], out[..., 1::2]

    def inverse_and_log_det(self, x: Array, *, context: Array | None = None):
        """Data -> latent: x (..., T, D) -> (eps (..., T * D), log|det d eps / d x| (...)).

        ``context`` is the control (..., T, control_dim) (None for an unconditional model).
        """
        x = self._check_pose(x)
        batch, length = x.shape[:-2], x.shape[-2]
        c = self._check_control(context, batch, length)
        h, total, parts = x, jnp.zeros(batch, jnp.float32), []
        if self.residual:
            h, total = self._changes_from_poses(x)
        for level in range(self.levels):
            h = squeeze_time(h)
            c = None if c is None else squeeze_time(c)
            h, ld = self.flows[level].inverse_and_log_det(h, context=c)
            total = total + ld
            if level < self.levels - 1:
                h, z = self.splits[level].split(h)
                if self.prior == "learned":
                    mean, logs = self._prior_params(level, h, c)
                    z = (z - mean) * jnp.exp(-logs)
                    total = total - jnp.sum(logs, axis=(-2, -1))
                parts.append(z)
        parts.append(h)
        flat = jnp.concatenate([jnp.reshape(p, batch + (-1,)) for p in parts], axis=-1)
        return flat, total

    def forward_and_log_det(self, z: Array, *, context: Array | None = None):
        """Latent -> data: eps (..., T * D) -> (x (..., T, D), log|det dx / d eps| (...))."""
        z = jnp.asarray(z, jnp.float32)
        parts = self.latent_parts(z)
        batch, length = z.shape[:-1], z.shape[-1] // self.pose_dim
        c = self._check_control(context, batch, length)
        contexts = []
        for _ in range(self.levels):
            c = None if c is None else squeeze_time(c)
            contexts.append(c)
        h, total = parts[-1], jnp.zeros(batch, jnp.float32)
        for level in reversed(range(self.levels)):
            c = contexts[level]
            if level < self.levels - 1:
                eps = parts[level]
                if self.prior == "learned":
                    mean, logs = self._prior_params(level, h, c)
                    eps = mean + jnp.exp(logs) * eps
                    total = total + jnp.sum(logs, axis=(-2, -1))
                h = self.splits[level].merge(h, eps)
            h, ld = self.flows[level].forward_and_log_det(h, context=c)
            total = total + ld
            h = unsqueeze_time(h)
        if self.residual:
            h, ld = self._poses_from_changes(h)
            total = total + ld
        return h, total

    def _changes_from_poses(self, x: Array) -> tuple[Array, Array]:
        """``residual``: x (..., T, D) -> normalised [u_0, u_1..u_{T-1}] and their log-det."""
        u, _ = self.difference.inverse_and_log_det(x)
        first, ld_first = self.first_norm.inverse_and_log_det(u[..., :1, :])
        change, ld_change = self.change_norm.inverse_and_log_det(u[..., 1:, :])
        return jnp.concatenate([first, change], axis=-2), ld_first + ld_change

    def _poses_from_changes(self, h: Array) -> tuple[Array, Array]:
        """The inverse of :meth:`_changes_from_poses`: the changes summed back up."""
        first, ld_first = self.first_norm.forward_and_log_det(h[..., :1, :])
        change, ld_change = self.change_norm.forward_and_log_det(h[..., 1:, :])
        x, _ = self.difference.forward_and_log_det(jnp.concatenate([first, change], axis=-2))
        return x, ld_first + ld_change

    # ------------------------------------------------------------------ user-facing API

    def encode(self, x: Array, control: Array | None = None) -> Array:
        """Poses (..., T, D) -> flat standard-normal latents (..., T * D)."""
        return self.inverse_and_log_det(x, context=control)[0]

    def decode(self, z: Array, control: Array | None = None) -> Array:
        """Flat latents (..., T * D) -> poses (..., T, D); the exact inverse of ``encode``."""
        return self.forward_and_log_det(z, context=control)[0]

    def distribution(self, length: int | None = None) -> Transformed:
        """This model as a distribution over windows: ``Transformed(Normal((T * D,)), self)``.

        The base is the standard normal over the flat latents (..., T * D) of ``encode``;
        ``length`` T = None leaves their size open (enough for ``log_prob``; ``sample``
        needs it).
        """
        return Transformed(Normal((None if length is None else length * self.pose_dim,)), self)

    def log_prob(self, x: Array, control: Array | None = None) -> Array:
        """log p(x | control) per window (...,) in nats, in the units of x (all T frames)."""
        return self.distribution().log_prob(x, context=control)

    @property
    def steps(self) -> int:
        """The old name of :attr:`K` (read-only)."""
        return self.K

    def sample(
        self,
        key: Array,
        control: Array | None = None,
        *,
        num: int | None = None,
        length: int | None = None,
        temperature: float = 1.0,
    ) -> Array:
        """Draw windows x = f(temperature * eps), eps ~ N(0, I).

        Conditional: ``control`` (B, T, control_dim) (or (T, control_dim)) fixes batch and
        T. Unconditional: pass ``num`` (batch size) and optionally ``length`` (T; default
        the constructor's ``length``). temperature 0 gives
        the decoded zero latent.
        """
        if control is not None:
            shape = getattr(control, "shape", None)
            if shape is None or len(shape) < 2:
                raise ValueError(
                    f"Glow.sample expects control of shape (..., T, {self.control_dim}), got "
                    f"{shape if shape is not None else type(control).__name__}"
                )
            batch, t = tuple(shape[:-2]), shape[-2]
            if num is not None and batch != (num,):
                raise ValueError(f"Glow.sample: num={num} disagrees with control shape {shape}")
            if length is not None and length != t:
                raise ValueError(f"Glow.sample: length={length} disagrees with control {shape}")
        else:
            if self.conditional:
                raise ValueError(
                    f"This Glow is conditional: Glow.sample needs a control of shape "
                    f"(B, T, {self.control_dim})"
                )
            if num is None:
                raise ValueError(
                    "Glow.sample of an unconditional model needs num (batch size), e.g. "
                    "model.sample(key, num=8) (length defaults to the model's length, "
                    f"{self.length} frames)"
                )
            batch, t = (int(num),), int(self.length if length is None else length)
        self._check_length(t)
        check_temperature(temperature, "Glow.sample")
        if any(n == 0 for n in batch):
            raise ValueError(f"Glow.sample: the batch is empty (shape {batch}); ask for >= 1")
        return self.distribution(t).sample(key, batch, context=control, temperature=temperature)
