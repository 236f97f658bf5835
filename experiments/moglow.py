"""MoGlow (MoGlow paper, Sec. 4): autoregressive, control-conditioned Glow with LSTM couplings.

Run: ``python -m experiments.moglow --preset quick`` (synthetic data, minutes on a CPU),
``--preset paper`` (the paper's locomotion configuration), ``--preset preferred`` (the same
with history dropout 0.7), ``--set conditioner=ff`` for the Markov (feed-forward) ablation,
``--set compute_dtype=bfloat16`` (or ``float32``) to choose the conditioner matmuls' precision
(default ``auto``: bfloat16 on a recent NVIDIA GPU, float32 elsewhere).

Training objective: mean NLL per target frame (frames tau..T-1 of each window, the official
scope), nats, standardised space, with history dropout. ``evaluate`` returns per-window
log-likelihoods (nats, standardised): ``"window"`` (all T frames, zero history before frame
0), ``"official"`` (frames tau..T-1 given the first tau, no dropout) and
``"official_dropout"`` (the same with training-time history dropout, comparable with the
official code's validation curves).
"""

from __future__ import annotations

import dataclasses
import math
import sys

import jax
import jax.numpy as jnp

from motionflows.bijectors import initialize_from_data
from motionflows.config import (
    INF,
    SMOKE_DATA,
    DataConfig,
    Scope,
    TrainConfig,
    check_compute_dtype,
    check_fields,
    matmul_dtype,
    smoke_train,
)
from motionflows.data.features import HOLDEN_ROOT_SIGMA_S
from motionflows.data.names import CONTROL_DIM, POSE_DIM
from motionflows.deprecation import key_first
from motionflows.inference import inference_copy
from motionflows.models.moglow import OWN_HISTORY_TARGETS, MoGlow
from motionflows.models.validation import check_sample_args

NAME = "moglow"
CAUSAL = True  # frame t depends on frames < t only

_LN2 = math.log(2.0)


