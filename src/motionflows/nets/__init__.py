"""Conditioner networks for coupling layers (all with zero-initialised output layers).

``MLP`` / ``coupling_mlp`` (per frame, :mod:`motionflows.nets.mlp`) are imported eagerly;
the sequence networks (``ConvNet``, ``TimeConv`` in :mod:`motionflows.nets.conv`, ``LSTM``,
``LSTMLayer`` in :mod:`motionflows.nets.lstm`; MoGlow's ``LSTMConditioner``,
``FeedForwardConditioner`` and ``CondEmbedding`` in :mod:`motionflows.nets.moglow_conditioners`)
are imported on first access.
"""

from __future__ import annotations

import importlib

from motionflows.nets.mlp import MLP, coupling_mlp

_LAZY = {
    "ConvNet": "motionflows.nets.conv",
    "TimeConv": "motionflows.nets.conv",
    "LSTM": "motionflows.nets.lstm",
    "LSTMLayer": "motionflows.nets.lstm",
    "LSTMConditioner": "motionflows.nets.moglow_conditioners",
    "FeedForwardConditioner": "motionflows.nets.moglow_conditioners",
    "CondEmbedding": "motionflows.nets.moglow_conditioners",
}

__all__ = ["MLP", "coupling_mlp", *_LAZY]


def __getattr__(name: str):
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'motionflows.nets' has no attribute {name!r}")
