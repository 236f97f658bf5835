"""Fixed-length Glow (MoGlow paper, Sec. 3): one-shot windows of poses, with or without control.

Run: ``python -m experiments.glow_fixed --preset quick`` (synthetic data, minutes on a CPU),
``--data bandai`` for the Bandai-Namco dev set, ``--set conditional=false`` for the
unconditional model, ``--set prior=learned`` for glow-pytorch's learned split prior.

Training objective: the mean negative log-likelihood per frame of whole windows, in nats,
standardised space: ``-mean_b log p(x_b | c_b) / T``. ``evaluate`` gives the exact
per-window log-likelihood over all T frames (key ``"window"``); the runner turns it into
nats/frame in metres and bits/frame standardised.
"""

from __future__ import annotations

import dataclasses
import math
import sys

import jax
import jax.numpy as jnp
from flax import nnx

from motionflows.bijectors import initialize_from_data
from motionflows.config import (
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
from motionflows.models.glow import COUPLINGS, PRIORS, Glow
from motionflows.models.validation import check_sample_args

NAME = "glow_fixed"
CAUSAL = False  # a joint density of a fixed-length window
FIXED_LENGTH = True  # trained on config.data.window frames; other lengths warn

_LN2 = math.log(2.0)


@dataclasses.dataclass(frozen=True)
class Config:
    """Glow experiment config: data, training, and the model fields below."""

    data: DataConfig = DataConfig()
    train: TrainConfig = TrainConfig()
    levels: int = 4  # L: squeeze levels; data.window must be divisible by 2**L
    K: int = 32  # flow steps per level (MoGlow's config calls it K too)
    hidden: int = 512  # coupling nets' hidden width
    conditional: bool = True  # condition on the control signal (False = unconditional)
    prior: str = "standard"  # "standard" (paper) or "learned" (glow-pytorch split prior)
    compute_dtype: str = "auto"  # coupling nets' conv precision: "auto" | "float32" | "bfloat16"
    coupling: str = "affine"  # "affine" (paper) | "additive" (volume-preserving, never amplifies)
    coupling_eps: float = 1e-6  # floor of the affine coupling scale
    residual: bool = False  # flow the first frame and the frame-to-frame changes (our option)
    residual_decay: float = 1.0  # with residual: u_t = x_t - a x_{t-1}, a in (0, 1]

    def __post_init__(self):
        if self.levels < 1 or self.K < 1 or self.hidden < 1:
            raise ValueError(
                f"levels, K and hidden must be >= 1, got {self.levels}, {self.K}, {self.hidden}"
            )
        multiple = 2**self.levels
        if self.data.window % multiple:
            raise ValueError(
                f"Glow with levels={self.levels} needs data.window divisible by 2**levels = "
                f"{multiple}, got window={self.data.window}; change data.window or levels"
            )
        if self.prior not in PRIORS:
            raise ValueError(f"prior must be one of {PRIORS}, got {self.prior!r}")
        if self.coupling not in COUPLINGS:
            raise ValueError(f"coupling must be one of {COUPLINGS}, got {self.coupling!r}")
        check_compute_dtype(self.compute_dtype)
        check_fields(self, MODEL_LIMITS)
        if not 0.0 < self.residual_decay <= 1.0:
            raise ValueError(f"residual_decay must be in (0, 1], got {self.residual_decay}")
        if self.residual_decay != 1.0 and not self.residual:
            raise ValueError("residual_decay needs residual=true (it shapes the change)")


MODEL_LIMITS = {  # as cfg.check_fields reads them: (lowest, highest, lowest ok?, highest ok?)
    "coupling_eps": (0.0, 1.0, True, False),
}


PRESETS: dict[str, Config] = {
    # MoGlow paper (Henter, Alexanderson & Beskow 2020), Sec. 3 and 5.2, with the optimiser
    # of the glow-pytorch code the authors started from (../shared/OFFICIAL_RECIPES.md):
    # L = 4 levels, K = 32 steps, coupling nets with two hidden conv layers of 512 channels
    # and ReLU, the control squeezed with x but never split, 20k steps, the MoGlow data
    # (80-frame windows, mirror and time reversal, standardiser on the augmented training
    # set), batch 100; Adam lr 1e-3, betas (0.9, 0.9999), noam warm-up 4000 with a 1e-4
    # floor, clip values 5 then global norm 100; glow-pytorch's learned split prior.
    # Not reproduced: glow-pytorch's ActNorm after each hidden conv and the exp(3 * logs)
    # output scale of its zero-initialised last conv (our net: conv3 -> ReLU -> conv1 ->
    # ReLU -> zero conv3).
    "paper": Config(
        data=DataConfig(
            window=80, hop=10, mirror=True, reverse=True, root_sigma_s=HOLDEN_ROOT_SIGMA_S
        ),
        train=TrainConfig(
            steps=20_000,
            batch_size=100,
            lr=1e-3,
            b1=0.9,
            b2=0.9999,
            warmup_steps=4000,
            schedule="noam",
            min_lr_ratio=0.1,
            clip_value=5.0,
            clip_norm=100.0,
            eval_every=1000,
            checkpoint_every=2000,
        ),
        prior="learned",
    ),
    # Minutes on 2 CPU cores: 1.6 s windows, a small flow, a smaller synthetic set.
    "quick": Config(
        data=DataConfig(window=32, hop=8, synthetic_clips=60),
        train=TrainConfig(
            steps=2000,
            batch_size=32,
            lr=1e-3,
            warmup_steps=50,
            clip_value=5.0,
            clip_norm=100.0,
            eval_every=500,
            eval_batches=4,
            log_every=20,
            checkpoint_every=1000,
        ),
        levels=2,
        K=8,
        hidden=128,
    ),
}
# At most 60 minutes of training on 2 CPU cores (docs/readme/cpu_budget.md has the search):
# the quick flow (L = 2, K = 8, width 128) on the 4 s windows the bench scores, 20000 steps
# (45.5 min on the idle 2-core EPYC; 12000 steps slid 25 % more with a 27 % higher pose FD
# on the unseen performer, for a 7 nats/frame better test NLL) with additive couplings: the
# affine coupling's scale lies in (eps, 1 + eps), so sampling can only amplify, and 3-4 %
# of the affine model's samples on the unseen performer blew up; additive: none of 256
# (docs/readme/glow.md). Since 2026-12-05 it flows the leaky change (residual, a = 0.9):
# on the unseen performer, two seeds, jerk 1.04-1.06x the data's (poses: 1.52x), 18-27 %
# less sliding and 68-69 nats/frame more likelihood, the Frechet distances within the
# seeds' spread; a = 1 drifts off the floor (glow.md, "Flowing the change").
PRESETS["cpu"] = Config(
    data=DataConfig(window=80, hop=10, mirror=True),
    train=TrainConfig(
        steps=20000,
        batch_size=32,
        lr=1e-3,
        warmup_steps=200,
        schedule="cosine",
        min_lr_ratio=0.05,
        clip_value=5.0,
        clip_norm=100.0,
        eval_every=1000,
        eval_batches=4,
        log_every=50,
        checkpoint_every=1000,
    ),
    levels=2,
    K=8,
    hidden=128,
    coupling="additive",
    residual=True,
    residual_decay=0.9,
    compute_dtype="float32",  # a CPU budget: the precision it was searched and shipped in
)
# Seconds: tests and the bench's smoke budget (a CI-sized flow, 30 steps, 1.6 s windows).
PRESETS["smoke"] = dataclasses.replace(
    PRESETS["quick"],
    data=DataConfig(**SMOKE_DATA),
    train=smoke_train(PRESETS["quick"].train),
    levels=2,
    K=2,
    hidden=16,
)
PRESETS["paper_unconditional"] = dataclasses.replace(PRESETS["paper"], conditional=False)
PRESETS["quick_unconditional"] = dataclasses.replace(PRESETS["quick"], conditional=False)

SCOPES: dict[str, Scope] = {
    "window": Scope("log p(x_1:T | c_1:T) of the whole window, all T frames, exact"),
}


def build(config: Config, *, key: jax.Array) -> Glow:
    """The Glow of ``config`` with fresh parameters drawn from ``key``."""
    return Glow(
        POSE_DIM,
        levels=config.levels,
        K=config.K,
        hidden=config.hidden,
        control_dim=CONTROL_DIM if config.conditional else 0,
        prior=config.prior,
        compute_dtype=matmul_dtype(config.compute_dtype),
        coupling=config.coupling,
        coupling_eps=config.coupling_eps,
        length=config.data.window,
        residual=config.residual,
        residual_decay=config.residual_decay,
        rngs=nnx.Rngs(params=key),
    )


def _control(model: Glow, batch: dict):
    return batch["control"] if model.conditional else None


def initialize(model: Glow, batch: dict, *, key: jax.Array) -> Glow:
    """Data-dependent ActNorm initialisation on one batch (pure: returns a new model)."""
    del key
    return initialize_from_data(model, batch["pose"], context=_control(model, batch))


def loss(model: Glow, batch: dict, key: jax.Array):
    """Mean NLL per frame (nats, standardised), with bits/frame in the metrics."""
    del key
    ll = model.log_prob(batch["pose"], _control(model, batch))
    nll = -jnp.mean(ll) / batch["pose"].shape[-2]
    return nll, {"nll_per_frame": nll, "bits_per_frame": nll / _LN2}


def evaluate(model: Glow, batch: dict, key: jax.Array) -> dict:
    """``{"window": (B,)}``: exact log p(x_1:T | c_1:T) per window (nats, standardised)."""
    del key
    return {"window": model.log_prob(batch["pose"], _control(model, batch))}


def sample(
    model: Glow,
    key,
    control,
    *,
    temperature: float = 1.0,
    seed_history=None,
    seed_pose=None,
):
    """Poses (B, T, 63), standardised, for standardised control (B, T, 3).

    The unconditional model uses the control only for its shape. ``seed_history`` (old
    name ``seed_pose``, deprecated) is checked but ignored: a fixed-length Glow generates
    the whole window at once and cannot condition on given first frames. The old argument
    order ``(model, control, key)`` still works, with a ``DeprecationWarning``.
    """
    key, control = key_first("glow_fixed.sample", key, control)
    control, _ = check_sample_args(
        control, temperature, seed_history, "glow_fixed.sample", seed_pose=seed_pose
    )
    if model.conditional:
        return model.sample(key, control, temperature=temperature)
    b, t = control.shape[:2]
    return model.sample(key, num=b, length=t, temperature=temperature)


if __name__ == "__main__":
    from motionflows.training import experiment_main

    raise SystemExit(experiment_main(sys.modules[__name__]))