@dataclasses.dataclass(frozen=True)
class Config:
    """MoGlow experiment config: data, training, and the model fields below."""

    data: DataConfig = DataConfig()
    train: TrainConfig = TrainConfig()
    K: int = 16  # flow steps
    hidden: int = 512  # coupling LSTM units
    layers: int = 2  # coupling LSTM layers
    tau: int = 10  # history frames in the condition
    dropout: float = 0.95  # history dropout probability (training)
    compute_dtype: str = "auto"  # conditioner matmuls: "auto" | "float32" | "bfloat16"
    conditioner: str = "lstm"  # "lstm" (MoGlow) | "ff" (Markov ablation)
    base: str = "normal"  # "normal" | "studentt"
    df: float = 5.0  # Student-t degrees of freedom (base = "studentt")
    residual: bool = False  # flow x_t - x_{t-1} (our option; see MoGlow's docstring)
    dropout_keeps_last: bool = False  # history dropout never drops x_{t-1} (an ablation)
    history_noise: float = 0.0  # std of training noise on the history poses (standardised)
    residual_world: bool = False  # residual taken in the world: planted feet change by 0
    world_joints: str = "all"  # with residual_world: "all" joints or the "feet" only
    absolute_foot_heights: bool = False  # with residual: the feet's heights flowed, not changed
    stance_hint: bool = False  # condition on where a planted foot would be (an ablation)
    cond_embedding: int = 0  # 0, or the width of one linear map of cond all K steps read
    own_history: float = 0.0  # P(a history frame is the model's own draw) in training
    own_history_passes: int = 1  # draws from drawn histories: up to this many frames deep
    own_history_temperature: float = 0.8  # temperature of those draws
    own_history_target: str = "pose"  # after a drawn history: the true "pose" or "change"
    mask_padded: bool = False  # train on padded windows' real frames only (no frozen tail)

    def __post_init__(self):
        if self.K < 1 or self.hidden < 1 or self.layers < 1 or self.tau < 1:
            raise ValueError(
                f"K, hidden, layers and tau must be >= 1, got {self.K}, {self.hidden}, "
                f"{self.layers}, {self.tau}"
            )
        if self.data.window <= self.tau:
            raise ValueError(
                f"MoGlow needs data.window > tau (the first tau frames are the history), got "
                f"window={self.data.window}, tau={self.tau}"
            )
        if not 0.0 <= self.dropout < 1.0:
            raise ValueError(f"dropout must be in [0, 1), got {self.dropout}")
        if self.residual_world and not self.residual:
            raise ValueError("residual_world=True needs residual=True (--set residual=true)")
        if self.absolute_foot_heights and not self.residual:
            raise ValueError("absolute_foot_heights=True needs residual=True (--set residual=true)")
        if self.world_joints != "all" and not self.residual_world:
            raise ValueError(
                f"world_joints={self.world_joints!r} needs residual_world=True "
                "(--set residual_world=true)"
            )
        if not 0.0 <= self.own_history <= 1.0:
            raise ValueError(f"own_history must be in [0, 1], got {self.own_history}")
        if self.own_history_passes < 1:
            raise ValueError(f"own_history_passes must be >= 1, got {self.own_history_passes}")
        if not self.own_history_temperature >= 0.0:
            raise ValueError(
                f"own_history_temperature must be >= 0, got {self.own_history_temperature}"
            )
        if self.own_history_target not in OWN_HISTORY_TARGETS:
            raise ValueError(
                f"own_history_target must be one of {', '.join(OWN_HISTORY_TARGETS)}, "
                f"got {self.own_history_target!r}"
            )
        check_fields(self, MODEL_LIMITS)
        check_compute_dtype(self.compute_dtype)
        if self.conditioner not in ("lstm", "ff"):
            raise ValueError(f"conditioner must be 'lstm' or 'ff', got {self.conditioner!r}")
        if self.base not in ("normal", "studentt"):
            raise ValueError(f"base must be 'normal' or 'studentt', got {self.base!r}")


MODEL_LIMITS = {  # as cfg.check_fields reads them: (lowest, highest, lowest ok?, highest ok?)
    "df": (0.0, 1e6, False, True),
    "history_noise": (0.0, 1e3, True, True),
    "cond_embedding": (0, INF, True, True),
}


