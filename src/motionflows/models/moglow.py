"""MoGlow: an autoregressive, control-conditioned Glow with LSTM couplings (Henter et al. 2020).

Model (the semantics of the official StyleGestures code, so its checkpoints import exactly)
-------------------------------------------------------------------------------------------
Poses x_t (D = 63 standardised values), controls c_t (3 standardised values). For a target
frame t the condition is, frame by frame, the tau previous poses and the tau + 1 controls up
to and including c_t, poses first::

    cond_t = [x_{t-tau}, ..., x_{t-1}, c_{t-tau}, ..., c_t]       (tau*D + (tau+1)*C values)

(663 for tau = 10). Each target pose passes through K flow steps, data -> latent::

    ActNorm:         u = (x + bias) * exp(logs)
    LU 1x1 map:      v = W u,  W = P L (U + diag(sign_s * exp(log_s)))
    affine coupling: v_a = v[:31] passes, h = Linear(LSTM([v_a, cond_t]))  (64 outputs)
                     shift = h[0::2], scale = sigmoid(h[1::2] + 2) + 1e-6,
                     z_b = (v_b + shift) * scale

and the base density is N(0, I) per frame (option: a standard Student-t; both from
:mod:`motionflows.distributions`). Each flow step's
coupling LSTM (2 layers x 512 units by default) carries its own state along time: zero at
the start of a window in training/scoring, carried frame by frame in sampling.

The K steps are a :class:`motionflows.bijectors.Scan` of
``Chain([AffineCoupling(LSTMConditioner), InvertibleLinear, ActNorm])`` run over whole
sequences of target frames (the conditioner is a causal sequence model, a ``lax.scan`` over
time). Step ``k`` of our stack is the official ``flow.layers.{K-1-k}`` (the Scan runs its
last step first in the data -> latent direction; the official code runs layer 0 first).

Scopes of :meth:`MoGlow.log_prob` (nats, standardised space, per window (B,)):

* ``"official"``: frames tau .. T-1 given frames 0 .. tau-1 (and all T controls); the LSTM
  starts at zero at frame tau. This is what the official code reports.
* ``"window"``: all T frames, with a zero (mean-pose in standardised space) history and zero
  controls before frame 0; the LSTM starts at zero before frame 0. This is exactly the
  density of :meth:`MoGlow.sample` with the default (zero) seed.

History dropout (training): each of the tau history poses in cond_t is zeroed independently
per (window, t) with probability p, without rescaling; controls and z_a are never dropped.

Sampling and streaming
----------------------
:meth:`MoGlow.sample` is one ``lax.scan`` over frames; each frame is one
``frame_flow().forward_step`` (the bijectors' frame step, whose explicit carry holds the K
LSTM states and the K 1x1 maps with their inverses, formed once per stream), so training
(``flow.inverse_and_log_det``), per-frame scoring (``inverse_step``) and sampling run the
same bijector code. With ``residual`` a :class:`motionflows.bijectors.Difference` follows
the K steps (its carry: x_{t-1}).
The latent of frame t (counted from the start of the stream) is
``temperature * N(0, I)`` drawn with ``jax.random.fold_in(key, t)``; :meth:`stream_step`
uses the same rule with ``state.t``, so passing the same ``key`` at every step reproduces
``sample(key, ...)`` exactly.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from motionflows.bijectors import (
    ActNorm,
    AffineCoupling,
    Bijector,
    Chain,
    Difference,
    Fixed,
    InvertibleLinear,
    MapContext,
    Scan,
    coupling_sizes,
)
from motionflows.data.features import carry_to_next_root
from motionflows.data.names import CONTROL_DIM, FOOT_JOINTS, POSE_DIM
from motionflows.deprecation import renamed
from motionflows.distributions import Normal, StudentT
from motionflows.models.validation import check_input, check_temperature
from motionflows.nets.moglow_conditioners import (
    CondEmbedding,
    FeedForwardConditioner,
    LSTMConditioner,
)
from motionflows.nets.precision import compute_dtype_name

Array = jax.Array

__all__ = [
    "FeedForwardConditioner",
    "LSTMConditioner",
    "MoGlow",
    "StreamState",
    "build_conditions",
    "history_dropout_mask",
    "previous_frames",
    "import_stylegestures",
    "load_stylegestures_checkpoint",
]

WORLD_JOINTS: tuple[str, ...] = ("all", "feet")
"""Values of ``MoGlow(world_joints=...)``: the joints whose residual ``residual_world`` takes
in the world."""
OWN_HISTORY_TARGETS: tuple[str, ...] = ("pose", "change")
"""Values of ``MoGlow(own_history_target=...)``."""
_FEET_CHANNELS = np.isin(np.arange(POSE_DIM) // 3, FOOT_JOINTS)
"""(63,) bool: the x, y, z channels of the ankles and toes."""
_FOOT_HEIGHT_CHANNELS = _FEET_CHANNELS & (np.arange(POSE_DIM) % 3 == 1)
"""(63,) bool: the heights (y) of the ankles and toes."""
_FEET_INDEX = np.flatnonzero(_FEET_CHANNELS)
"""(12,) int: the channels of ``_FEET_CHANNELS`` (the ``stance_hint`` channels, in order)."""


# ----------------------------------------------------------------------------- conditions


def history_dropout_mask(key: Array, shape: tuple[int, ...], tau: int, rate: float) -> Array:
    """Keep-mask (*shape, tau) float32: each history frame kept with probability 1 - rate."""
    if rate <= 0.0:
        return jnp.ones((*shape, tau), jnp.float32)
    return jax.random.bernoulli(key, 1.0 - rate, (*shape, tau)).astype(jnp.float32)


def build_conditions(
    pose: Array,
    control: Array,
    tau: int,
    *,
    scope: str = "official",
    dropout: float = 0.0,
    key: Array | None = None,
    keep_last: bool = False,
    history_pose: Array | None = None,
) -> tuple[Array, Array]:
    """Targets and per-frame conditions of a batch of windows.

    Args:
      pose: (B, T, D), control (B, T, C) (standardised).
      tau: history length.
      scope: ``"official"`` (targets = frames tau..T-1) or ``"window"`` (all T frames, with
        tau zero poses and zero controls before frame 0).
      dropout: history-dropout probability (needs ``key`` when > 0).
      keep_last: never drop x_{t-1} (only the older tau-1 frames); see ``MoGlow``'s
        ``dropout_keeps_last``.
      history_pose: (B, T, D) the poses the histories are built from (default ``pose``;
        ``MoGlow``'s ``history_noise`` passes noisy copies), the targets stay ``pose``.
    Returns:
      targets (B, T', D) and cond (B, T', tau*D + (tau+1)*C) with
      cond[:, s] = [x_{t-tau}, ..., x_{t-1}, m * ..., c_{t-tau}, ..., c_t] for t = s + offset.
    """
    if scope not in ("official", "window"):
        raise ValueError(f"unknown scope {scope!r}: use 'official' or 'window'")

    def widen(x):  # "window": tau zero frames before frame 0
        if scope == "official":
            return x
        return jnp.pad(x, [(0, 0)] * (x.ndim - 2) + [(tau, 0), (0, 0)])

    pose_p, control_p = widen(pose), widen(control)
    source_p = pose_p if history_pose is None else widen(history_pose)
    n = pose_p.shape[-2] - tau  # number of target frames
    targets = pose_p[..., tau:, :]
    hist = jnp.stack([source_p[..., j : j + n, :] for j in range(tau)], axis=-2)  # (.., n, tau, D)
    ctrl = jnp.stack([control_p[..., j : j + n, :] for j in range(tau + 1)], axis=-2)
    if dropout > 0.0:
        if key is None:
            raise ValueError("history dropout > 0 needs a jax.random key")
        mask = history_dropout_mask(key, hist.shape[:-2], tau, dropout)
        if keep_last:  # hist[..., tau - 1, :] is x_{t-1}
            mask = mask.at[..., -1].set(1.0)
        hist = hist * mask[..., None]
    batch = hist.shape[:-2]
    cond = jnp.concatenate([hist.reshape(*batch, -1), ctrl.reshape(*batch, -1)], axis=-1)
    return targets, cond


def previous_frames(pose: Array, tau: int, scope: str = "official") -> Array:
    """The pose before each target frame of :func:`build_conditions`: (B, T', D).

    ``"official"``: frames tau-1 .. T-2; ``"window"``: a zero frame, then frames 0 .. T-2.
    """
    if scope == "window":
        return jnp.pad(pose, [(0, 0)] * (pose.ndim - 2) + [(1, 0), (0, 0)])[..., :-1, :]
    return pose[..., tau - 1 : -1, :]


# ----------------------------------------------------------------------------- model


class StreamState(NamedTuple):
    """Carry of the frame-by-frame sampler (a pytree; jit-friendly).

    carry: the frame carry of the flow (:meth:`MoGlow.initial_carry`): per step, with a
      leading K axis, the coupling-LSTM states (K, B, H) and the 1x1 map with its inverse
      (K, D, D); with ``residual`` also the previous pose (B, D).
    poses: (B, tau, D) the last tau poses; controls: (B, tau, C) the last tau controls.
    t: int32 scalar, frames produced so far (the key of frame t is fold_in(key, t)).
    """

    carry: Any
    poses: Array
    controls: Array
    t: Array


def _step_factory(pose_dim, cond_dim, hidden, num_layers, conditioner, compute_dtype, eps):
    na, nb = coupling_sizes(pose_dim)
    net_cls = LSTMConditioner if conditioner == "lstm" else FeedForwardConditioner

    def make(rngs: nnx.Rngs):
        net = net_cls(
            na,
            cond_dim,
            2 * nb,
            hidden=hidden,
            num_layers=num_layers,
            compute_dtype=compute_dtype,
            rngs=rngs,
        )
        return Chain(
            [
                AffineCoupling(pose_dim, net, eps=eps),
                InvertibleLinear(pose_dim, rngs=rngs),
                ActNorm(pose_dim),
            ]
        )

    return make


class MoGlow(nnx.Module):
    """MoGlow (see the module docstring).

    Args:
      pose_dim, control_dim: D and C (default 63 and 3 from ``motionflows.data.names``).
      tau: history length (10).
      K: the number of flow steps (16); ``num_steps=`` is its deprecated old name.
      hidden, num_layers: coupling LSTM size (512, 2).
      conditioner: ``"lstm"`` (MoGlow) or ``"ff"`` (the Markov feed-forward ablation).
      base: ``"normal"`` or ``"studentt"`` (standard, ``df`` degrees of freedom).
      dropout: history-dropout probability used by :meth:`log_prob` when given a key.
      compute_dtype: ``None`` (float32) or ``"bfloat16"`` for the conditioner matmuls.
      residual: flow the change ``x_t - x_{t-1}`` instead of ``x_t`` (the previous pose,
        never dropped, noisy in training with ``history_noise``; zero before frame 0). A
        shift by a function of the history, so the log-determinant is unchanged and the
        density of x_t is exact; the ActNorm data initialisation then sees the per-frame
        change, whose scale is the predictable part a plain MoGlow needs many steps to
        learn (see docs/readme/moglow_quality.md).
      dropout_keeps_last: history dropout never drops x_{t-1}, only the older tau - 1
        frames (our option, an ablation of the long-run drift of ``residual`` models: at
        the `cpu` size it improves the NLL by ~20 nats/frame but worsens rollouts; see
        docs/readme/moglow_quality.md#long-runs-drift).
      residual_world: with ``residual``, the change is taken in the world: the previous pose
        is first carried into frame t's root frame by the control c_{t-1}
        (:func:`motionflows.data.features.carry_to_next_root`), u_t = x_t - carry(x_{t-1}),
        so a joint at rest in the world (a planted foot) has u_t = 0 instead of minus the
        root's motion. Still a shift by a function of the history and the controls: log-det
        0. Needs D = 63, C = 3 and the standardiser's statistics (:meth:`with_units`; the
        defaults, mean 0 and std 1, mean the data are in metres and m/frame, rad/frame).
      world_joints: with ``residual_world``, whose change is taken in the world: ``"all"``
        joints, or the ``"feet"`` only (ankles and toes, ``data.names.FOOT_JOINTS``; every
        other joint's change stays in the root frame, x_t - x_{t-1}). Both are ablations no
        preset uses: they slide more than the root-frame residual
        (docs/readme/moglow_quality.md#foot-sliding-the-control-carried-the-gait-cycle).
      absolute_foot_heights: with ``residual``, the ankles' and toes' heights are flowed as
        they are, not as their change: u_t = x_t there (the previous pose's value is replaced
        by 0, still a shift by a function of the history: log-det 0), so the flow can put a
        planted foot's density at the floor instead of integrating its height from frame to
        frame (our option, an ablation; docs/readme/moglow_quality.md).
      stance_hint: append to every condition cond_t where each ankle and toe would be at
        frame t had it stood still in the world since t-1, relative to where it was:
        carry(x_{t-1}) - x_{t-1} on their 12 channels (standardised; ``carry`` as in
        ``residual_world``, by the control c_{t-1}), so a conditioner can place a planted
        foot by passing one input through instead of computing the root's move. x_{t-1} is
        the pose the ``residual`` change is taken from (never dropped; noisy in training
        with ``history_noise``). A condition only: the log-determinant and the flowed
        values are unchanged. Needs D = 63, C = 3 and the standardiser's statistics
        (:meth:`with_units`). Our option, an ablation of the stance creep
        (docs/readme/moglow_quality.md); no preset uses it.
      cond_embedding: 0 (the official model: every coupling's conditioner reads cond_t) or
        a width E: a learned linear map e_t = cond_t W (no bias, :class:`CondEmbedding`)
        runs once per frame and all K conditioners read e_t (E values) instead of cond_t.
        That constrains each coupling's weights on the condition to rank E in a row space
        the K steps share, and replaces K (cond x 4H) products per frame by one (cond x E)
        and K (E x 4H): with tau = 5 (cond 333), E = 64 and a 128-unit LSTM, the
        conditioners' products per frame fall by about half. A condition only: log-dets
        and the residual's previous pose are unchanged (the ``Difference`` reads cond_t).
        Our option; no preset uses it: at E = 64 the ``cpu`` preset trains 24 % faster but its
        pose statistics are worse (docs/readme/cpu_budget.md).
      history_noise: standard deviation (standardised units) of Gaussian noise added to
        every history pose when :meth:`log_prob` is given a key (training): the histories
        and, with ``residual``, the pose the change is added to are x~_s = x_s + sigma *
        eps_s, eps_s ~ N(0, I) per frame, while the targets stay the true x_t. The model
        then learns p(x_t | noisy history), which teaches it to correct its own past errors
        instead of integrating them (our option, against exposure bias; 0 = off). Scoring
        without a key and sampling use the clean history.
      own_history: probability that a history frame is the model's own draw when
        :meth:`log_prob` is given a key (training; parallel scheduled sampling, our option
        against exposure bias; 0 = off). A first pass, without gradient, draws every target
        frame from its history at ``own_history_temperature``:
        x^_t = f(z_t; cond_t), z_t ~ T * N(0, I); each frame s of the window is then
        replaced by x^_s with probability p, independently per (window, frame), in the
        histories (and the ``residual``'s previous pose) of the later frames; the targets
        follow ``own_history_target``. ``own_history_passes`` = n repeats the draw from
        the mixed histories, so frame t's history holds draws up to n frames deep (a draw
        from a drawn history). The model learns p(x_t | a history with its own errors), the
        situation of free-running sampling, whose correlated errors (a creeping stance
        foot) Gaussian ``history_noise`` does not imitate. Costs one sequence pass (no
        backward) per training step and pass (the quick size: 1.7-2x the step time). The
        coupling LSTMs of the draw pass run over the drawn frames, as in sampling, with
        the real histories in cond_t. Applied before ``history_noise`` and dropout.
      own_history_passes: n >= 1 above.
      own_history_temperature: T >= 0 of those draws (the temperature the model samples at).
      own_history_target: what frame t is trained to be after a drawn history: ``"pose"``
        the true x_t (the model learns to return to the real trajectory in one frame; a
        planted foot drawn 1 cm off is taught to slide back), or ``"change"`` the true
        change continued from the drawn previous frame, x_t + (x^_{t-1} - x_{t-1}) (a
        planted foot stays where it was drawn; the model learns to carry on from its own
        past, not to correct it). The shift is a function of the history, so either is an
        exact density of its targets.
      mask_padded: train on the real frames of padded windows only (our option; False =
        every frame). A take shorter than the window is padded with its last pose frozen
        and zero control; the training loss (``experiments/moglow.py``'s ``loss``) then
        scores only the frames the batch's ``valid`` marks, from :meth:`log_prob` with
        ``per_frame=True``. Exact, since the model is causal: a real frame's density never
        reads the padding after it.
      rngs: ``nnx.Rngs`` (or a key) for the initial parameters.
    """

    def __init__(
        self,
        pose_dim: int = POSE_DIM,
        control_dim: int = CONTROL_DIM,
        *,
        tau: int = 10,
        K: int | None = None,
        hidden: int = 512,
        num_layers: int = 2,
        conditioner: str = "lstm",
        base: str = "normal",
        df: float = 5.0,
        dropout: float = 0.0,
        compute_dtype: str | None = None,
        eps: float = 1e-6,
        residual: bool = False,
        dropout_keeps_last: bool = False,
        history_noise: float = 0.0,
        residual_world: bool = False,
        world_joints: str = "all",
        absolute_foot_heights: bool = False,
        stance_hint: bool = False,
        cond_embedding: int = 0,
        own_history: float = 0.0,
        own_history_passes: int = 1,
        own_history_temperature: float = 0.8,
        own_history_target: str = "pose",
        mask_padded: bool = False,
        rngs: nnx.Rngs | Array,
        num_steps: int | None = None,
    ):
        K = renamed(
            "MoGlow", old="num_steps", new="K", old_value=num_steps, new_value=K, default=16
        )
        if conditioner not in ("lstm", "ff"):
            raise ValueError(f"conditioner must be 'lstm' or 'ff', got {conditioner!r}")
        if base not in ("normal", "studentt"):
            raise ValueError(f"base must be 'normal' or 'studentt', got {base!r}")
        if not 0.0 <= float(dropout) < 1.0:
            raise ValueError(f"dropout must be in [0, 1), got {dropout}")
        if not float(history_noise) >= 0.0:
            raise ValueError(f"history_noise must be >= 0, got {history_noise}")
        if not 0.0 <= float(own_history) <= 1.0:
            raise ValueError(f"own_history must be in [0, 1], got {own_history}")
        if int(own_history_passes) < 1:
            raise ValueError(f"own_history_passes must be >= 1, got {own_history_passes}")
        check_temperature(own_history_temperature, "MoGlow(own_history_temperature=...)")
        if own_history_target not in OWN_HISTORY_TARGETS:
            raise ValueError(
                f"own_history_target must be one of {', '.join(OWN_HISTORY_TARGETS)}, "
                f"got {own_history_target!r}"
            )
        if int(tau) < 1 or int(K) < 1 or int(pose_dim) < 2 or int(control_dim) < 0:
            raise ValueError(
                f"MoGlow needs tau >= 1, K >= 1, pose_dim >= 2; got tau={tau}, "
                f"K={K}, pose_dim={pose_dim}"
            )
        if int(cond_embedding) < 0:
            raise ValueError(
                f"cond_embedding must be 0 (off) or the embedding's width, got {cond_embedding}"
            )
        if residual_world and not residual:
            raise ValueError("residual_world=True needs residual=True (it changes what is flowed)")
        if world_joints not in WORLD_JOINTS:
            raise ValueError(
                f"world_joints must be one of {', '.join(WORLD_JOINTS)}, got {world_joints!r}"
            )
        if world_joints != "all" and not residual_world:
            raise ValueError(
                f"world_joints={world_joints!r} needs residual_world=True (it picks the joints "
                "whose change residual_world takes in the world)"
            )
        if absolute_foot_heights and not residual:
            raise ValueError(
                "absolute_foot_heights=True needs residual=True (it keeps the feet's heights "
                "out of the change that residual flows)"
            )
        if absolute_foot_heights and int(pose_dim) != POSE_DIM:
            raise ValueError(
                f"absolute_foot_heights needs the motion features (pose_dim={POSE_DIM}), "
                f"got pose_dim={pose_dim}"
            )
        if residual_world and (int(pose_dim), int(control_dim)) != (POSE_DIM, CONTROL_DIM):
            raise ValueError(
                f"residual_world needs the motion features (pose_dim={POSE_DIM} joint "
                f"positions, control_dim={CONTROL_DIM} root moves), got {pose_dim}, {control_dim}"
            )
        if stance_hint and (int(pose_dim), int(control_dim)) != (POSE_DIM, CONTROL_DIM):
            raise ValueError(
                f"stance_hint needs the motion features (pose_dim={POSE_DIM} joint positions, "
                f"control_dim={CONTROL_DIM} root moves), got {pose_dim}, {control_dim}"
            )
        compute_dtype = compute_dtype_name(compute_dtype, "MoGlow")
        self.pose_dim = int(pose_dim)
        self.control_dim = int(control_dim)
        self.tau = int(tau)
        self.K = int(K)
        self.hidden = int(hidden)
        self.num_layers = int(num_layers)
        self.conditioner = conditioner
        self.base = base
        self.df = float(df)
        self.dropout = float(dropout)
        self.compute_dtype = compute_dtype
        self.eps = float(eps)
        self.residual = bool(residual)
        self.dropout_keeps_last = bool(dropout_keeps_last)
        self.history_noise = float(history_noise)
        self.residual_world = bool(residual_world)
        self.world_joints = world_joints
        self.absolute_foot_heights = bool(absolute_foot_heights)
        self.stance_hint = bool(stance_hint)
        self.cond_embedding = int(cond_embedding)
        self.own_history = float(own_history)
        self.own_history_passes = int(own_history_passes)
        self.own_history_temperature = float(own_history_temperature)
        self.own_history_target = own_history_target
        self.mask_padded = bool(mask_padded)
        if self.residual_world or self.stance_hint:  # [pose mean, pose std, ctrl mean, std]
            self.units = Fixed(
                jnp.concatenate(
                    [jnp.zeros(pose_dim), jnp.ones(pose_dim), jnp.zeros(control_dim),
                     jnp.ones(control_dim)]
                ).astype(jnp.float32)
            )  # fmt: skip
        self.cond_dim = self.tau * self.pose_dim + (self.tau + 1) * self.control_dim
        if self.stance_hint:
            self.cond_dim += _FEET_INDEX.size
        if not isinstance(rngs, nnx.Rngs):
            rngs = nnx.Rngs(rngs)
        factory = _step_factory(
            self.pose_dim,
            self.cond_embedding or self.cond_dim,
            self.hidden,
            self.num_layers,
            conditioner,
            compute_dtype,
            self.eps,
        )
        self.flow = Scan(factory, self.K, rngs=rngs)
        # drawn after the steps, so that the steps' initial parameters do not depend on it
        self.embed = (
            CondEmbedding(
                self.cond_dim, self.cond_embedding, compute_dtype=compute_dtype, rngs=rngs
            )
            if self.cond_embedding
            else None
        )

    # -- the residual's previous pose

    def with_units(self, pose_mean, pose_std, control_mean, control_std) -> MoGlow:
        """A copy whose ``residual_world`` and ``stance_hint`` carry works in these units: the
        standardiser's per-channel means and stds of poses (D,) (metres) and controls (C,).
        Pure."""
        if not (self.residual_world or self.stance_hint):
            raise ValueError("MoGlow.with_units is only for residual_world or stance_hint models")
        parts = [np.asarray(a, np.float32).reshape(-1) for a in
                 (pose_mean, pose_std, control_mean, control_std)]  # fmt: skip
        sizes = [self.pose_dim, self.pose_dim, self.control_dim, self.control_dim]
        if [p.size for p in parts] != sizes or not all(np.isfinite(p).all() for p in parts):
            raise ValueError(f"MoGlow.with_units: need finite arrays of sizes {sizes}")
        if (parts[1] <= 0).any() or (parts[3] <= 0).any():
            raise ValueError("MoGlow.with_units: stds must be positive")
        model = nnx.clone(self)
        model.units[...] = jnp.asarray(np.concatenate(parts))
        return model

    def _carried(self, previous: Array, cond: Array) -> Array:
        """x_{t-1} (..., D) carried into frame t's root frame by c_{t-1}, read from cond
        (..., cond_dim) (the controls there are never dropped); standardised in and out."""
        d, c, tau = self.pose_dim, self.control_dim, self.tau
        units = jax.lax.stop_gradient(self.units[...])
        p_mean, p_std = units[:d], units[d : 2 * d]
        c_mean, c_std = units[2 * d : 2 * d + c], units[2 * d + c :]
        start = tau * d + (tau - 1) * c  # c_{t-1}: the last history control
        control = c_mean + c_std * cond[..., start : start + c]
        return (carry_to_next_root(p_mean + p_std * previous, control) - p_mean) / p_std

    def _carry_previous(self, previous: Array, cond: Array) -> Array:
        """``residual_world``: x_{t-1} carried (:meth:`_carried`), on the ``world_joints``."""
        moved = self._carried(previous, cond)
        if self.world_joints == "feet":
            return jnp.where(_FEET_CHANNELS, moved, previous)
        return moved

    def _previous(self, previous: Array, cond: Array) -> Array:
        """What the ``residual`` change is taken from: x_{t-1} carried (``residual_world``),
        with the feet's heights 0 (``absolute_foot_heights``)."""
        if self.residual_world:
            previous = self._carry_previous(previous, cond)
        if self.absolute_foot_heights:
            previous = jnp.where(_FOOT_HEIGHT_CHANNELS, 0.0, previous)
        return previous

    def _hinted(self, cond: Array, previous: Array) -> Array:
        """cond (..., cond_dim without the hint), with ``stance_hint`` followed by
        carry(x_{t-1}) - x_{t-1} on the feet's 12 channels; previous = x_{t-1} (..., D)."""
        if not self.stance_hint:
            return cond
        hint = (self._carried(previous, cond) - previous)[..., _FEET_INDEX]
        return jnp.concatenate([cond, hint], axis=-1)

    def conditions(
        self,
        pose: Array,
        control: Array,
        *,
        scope: str = "official",
        history_pose: Array | None = None,
        **options,
    ) -> tuple[Array, Array, Array]:
        """(targets (B, T', D), cond (B, T', cond_dim), previous (B, T', D)) of windows:
        :func:`build_conditions` (``options``: dropout, key, keep_last), the pose before
        each target frame (:func:`previous_frames` of the histories' poses) and, with
        ``stance_hint``, the hint appended to cond."""
        history = pose if history_pose is None else history_pose
        targets, cond = build_conditions(
            pose, control, self.tau, scope=scope, history_pose=history, **options
        )
        previous = previous_frames(history, self.tau, scope)
        return targets, self._hinted(cond, previous), previous

    def _difference(self) -> Difference:
        """The ``residual`` map: u_t = x_t - previous(x_{t-1}) (:meth:`_previous`)."""
        moves = self.residual_world or self.absolute_foot_heights
        return Difference(self.pose_dim, self._previous if moves else None)

    # -- validation

    def _check(self, pose: Array | None, control: Array, name: str) -> tuple[Array | None, Array]:
        """Shapes, then dtype, emptiness and finiteness (``validation.check_input``);
        returns (pose, control) as float32."""
        c = getattr(control, "shape", None)
        if c is None or len(c) != 3 or c[-1] != self.control_dim:
            raise ValueError(f"MoGlow.{name}: control must be (B, T, {self.control_dim}), got {c}")
        if pose is not None:
            p = getattr(pose, "shape", None)
            if p is None or len(p) != 3 or p[-1] != self.pose_dim:
                raise ValueError(f"MoGlow.{name}: pose must be (B, T, {self.pose_dim}), got {p}")
            if p[:2] != c[:2]:
                raise ValueError(f"MoGlow.{name}: pose {p} and control {c} must share (B, T)")
            pose = check_input(pose, "pose", f"MoGlow.{name}")
        return pose, check_input(control, "control", f"MoGlow.{name}")

    # -- base density

    @property
    def num_steps(self) -> int:
        """The old name of :attr:`K` (read-only)."""
        return self.K

    def base_density(self) -> Normal | StudentT:
        """The per-frame base density over (D,): standard normal or standard Student-t."""
        if self.base == "normal":
            return Normal((self.pose_dim,))
        return StudentT((self.pose_dim,), df=self.df)

    def base_log_prob(self, z: Array) -> Array:
        """Per-frame base log-density summed over channels: (..., D) -> (...)."""
        return self.base_density().log_prob(z)

    # -- sequence pass (training, scoring)

    def inverse_and_log_det(
        self,
        pose: Array,
        *,
        context: Array,
        scope: str = "official",
        dropout: float = 0.0,
        key: Array | None = None,
        history_noise: float = 0.0,
        own_history: float = 0.0,
        per_frame: bool = False,
    ) -> tuple[Array, Array]:
        """Data -> latent for the target frames of windows.

        pose (B, T, D), context = control (B, T, C) -> (z (B, T', D), log|det dz/dx| (B,)),
        T' = T - tau ("official") or T ("window"); with ``per_frame`` the log-det of each
        target frame (B, T'), summing to the former. ``dropout``, ``own_history`` and
        ``history_noise`` (the training-time corruptions of the history, in that order of
        effect: own draws, then noise, then dropout; see the class docstring) need ``key``.
        Used by ``initialize_from_data``.
        """
        pose, context = self._check(pose, context, "inverse_and_log_det")
        if scope == "official" and pose.shape[1] <= self.tau:
            raise ValueError(
                f"MoGlow: the official scope scores frames tau..T-1, so windows need more than "
                f"tau={self.tau} frames, got T={pose.shape[1]}; use longer windows or "
                "scope='window'"
            )
        history = pose
        if own_history > 0.0:
            if key is None:
                raise ValueError("own_history > 0 needs a jax.random key")
            own_key = jax.random.fold_in(key, 2)  # key: dropout mask; fold_in 1: noise
            history = self._own_history(pose, context, scope, own_key, own_history)
        drawn = history
        if history_noise > 0.0:
            if key is None:
                raise ValueError("history_noise > 0 needs a jax.random key")
            noise_key = jax.random.fold_in(key, 1)  # `key` itself draws the dropout mask
            history = history + history_noise * jax.random.normal(noise_key, pose.shape)
        targets, cond, previous = self.conditions(
            pose,
            context,
            scope=scope,
            dropout=dropout,
            key=key,
            keep_last=self.dropout_keeps_last,
            history_pose=history,
        )
        if own_history > 0.0 and self.own_history_target == "change":  # x_t + x^_{t-1} - x_{t-1}
            targets = targets + previous_frames(drawn - pose, self.tau, scope)
        if self.residual:  # the changes x_t - x~_{t-1} of the target frames (log-det 0),
            # by the sampler's own Difference frame step, every target frame at once
            targets = self._difference().inverse_step(targets, context_t=cond, carry=previous)[0]
        steps = self._steps()
        if per_frame:
            return steps.inverse_and_frame_log_det(targets, context=cond)
        return steps.inverse_and_log_det(targets, context=cond)

    def _own_history(self, pose: Array, control: Array, scope: str, key: Array, rate: float):
        """The histories of parallel scheduled sampling (``own_history``): pose (B, T, D)
        with each target frame replaced, with probability ``rate`` per (window, frame), by
        the model's draw from its own (clean, undropped) history; ``own_history_passes``
        draws, each from the last pass's mixed histories. No gradient flows into the draws.
        """
        offset = self.tau if scope == "official" else 0
        mask_key, *draw_keys = jax.random.split(key, 1 + self.own_history_passes)
        mine = jax.random.bernoulli(mask_key, rate, (*pose.shape[:-2], pose.shape[-2] - offset, 1))
        history = pose
        for draw_key in draw_keys:  # a few passes (static), not frames or flow steps
            targets, cond, previous = self.conditions(
                pose, control, scope=scope, history_pose=history
            )
            z = self.base_density().sample(
                draw_key, targets.shape[:-1], temperature=self.own_history_temperature
            )
            drawn = self._steps().forward(z, context=cond)
            if self.residual:  # x^_t = u_t + previous(x_{t-1} of this pass's history)
                drawn = self._difference().forward_step(drawn, context_t=cond, carry=previous)[0]
            drawn = jax.lax.stop_gradient(drawn)
            history = pose.at[..., offset:, :].set(jnp.where(mine, drawn, pose[..., offset:, :]))
        return history

    def log_prob(
        self,
        pose: Array,
        control: Array,
        *,
        scope: str = "official",
        key: Array | None = None,
        dropout: float | None = None,
        per_frame: bool = False,
    ) -> Array:
        """Log-likelihood per window (B,) in nats (standardised space); with ``per_frame``
        that of each target frame (B, T'), log p(x_t | x_<t, c), summing to the former.

        ``scope="official"``: frames tau..T-1 given the first tau; ``"window"``: all T frames
        with a zero history. With ``key`` the training-time history dropout (probability
        ``dropout``, default ``self.dropout``), ``self.own_history`` and
        ``self.history_noise`` are applied; without a key none is.
        """
        if key is None and dropout:
            raise ValueError(
                f"MoGlow.log_prob: dropout={dropout} needs a key to draw the dropped history "
                "frames (pass key=jax.random.key(...)), or leave dropout unset for clean scoring"
            )
        rate = 0.0 if key is None else (self.dropout if dropout is None else float(dropout))
        pose, control = self._check(pose, control, "log_prob")  # messages name log_prob
        z, log_det = self.inverse_and_log_det(
            pose,
            context=control,
            scope=scope,
            dropout=rate,
            key=key,
            history_noise=0.0 if key is None else self.history_noise,
            own_history=0.0 if key is None else self.own_history,
            per_frame=per_frame,
        )
        frames = self.base_log_prob(z)  # (B, T')
        return frames + log_det if per_frame else jnp.sum(frames, axis=-1) + log_det

    def num_targets(self, num_frames: int, scope: str = "official") -> int:
        """Scored frames per window of ``num_frames`` frames."""
        return num_frames - self.tau if scope == "official" else num_frames

    # -- frame-by-frame maps (the bijectors' frame steps)

    def _steps(self) -> Bijector:
        """The K flow steps given cond_t: ``flow``, reading e_t = ``embed``(cond_t) with
        ``cond_embedding``."""
        return self.flow if self.embed is None else MapContext(self.flow, self.embed)

    def frame_flow(self) -> Bijector:
        """The per-frame map latent z_t -> pose x_t given cond_t: the K steps (``flow``;
        with ``cond_embedding`` they read ``embed``(cond_t)), then, with ``residual``, a
        :class:`~motionflows.bijectors.Difference` (x_t = u_t + x_{t-1}). Its
        ``forward_step`` samples a frame, its ``inverse_step`` scores one."""
        if self.residual:
            return Chain([self._steps(), self._difference()])
        return self._steps()

    def initial_carry(self, batch: int):
        """The carry of :meth:`frame_flow` before frame 0 for ``batch`` sequences: zero LSTM
        states and the K 1x1 maps with their inverses (leading K axis), and with
        ``residual`` a zero previous pose (B, D)."""
        return self.frame_flow().initial_carry((int(batch),))

    def inverse_weights(self) -> Array:
        """(K, D, D): W_k^-1 of every 1x1 map (``InvertibleLinear.inverse_weight``), from
        the stacked steps or, in an :func:`~motionflows.inference.inference_copy`, the
        unrolled ones."""
        if isinstance(self.flow, Scan):
            linear = self.flow.steps.bijectors[1]
            return jax.vmap(lambda lin: lin.inverse_weight())(linear)
        return jnp.stack([step.bijectors[1].inverse_weight() for step in self.flow.bijectors])

    def _frame_to_latent(self, x_t: Array, cond_t: Array, carry):
        """Data -> latent for one frame: x_t (B, D) -> (z_t (B, D), log_det (B,), new carry).

        ``frame_flow().inverse_step``; run over t from :meth:`initial_carry` it equals
        :meth:`inverse_and_log_det` with ``scope="window"``, frame by frame.
        """
        return self.frame_flow().inverse_step(x_t, context_t=cond_t, carry=carry)

    # -- sampling and streaming

    def _seed(self, batch: int, seed_history: Array | None, seed_control: Array | None):
        tau, d, c = self.tau, self.pose_dim, self.control_dim

        def fit(arr, dim, name):
            if arr is None:
                return jnp.zeros((batch, tau, dim), jnp.float32)
            arr = check_input(arr, name, "MoGlow")
            if arr.ndim == 2:
                arr = jnp.broadcast_to(arr[None], (batch, *arr.shape))
            if arr.ndim != 3 or arr.shape[-1] != dim or arr.shape[0] != batch:
                raise ValueError(
                    f"MoGlow: {name} must be (B={batch}, S, {dim}) frames, got {arr.shape}"
                )
            arr = arr[:, -tau:]
            short = tau - arr.shape[1]
            return jnp.pad(arr, ((0, 0), (short, 0), (0, 0))) if short else arr

        return fit(seed_history, d, "seed_history"), fit(seed_control, c, "seed_control")

    def init_stream(
        self,
        batch: int,
        seed_history: Array | None = None,
        *,
        seed_control: Array | None = None,
    ) -> StreamState:
        """Start a stream of ``batch`` characters.

        seed_history: None (zeros: the official sampler's start) or (B, S, D) poses (the last
        tau are used; fewer are left-padded with zeros). seed_control likewise (B, S, C).
        """
        poses, controls = self._seed(int(batch), seed_history, seed_control)
        carry = self.initial_carry(int(batch))
        if self.residual:  # the Difference's carry: the pose before the first new frame
            carry = (carry[0], poses[:, -1])
        return StreamState(carry=carry, poses=poses, controls=controls, t=jnp.zeros((), jnp.int32))

    def _advance(self, state: StreamState, control_t: Array, z_t: Array):
        batch = control_t.shape[0]
        cond_t = jnp.concatenate(
            [
                state.poses.reshape(batch, -1),
                state.controls.reshape(batch, -1),
                control_t,
            ],
            axis=-1,
        )
        cond_t = self._hinted(cond_t, state.poses[:, -1])
        x_t, _, carry = self.frame_flow().forward_step(z_t, context_t=cond_t, carry=state.carry)
        new = StreamState(
            carry=carry,
            poses=jnp.concatenate([state.poses[:, 1:], x_t[:, None]], axis=1),
            controls=jnp.concatenate([state.controls[:, 1:], control_t[:, None]], axis=1),
            t=state.t + 1,
        )
        return x_t, new

    def stream_step(
        self,
        state: StreamState,
        control_t: Array,
        key: Array,
        *,
        temperature: float = 1.0,
    ) -> tuple[Array, StreamState]:
        """One frame: control_t (B, C) -> (pose_t (B, D), new state). Jittable.

        The latent is ``temperature * eps`` with eps drawn from ``fold_in(key, state.t)``:
        passing the same key at every step reproduces :meth:`sample` with that key.
        """
        shape = tuple(getattr(control_t, "shape", np.shape(control_t)))
        if shape != (state.poses.shape[0], self.control_dim):
            raise ValueError(
                f"MoGlow.stream_step: control_t must be (B={state.poses.shape[0]}, "
                f"{self.control_dim}), got {shape}"
            )
        control_t = check_input(control_t, "control_t", "MoGlow.stream_step")
        check_temperature(temperature, "MoGlow.stream_step")
        z_t = self.base_density().sample(
            jax.random.fold_in(key, state.t), (control_t.shape[0],), temperature=temperature
        )
        return self._advance(state, control_t, z_t)

    def generate(
        self,
        z: Array,
        control: Array,
        *,
        seed_history: Array | None = None,
        seed_control: Array | None = None,
    ) -> Array:
        """Latents z (B, T, D) and control (B, T, C) -> poses (B, T, D), frame by frame."""
        _, control = self._check(None, control, "generate")
        z = check_input(z, "z", "MoGlow.generate")
        if z.ndim != 3 or z.shape[:2] != control.shape[:2] or z.shape[-1] != self.pose_dim:
            raise ValueError(
                f"MoGlow.generate: z must be (B, T, {self.pose_dim}) with the control's (B, T) "
                f"{tuple(control.shape[:2])}, got {tuple(z.shape)}"
            )
        state = self.init_stream(control.shape[0], seed_history, seed_control=seed_control)

        def body(st, inputs):
            c_t, z_t = inputs
            x_t, st = self._advance(st, c_t, z_t)
            return st, x_t

        _, xs = jax.lax.scan(body, state, (jnp.swapaxes(control, 0, 1), jnp.swapaxes(z, 0, 1)))
        return jnp.swapaxes(xs, 0, 1)

    def sample(
        self,
        key: Array,
        control: Array,
        *,
        seed_history: Array | None = None,
        seed_control: Array | None = None,
        temperature: float = 1.0,
    ) -> Array:
        """Poses (B, T, D) following control (B, T, C); one ``lax.scan`` over frames.

        Frame t's latent is ``temperature * eps_t``, eps_t from ``fold_in(key, t)``
        (temperature 0 gives the exact mode path of the latent). Jit it at the call site.
        On XLA:CPU, sample from :func:`motionflows.inference.inference_copy` of the model
        (the same poses, bit for bit, about twice as fast at batch 1; the library's own
        samplers do).
        """
        _, control = self._check(None, control, "sample")
        check_temperature(temperature, "MoGlow.sample")
        state = self.init_stream(control.shape[0], seed_history, seed_control=seed_control)

        def body(st, c_t):
            return self.stream_step(st, c_t, key, temperature=temperature)[::-1]

        _, xs = jax.lax.scan(body, state, jnp.swapaxes(control, 0, 1))
        return jnp.swapaxes(xs, 0, 1)


# The official-checkpoint import lives in its own file (re-exported here).
from motionflows.models.moglow_import import (  # noqa: E402
    import_stylegestures,
    load_stylegestures_checkpoint,
)
