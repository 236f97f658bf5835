"""MoGlow (MoGlow paper, Sec. 4): autoregressive, control-conditioned Glow with LSTM couplings.

Run: ``python -m experiments.moglow --preset quick`` (synthetic data, minutes on a CPU),
``--preset paper`` (the paper's locomotion configuration), ``--preset preferred`` (the same
with history dropout 0.7), ``--set conditioner=ff`` for the Markov (feed-forward) ablation,
``--set compute_dtype=bfloat16`` for bfloat16 conditioner matmuls.

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
from motionflows.config import DataConfig, Scope, TrainConfig
from motionflows.data.names import CONTROL_DIM, POSE_DIM
from motionflows.models.moglow import MoGlow

NAME = "moglow"

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
    compute_dtype: str = "float32"  # conditioner matmuls: "float32" | "bfloat16"
    conditioner: str = "lstm"  # "lstm" (MoGlow) | "ff" (Markov ablation)
    base: str = "normal"  # "normal" | "studentt"
    df: float = 5.0  # Student-t degrees of freedom (base = "studentt")

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
        if self.compute_dtype not in ("float32", "bfloat16"):
            raise ValueError(
                f"compute_dtype must be 'float32' or 'bfloat16', got {self.compute_dtype!r}"
            )
        if self.conditioner not in ("lstm", "ff"):
            raise ValueError(f"conditioner must be 'lstm' or 'ff', got {self.conditioner!r}")
        if self.base not in ("normal", "studentt"):
            raise ValueError(f"base must be 'normal' or 'studentt', got {self.base!r}")


PRESETS: dict[str, Config] = {
    # The paper's locomotion model (Henter, Alexanderson & Beskow 2020, Sec. 4-5 and the
    # authors' public StyleGestures locomotion hparams, as remembered, not re-checked):
    # K = 16 steps, 2-layer LSTM with 512 units, tau = 10 frames of history, history dropout
    # 0.95, batch 100 windows of 80 frames (4 s at 20 fps), Adam lr 1e-3 with a 1000-step
    # warm-up ("noam" schedule with a 1e-4 floor, approximated here by a cosine decay to
    # 0.1 * lr), gradient clipping by value 5 and by global norm 100. The step count is an
    # assumption.
    "paper": Config(
        data=DataConfig(window=80, hop=10),
        train=TrainConfig(
            steps=80_000,
            batch_size=100,
            lr=1e-3,
            warmup_steps=1000,
            schedule="cosine",
            min_lr_ratio=0.1,
            clip_value=5.0,
            clip_norm=100.0,
            eval_every=2000,
            checkpoint_every=2000,
        ),
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
# The paper's configuration with the milder history dropout the authors later preferred.
PRESETS["preferred"] = dataclasses.replace(PRESETS["paper"], dropout=0.7)
PRESETS["paper_markov"] = dataclasses.replace(PRESETS["paper"], conditioner="ff")
PRESETS["quick_markov"] = dataclasses.replace(PRESETS["quick"], conditioner="ff")

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
        "as 'official' but with the training-time history dropout (random, key-dependent), "
        "comparable with the official validation curves",
        skip="tau",
    ),
}


def build(config: Config, *, key: jax.Array) -> MoGlow:
    """The MoGlow of ``config`` with fresh parameters drawn from ``key``."""
    return MoGlow(
        POSE_DIM,
        CONTROL_DIM,
        tau=config.tau,
        num_steps=config.K,
        hidden=config.hidden,
        num_layers=config.layers,
        conditioner=config.conditioner,
        base=config.base,
        df=config.df,
        dropout=config.dropout,
        compute_dtype=None if config.compute_dtype == "float32" else config.compute_dtype,
        rngs=key,
    )


def initialize(model: MoGlow, batch: dict, *, key: jax.Array) -> MoGlow:
    """Data-dependent ActNorm initialisation on one batch (pure: returns a new model)."""
    del key
    return initialize_from_data(model, batch["pose"], context=batch["control"])


def loss(model: MoGlow, batch: dict, key: jax.Array):
    """Mean NLL per target frame (nats, standardised) with history dropout from ``key``."""
    pose = batch["pose"]
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


@jax.jit
def _sample(model, control, key, temperature, seed_pose):
    return model.sample(key, control, seed_history=seed_pose, temperature=temperature)


def sample(
    model: MoGlow, control, key: jax.Array, *, temperature: float = 1.0, seed_pose=None
) -> jax.Array:
    """Poses (B, T, 63), standardised, following control (B, T, 3) (jitted scan over frames).

    ``seed_pose``: None (zero history, the official start) or (B, S, 63) standardised poses
    that precede the first frame (the last tau are used).
    """
    control = jnp.asarray(control, jnp.float32)
    if control.ndim != 3 or control.shape[-1] != CONTROL_DIM:
        raise ValueError(f"sample: control must be (B, T, {CONTROL_DIM}), got {control.shape}")
    if seed_pose is not None:
        seed_pose = jnp.asarray(seed_pose, jnp.float32)
    return _sample(model, control, key, jnp.float32(temperature), seed_pose)


if __name__ == "__main__":
    from motionflows.training import experiment_main

    raise SystemExit(experiment_main(sys.modules[__name__]))