PRESETS: dict[str, Config] = {
    # The paper's locomotion model exactly as the authors' `paper_version` configuration
    # (../shared/OFFICIAL_RECIPES.md): K = 16 steps, 2-layer LSTM with 512 units, tau = 10,
    # history dropout 0.95, 80-frame windows (70 target frames) with mirror and time-reversal
    # augmentation (the standardiser is fitted on the augmented training windows), batch 100,
    # Adam (0.9, 0.999, 1e-8), lr 1e-4 with the noam rule (warm-up 1000, floor 1e-4: a linear
    # warm-up then constant 1e-4), clip values at 5 then the global norm at 100, 160k steps,
    # validation every 200 steps. One difference: we validate on the held-out val split
    # (clean and with dropout), the official code on its last 100 training clips. The data
    # are Holden's features (root smoothed over 0.05 s), as the authors' data were made.
    "paper": Config(
        data=DataConfig(
            window=80, hop=10, mirror=True, reverse=True, root_sigma_s=HOLDEN_ROOT_SIGMA_S
        ),
        train=TrainConfig(
            steps=160_000,
            batch_size=100,
            lr=1e-4,
            warmup_steps=1000,
            schedule="noam",
            min_lr_ratio=1.0,
            clip_value=5.0,
            clip_norm=100.0,
            b1=0.9,
            b2=0.999,
            eps=1e-8,
            eval_every=200,
            checkpoint_every=2000,
        ),
        dropout=0.95,
    ),
    # Minutes on 2 CPU cores: a small flow on 2 s windows of the synthetic set.
    "quick": Config(
        data=DataConfig(window=40, hop=8, synthetic_clips=60),
        train=TrainConfig(
            steps=800,
            batch_size=32,
            lr=2e-3,
            warmup_steps=100,
            schedule="cosine",
            min_lr_ratio=0.1,
            clip_value=5.0,
            clip_norm=100.0,
            eval_every=400,
            eval_batches=4,
            log_every=25,
            checkpoint_every=400,
        ),
        K=4,
        hidden=128,
        layers=1,
        dropout=0.7,
    ),
}
# The authors' later `preferred` configuration: history dropout 0.7, lr 1e-3 with the noam
# rule (peak 1e-3 at step 999, decaying as sqrt(1000 / (g + 1)) to ~1.1e-4 at 80k, floor
# 1e-4), 80k steps; everything else as `paper`.
PRESETS["preferred"] = dataclasses.replace(
    PRESETS["paper"],
    dropout=0.7,
    train=dataclasses.replace(PRESETS["paper"].train, lr=1e-3, min_lr_ratio=0.1, steps=80_000),
)
# At most 60 minutes of training on 2 CPU cores (the search: docs/readme/moglow_quality.md):
# the quick flow (K = 4, one 128-unit LSTM, history dropout 0.7) made `residual`
# (it flows x_t - x_{t-1}: at 1600 steps this alone cut the jerk of samples on an unseen
# performer from 7x to 2x that of real motion and the test NLL by 127 nats/frame), on the
# 4 s windows the bench scores, 8000 steps of batch 32, with history_noise 0.03 (training
# on noisy histories: on held-out takes pose FD 0.078 -> 0.057, contact rate 0.18 -> 0.28,
# 3x less bone drift over 12 s, for 28 nats/frame of clean-history NLL), and every training
# take also replayed at 0.8x and 1.25x its speed (data.tempo: the same strides at other
# cadences; on the unseen performer foot sliding 0.286 -> 0.205 m/s, jerk 1.56x -> 1.41x,
# pose FD 0.065 -> 0.052, for 3 nats/frame of NLL; docs/readme/cpu_budget.md), with a
# history of tau = 5 frames (a quarter second) instead of 10: on the unseen performer, two
# seeds each, foot sliding 0.205 / 0.228 -> 0.193 / 0.201 m/s, contact rate 0.32 / 0.34 ->
# 0.41 / 0.43 (data 0.54), the same jerk and pose FD, 39 % fewer parameters, 18 % more
# training frames/s and 1.9x batch-1 sampling (docs/readme/cpu_budget.md, "MoGlow with tau 5"),
# validated, checkpointed and shipped as a running average of its parameters (ema_decay 0.999:
# on the unseen performer, three seeds each paired with the same seed without it, +8.7 / +3.0 /
# +5.2 nats/frame of window NLL with the same motion; cpu_budget.md, "Parameter averaging"),
# on foot-locked training takes (data.foot_lock: the stance feet pinned where they land)
# replayed at the slower speed only (data.tempo_replay="slower": the longer strides for
# each speed): on the unseen performer, two seeds, foot sliding 0.189 / 0.190 -> 0.147 /
# 0.146 m/s, skate ratio 0.043 / 0.048 -> 0.026 / 0.025, jerk 1.50x / 1.45x -> 1.47x /
# 1.48x, the same pose FD, for a contact rate of 0.38-0.39 (was 0.42) and 0-11 nats/frame
# of window NLL (cpu_budget.md, "MoGlow on foot-locked takes with only the slower replays"),
# and on those takes a history of tau = 3 frames (0.15 s): on the unseen performer, two
# seeds each against tau 5, foot sliding 0.147 / 0.146 -> 0.153 / 0.135 m/s, contact rate
# 0.375 / 0.388 -> 0.433 / 0.424, pose FD 0.048 / 0.049 -> 0.045 / 0.044, window NLL
# -261.6 / -266.7 -> -269.4 / -269.3 nats/frame, the same jerk (1.49x / 1.47x; a third
# seed moved at 1.56x, outside the 1.5x target, with the same pose FD and contact rate,
# where three seeds of tau 5 stayed inside it: --set tau=5 for that), a quarter fewer
# parameters and 4 % more training frames/s (cpu_budget.md, "With a history of tau = 3").
PRESETS["cpu"] = dataclasses.replace(
    PRESETS["quick"],
    data=DataConfig(
        window=80, hop=10, mirror=True, tempo=1.25, tempo_replay="slower", foot_lock=True
    ),
    train=dataclasses.replace(
        PRESETS["quick"].train,
        steps=8000,
        warmup_steps=200,
        eval_every=1000,
        checkpoint_every=1000,
        log_every=50,
        ema_decay=0.999,
    ),
    tau=3,
    residual=True,
    history_noise=0.03,
    compute_dtype="float32",  # a CPU budget: the precision it was searched and shipped in
)
# Seconds: tests and the bench's smoke budget (a CI-sized flow, 30 steps, 1.6 s windows).
PRESETS["smoke"] = dataclasses.replace(
    PRESETS["quick"],
    data=DataConfig(**SMOKE_DATA),
    train=smoke_train(PRESETS["quick"].train),
    K=2,
    hidden=16,
    layers=1,
)
PRESETS["paper_markov"] = dataclasses.replace(PRESETS["paper"], conditioner="ff")
PRESETS["quick_markov"] = dataclasses.replace(PRESETS["quick"], conditioner="ff")

