"""Test helper: a model whose parameters are moved off their initial values."""

from __future__ import annotations

import jax
from flax import nnx


def perturbed(module, key, scale: float = 0.15):
    """``module`` with every trainable parameter plus ``scale`` * N(0, 1) noise, so that
    zero-initialised heads and identity-initialised layers are non-trivial."""
    graph, params, rest = nnx.split(module, nnx.Param, ...)
    leaves, tdef = jax.tree.flatten(params)
    keys = jax.random.split(key, len(leaves))
    leaves = [p + scale * jax.random.normal(k, p.shape) for p, k in zip(leaves, keys, strict=True)]
    return nnx.merge(graph, jax.tree.unflatten(tdef, leaves), rest)
