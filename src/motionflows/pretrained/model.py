"""A trained run wrapped to work in data units: controls in, poses in metres out."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import jax
import numpy as np

from motionflows.data.names import CONTROL_DIM, POSE_DIM
from motionflows.errors import RunError
from motionflows.models.validation import check_input, check_temperature
from motionflows.runs import (
    check_sample_control,
    experiment_sample,
    fixed_length,
    frame_multiple,
    warn_if_control_unseen,
    warn_if_not_window,
    window_scope_evaluate,
)

INFO_FILE = "pretrained.json"
"""Optional file of an exported run: ``{"temperature": T, "scope": ..., "notes": ...}``."""


def _array(x: Any, channels: int, name: str, where: str) -> np.ndarray:
    """``x`` as (B, T, channels) float32 after the models' shared input checks."""
    shape = tuple(np.shape(x))
    if len(shape) != 3 or shape[-1] != channels:
        raise ValueError(f"{where}: {name} must be (B, T, {channels}), got {shape}")
    return np.asarray(check_input(x, name, where))


def read_info(path: Path, module) -> dict:
    """``pretrained.json`` ({} when absent), its temperature and scope checked: a damaged
    file is one ``RunError`` naming it and the fix."""
    if not path.is_file():
        return {}
    fix = "export the run again (motionflows export RUN --out DIR), or delete the file"
    try:
        info = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise RunError(f"{path} cannot be read ({err}); {fix}") from None
    if not isinstance(info, dict):
        raise RunError(f"{path} must hold a JSON object; {fix}")
    if "temperature" in info:
        try:
            check_temperature(info["temperature"], str(path))
        except ValueError as err:
            raise RunError(f"{err}; {fix}") from None
    scopes = list(getattr(module, "SCOPES", {}) or {})
    if info.get("scope") is not None and info["scope"] not in scopes:
        raise RunError(
            f"{path}: scope {info['scope']!r} is not one of {module.NAME}'s {scopes}; {fix}"
        )
    return info


class PretrainedModel:
    """A run's model, standardiser and config behind a data-unit API.

    Attributes:
      module: the experiment module; config: the run's config; model: the trained model
      (standardised units); standardizer: the run's standardiser; temperature: the sampling
      temperature the model was validated at (``pretrained.json``; 1.0 when absent);
      scope: the likelihood scope :meth:`log_prob` returns; fps and window from the config;
      fixed_length: True for a model that samples only its training window (the
      experiment's ``FIXED_LENGTH``: the Glow; the VAE-LSTM samples any T divisible by 4);
      frame_multiple: every T the model draws is a multiple of this (Glow 2**levels,
      VAE-LSTM 4, MoGlow 1).
    """

    def __init__(self, module, config, model, standardizer, *, info: dict | None = None):
        self.module, self.config, self.model = module, config, model
        self.standardizer = standardizer
        info = info or {}
        self.temperature = float(info.get("temperature", 1.0))
        scopes = list(getattr(module, "SCOPES", {}) or {})
        self.scope = info.get("scope") or ("window" if "window" in scopes else scopes[0])
        self.fps = float(config.data.fps)
        self.window = int(config.data.window)
        self.name = getattr(module, "NAME", "model")
        self.fixed_length = fixed_length(module)
        self.frame_multiple = frame_multiple(model)
        self._sample = jax.jit(
            lambda model, key, control, temperature: experiment_sample(
                module, model, key, control, temperature=temperature
            )
        )
        window = window_scope_evaluate(module) if self.scope == "window" else None
        self._evaluate = window or jax.jit(module.evaluate)

    @classmethod
    def from_run(cls, run_dir: str | Path, *, checkpoint: str = "best") -> PretrainedModel:
        """Load any run directory (trained or exported) as a :class:`PretrainedModel`."""
        from motionflows.training import load_run, load_standardizer

        run_dir = Path(run_dir)
        module, config, model, _ = load_run(run_dir, checkpoint=checkpoint, load_data=False)
        info = read_info(run_dir / INFO_FILE, module)
        return cls(module, config, model, load_standardizer(run_dir), info=info)

    def sample(self, control, *, seed: int = 0, temperature: float | None = None) -> np.ndarray:
        """Poses (B, T, 63) in metres for controls (B, T, 3) in m/frame and rad/frame.

        ``temperature`` defaults to :attr:`temperature`; a fixed-length model (Glow) is
        meant for T = :attr:`window` and warns (``UserWarning``) at other lengths. The same
        seed gives the same motion.
        """
        where = "PretrainedModel.sample"
        control = _array(control, CONTROL_DIM, "control", where)
        check_sample_control(
            self.module, self.config, self.model, self.standardizer, control, where, "a control of"
        )
        temp = self.temperature if temperature is None else temperature
        temp = float(check_temperature(temp, where))
        if isinstance(seed, bool) or not isinstance(seed, int | np.integer):
            raise ValueError(f"{where}: seed must be an integer, got {seed!r}")
        c = np.asarray(self.standardizer.normalize_control(control), np.float32)
        x = self._sample(self.model, jax.random.key(int(seed)), c, np.float32(temp))
        return np.asarray(self.standardizer.denormalize_pose(np.asarray(x)), np.float32)

    def log_prob(self, pose, control) -> np.ndarray:
        """Log-likelihood (B,) in nats per frame in metres of poses (B, T, 63) metres given
        controls (B, T, 3), in the scope :attr:`scope` (``"window"``: all T frames; for the
        VAE-LSTM ``"elbo"``, a lower bound). The standardiser's Jacobian is included:
        ``(log p_std + F log|d std / d x|) / F`` over the F scored frames. Warns
        (``UserWarning``) on a control far outside the training data and, for a fixed-length
        model, on T other than :attr:`window`, as :meth:`sample`."""
        where = "PretrainedModel.log_prob"
        pose = _array(pose, POSE_DIM, "pose", where)
        control = _array(control, CONTROL_DIM, "control", where)
        if pose.shape[:2] != control.shape[:2]:
            raise ValueError(f"pose {pose.shape} and control {control.shape} must share (B, T)")
        warn_if_not_window(self.module, self.config, pose.shape[1], where)
        warn_if_control_unseen(self.module, self.config, self.standardizer, control, where)
        batch = {
            "pose": np.asarray(self.standardizer.normalize_pose(pose), np.float32),
            "control": np.asarray(self.standardizer.normalize_control(control), np.float32),
        }
        lls = self._evaluate(self.model, batch, jax.random.key(0))
        ll = np.asarray(lls[self.scope], np.float64)
        scopes = getattr(self.module, "SCOPES", {}) or {}
        frames = pose.shape[1]
        if self.scope in scopes:
            frames = scopes[self.scope].scored_frames(pose.shape[1], self.config)
        ldpf = float(self.standardizer.log_det_per_frame)
        return ((ll + frames * ldpf) / frames).astype(np.float32)

    def __repr__(self) -> str:
        return (
            f"PretrainedModel({self.name}, fps={self.fps:g}, window={self.window}, "
            f"temperature={self.temperature:g}, scope={self.scope!r})"
        )
