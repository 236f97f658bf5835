"""Exact baselines: per-frame diagonal Gaussian and linear-Gaussian AR (closed-form fits).

Run: ``python -m experiments.baselines --preset quick --data synthetic`` (linear AR) or
``--set model=gaussian``. The trainer calls :func:`fit` (closed form) instead of gradient
steps; ``--set`` of ``train.*`` fields other than the batch size has no effect on a fit.
"""

from __future__ import annotations

import dataclasses
import math
import sys

import jax
import jax.numpy as jnp

from motionflows.config import INF, SMOKE_DATA, DataConfig, Scope, TrainConfig, check_fields
from motionflows.deprecation import key_first
from motionflows.models.baselines import (
    DiagonalGaussian,
    LinearGaussianAR,
    fit_gaussian,
    fit_linear_ar,
)
from motionflows.models.validation import check_sample_args

NAME = "baselines"
CAUSAL = True  # autoregressive (the Gaussian: frames independent)


@dataclasses.dataclass(frozen=True)
class Config:
    data: DataConfig = DataConfig()
    train: TrainConfig = TrainConfig(steps=0, batch_size=64, eval_batches=8)
    model: str = "linear_ar"  # "gaussian" or "linear_ar"
    tau: int = 10  # AR history length (frames); also the official scope's skipped frames
    covariance: str = "full"  # AR residual covariance: "full" or "diag"
    ridge: float = 1e-4  # ridge on the AR weights (standardised features)
    fit_scope: str = "window"  # AR fit objective: "window" (zero history) or "official"
    fit_windows: int | None = None  # at most this many training windows in the fit

    def __post_init__(self):
        for name, allowed in CHOICES.items():
            if getattr(self, name) not in allowed:
                raise ValueError(
                    f"{name} must be one of {', '.join(allowed)}, got {getattr(self, name)!r}"
                )
        check_fields(self, MODEL_LIMITS)
        if self.tau >= self.data.window:
            raise ValueError(
                f"tau must be less than data.window (the official scope scores frames "
                f"tau..T-1), got tau={self.tau}, window={self.data.window}"
            )


CHOICES = {
    "model": ("gaussian", "linear_ar"),
    "covariance": ("full", "diag"),
    "fit_scope": ("window", "official"),
}
MODEL_LIMITS = {  # as check_fields reads them: (lowest, highest, lowest ok?, highest ok?)
    "tau": (1, INF, True, True),
    "ridge": (0.0, 1e6, True, True),
    "fit_windows": (1, INF, True, True),
}


PRESETS: dict[str, Config] = {
    "paper": Config(),
    "quick": Config(fit_windows=1024),
    "cpu": Config(),  # closed-form fits on every training window: seconds
    "gaussian": Config(model="gaussian"),
    "linear_ar_diag": Config(covariance="diag"),
    # Seconds: tests and the bench's smoke budget (a small synthetic set, 1.6 s windows).
    "smoke": Config(
        data=DataConfig(**SMOKE_DATA),
        fit_windows=1024,
    ),
}

BENCH_MODELS: dict[str, dict] = {
    "gaussian": {"model": "gaussian"},
    "linear_ar": {"model": "linear_ar"},
}
"""The models ``motionflows bench`` runs from this experiment: name -> the Config fields."""

SCOPES: dict[str, Scope] = {
    "window": Scope("log p(x_1:T | c_1:T), all T frames; AR history before frame 1 = zeros"),
    "official": Scope("frames tau..T-1 given the true first tau frames", skip="tau"),
}


def build(config: Config, *, key: jax.Array):
    """The untrained baseline (zeros mean / unit covariance); ``key`` is unused."""
    del key
    if config.model == "gaussian":
        model = DiagonalGaussian()
        model.tau = int(config.tau)  # frames the official scope leaves out
        return model
    if config.model == "linear_ar":
        return LinearGaussianAR(config.tau, covariance=config.covariance, ridge=config.ridge)
    raise ValueError(f"model must be 'gaussian' or 'linear_ar', got {config.model!r}")


def loss(model, batch, key):
    """Mean negative window log-likelihood per frame (nats, standardised)."""
    del key
    ll = model.log_prob(batch["pose"], batch["control"])
    nll = -jnp.mean(ll) / batch["pose"].shape[1]
    return nll, {"nll_per_frame": nll}


def evaluate(model, batch, key):
    """``{"window": (B,), "official": (B,)}`` log-likelihoods (nats, standardised)."""
    del key
    skip = model.tau
    return {
        "window": model.log_prob(batch["pose"], batch["control"]),
        "official": model.log_prob(batch["pose"], batch["control"], skip=skip),
    }


def sample(model, key, control, *, temperature=1.0, seed_history=None, seed_pose=None):
    """Poses (B, T, 63), standardised, for standardised control (B, T, 3); the linear AR
    starts from ``seed_history`` (B, S, 63) when given (``seed_pose``: its deprecated old
    name), the Gaussian ignores it. The old argument order ``(model, control, key)`` still
    works, with a ``DeprecationWarning``."""
    key, control = key_first("baselines.sample", key, control)
    control, seed_history = check_sample_args(
        control, temperature, seed_history, "baselines.sample", seed_pose=seed_pose
    )
    if isinstance(model, DiagonalGaussian):
        return model.sample(key, control.shape[:2], temperature=temperature)
    return model.sample(key, control, temperature=temperature, seed_history=seed_history)


def fit(model, dataset, *, config: Config | None = None):
    """Closed-form maximum-likelihood fit on (up to ``fit_windows``) training windows."""
    config = config or PRESETS["paper"]
    bs = config.train.batch_size
    n = len(dataset.train.pose)
    if config.fit_windows is not None:
        n = min(n, config.fit_windows)
    batches = (
        dataset.batch("train", bs, seed=config.train.seed, index=i)
        for i in range(max(1, math.ceil(n / bs)))
    )
    if isinstance(model, DiagonalGaussian):
        return fit_gaussian(model, batches)
    if config.fit_scope not in ("window", "official"):
        raise ValueError(f"fit_scope must be 'window' or 'official', got {config.fit_scope!r}")
    skip = 0 if config.fit_scope == "window" else model.tau
    return fit_linear_ar(model, batches, skip=skip)


if __name__ == "__main__":
    from motionflows.training import experiment_main

    sys.exit(experiment_main(sys.modules[__name__]))