VALIDATION_SCOPE = "official"
"""The scope behind ``val_nll`` and the best checkpoint: the training objective's (frames
tau..T-1 given the first tau), as the official code validates; the ``window`` scope also
scores the first frames from a zero history, which a ``residual`` model fits worst."""

SCOPES: dict[str, Scope] = {
    "window": Scope(
        "log p(x_1:T | c_1:T) of all T frames, zero (mean-pose) history before frame 0, exact"
    ),
    "official": Scope(
        "log p(x_tau:T-1 | x_0:tau-1, c_0:T-1): frames tau..T-1 given the first tau, "
        "no dropout (the official MoGlow scope)",
        skip="tau",
    ),
    "official_dropout": Scope(
        "as 'official' but with the training-time history dropout (and own-history draws "
        "and history noise, if set; random, key-dependent), comparable with the official "
        "validation curves",
        skip="tau",
    ),
}


def build(config: Config, *, key: jax.Array, control_dim: int = CONTROL_DIM) -> MoGlow:
    """The MoGlow of ``config`` with fresh parameters drawn from ``key``; ``control_dim``
    for controls with more channels than the 3 root moves (e.g. the contact-label oracle of
    ``benchmarks/contact_oracle.py``)."""
    return MoGlow(
        POSE_DIM,
        control_dim,
        tau=config.tau,
        K=config.K,
        hidden=config.hidden,
        num_layers=config.layers,
        conditioner=config.conditioner,
        base=config.base,
        df=config.df,
        dropout=config.dropout,
        compute_dtype=matmul_dtype(config.compute_dtype),
        residual=config.residual,
        dropout_keeps_last=config.dropout_keeps_last,
        history_noise=config.history_noise,
        residual_world=config.residual_world,
        world_joints=config.world_joints,
        absolute_foot_heights=config.absolute_foot_heights,
        stance_hint=config.stance_hint,
        cond_embedding=config.cond_embedding,
        own_history=config.own_history,
        own_history_passes=config.own_history_passes,
        own_history_temperature=config.own_history_temperature,
        own_history_target=config.own_history_target,
        mask_padded=config.mask_padded,
        rngs=key,
    )


