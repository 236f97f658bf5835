"""Jitted functions kept across ``train`` / ``load_run`` / ``evaluate_run`` calls in one
process, so a second run of the same experiment (the bench, tests) reuses the compilations."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax

_CACHE: dict = {}
_SIZE = 16


def cached(key: Any, build: Callable[[], Any]) -> Any:
    """``build()`` once per hashable ``key`` (the 16 most recent kept); an unhashable key
    builds anew each time."""
    try:
        hash(key)
    except TypeError:
        return build()
    if key not in _CACHE:
        if len(_CACHE) >= _SIZE:
            _CACHE.pop(next(iter(_CACHE)))
        _CACHE[key] = build()
    return _CACHE[key]


def jitted_evaluate(module: Any):
    """``jax.jit(module.evaluate)``, one per evaluate function."""
    return cached(("evaluate", module.evaluate), lambda: jax.jit(module.evaluate))
