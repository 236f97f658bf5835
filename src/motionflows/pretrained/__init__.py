"""Trained models shipped with the package, ready to use in data units.

Each model is an exported run directory (``motionflows export RUN --out DIR``: config,
standardiser, metrics and the best parameters, no optimiser state) under
``motionflows/pretrained/models/<name>/``. Every command that takes a run directory also
takes ``pretrained:NAME``::

    motionflows sample pretrained:moglow-bandai --control walk-turn-run

From Python::

    from motionflows import pretrained
    pretrained.available()                      # ['glow-bandai', 'moglow-bandai', ...]
    model = pretrained.load("moglow-bandai")
    pose = model.sample(control)                # (B, T, 3) m/frame, rad/frame -> (B, T, 63) m
    ll = model.log_prob(pose, control)          # (B,) nats per frame in metres

The shipped weights were trained on the Bandai-Namco-Research-Motiondataset (CC BY-NC 4.0):
they inherit its non-commercial terms (see ``models/LICENSE.md``).
"""

from __future__ import annotations

from pathlib import Path

from motionflows.errors import RunError
from motionflows.pretrained.model import PretrainedModel

MODELS_DIR = Path(__file__).with_name("models")
"""Where the shipped run directories live (one folder per name)."""

__all__ = ["MODELS_DIR", "PretrainedModel", "available", "load", "path"]


def available() -> list[str]:
    """Names of the shipped models, sorted.

    Examples:
      >>> from motionflows import pretrained
      >>> "moglow-bandai" in pretrained.available()
      True
    """
    if not MODELS_DIR.is_dir():
        return []
    return sorted(p.name for p in MODELS_DIR.iterdir() if (p / "config.json").is_file())


def path(name: str) -> Path:
    """The run directory of the shipped model ``name``; ``RunError`` for an unknown name."""
    names = available()
    if name not in names:
        listed = ", ".join(names) if names else "none are installed"
        raise RunError(f"no pretrained model {name!r}; available: {listed}")
    return MODELS_DIR / name


def load(name: str) -> PretrainedModel:
    """The shipped model ``name`` as a :class:`PretrainedModel` (data units in and out).

    Examples:
      >>> import numpy as np
      >>> from motionflows import pretrained
      >>> model = pretrained.load("moglow-bandai")
      >>> control = np.zeros((2, 12, 3), np.float32)   # (B, T, 3): m/frame, m/frame, rad/frame
      >>> control[..., 0] = 0.05                        # walk forward at 1 m/s (20 fps)
      >>> pose = model.sample(control, seed=0)          # (B, T, 63) joint positions, metres
      >>> pose.shape, model.log_prob(pose, control).shape   # nats per frame in metres
      ((2, 12, 63), (2,))
    """
    return PretrainedModel.from_run(path(name))