def initialize(model: MoGlow, batch: dict, *, key: jax.Array, standardizer=None) -> MoGlow:
    """Data-dependent initialisation on one batch (pure: returns a new model): with
    ``residual_world`` or ``stance_hint`` the standardiser's units first
    (``MoGlow.with_units``; the training loop passes the run's ``standardizer``), then
    ActNorm."""
    del key
    if model.residual_world or model.stance_hint:
        if standardizer is None:
            raise ValueError(
                "a residual_world or stance_hint MoGlow needs the run's standardizer to "
                "initialise "
                "(initialize(model, batch, key=..., standardizer=dataset.standardizer))"
            )
        s = standardizer
        model = model.with_units(s.pose_mean, s.pose_std, s.control_mean, s.control_std)
    return initialize_from_data(model, batch["pose"], context=batch["control"])


def loss(model: MoGlow, batch: dict, key: jax.Array):
    """Mean NLL per target frame (nats, standardised) with history dropout (and
    ``own_history``, ``history_noise``) from ``key``; with ``model.mask_padded`` the mean
    over the target frames that ``batch["valid"]`` (B, T) marks real (a padded take's frozen
    tail is not scored)."""
    pose = batch["pose"]
    if model.mask_padded:
        ll = model.log_prob(pose, batch["control"], key=key, per_frame=True)  # (B, T')
        scored = batch["valid"][:, pose.shape[-2] - ll.shape[-1] :]
        count = jnp.maximum(jnp.sum(scored, dtype=ll.dtype), 1.0)
        nll = -jnp.sum(jnp.where(scored, ll, 0.0)) / count
    else:
        ll = model.log_prob(pose, batch["control"], key=key)
        nll = -jnp.mean(ll) / model.num_targets(pose.shape[-2])
    return nll, {"nll_per_frame": nll, "bits_per_frame": nll / _LN2}


def evaluate(model: MoGlow, batch: dict, key: jax.Array) -> dict[str, jax.Array]:
    """Per-window log-likelihoods (B,), nats, standardised: see ``SCOPES``."""
    pose, control = batch["pose"], batch["control"]
    return {
        "window": model.log_prob(pose, control, scope="window"),
        "official": model.log_prob(pose, control),
        "official_dropout": model.log_prob(pose, control, key=key),
    }


def window_log_prob(model: MoGlow, pose, control) -> jax.Array:
    """log p(x_1:T | c_1:T) (B,), nats, standardised, for any T >= 1 (the ``window`` scope
    alone: the bench scores prefixes with it, shorter than the ``official`` scope needs)."""
    return model.log_prob(pose, control, scope="window")


@jax.jit
def _sample(model, key, control, temperature, seed_history, seed_control):
    return model.sample(
        key, control, seed_history=seed_history, seed_control=seed_control,
        temperature=temperature,
    )  # fmt: skip


def sample(
    model: MoGlow,
    key: jax.Array,
    control,
    *,
    temperature: float = 1.0,
    seed_history=None,
    seed_pose=None,
    seed_control=None,
) -> jax.Array:
    """Poses (B, T, 63), standardised, following control (B, T, 3) (jitted scan over frames).
    The argument order is that of ``MoGlow.sample(key, control)``; the old ``(model,
    control, key)`` still works, with a ``DeprecationWarning``.

    ``seed_history``: None (zero history, the official start) or (B, S, 63) standardised
    poses that precede the first frame (the last tau are used); ``seed_pose`` is its
    deprecated old name. ``seed_control`` (B, S, 3) standardised: the controls of those
    frames (default zeros, the mean control; :meth:`MoGlow.init_stream`). Samples from
    :func:`motionflows.inference.inference_copy` of the model (separate step weights: the
    same poses, faster on XLA:CPU).
    """
    key, control = key_first("moglow.sample", key, control)
    control, seed_history = check_sample_args(
        control,
        temperature,
        seed_history,
        "moglow.sample",
        control_dim=model.control_dim,
        seed_pose=seed_pose,
    )
    sampler = inference_copy(model)
    return _sample(sampler, key, control, jnp.float32(temperature), seed_history, seed_control)


if __name__ == "__main__":
    from motionflows.training import experiment_main

    raise SystemExit(experiment_main(sys.modules[__name__]))
