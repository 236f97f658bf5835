"""Compilations kept for reuse: jitted functions across ``train`` / ``load_run`` /
``evaluate_run`` calls in one process (:func:`cached`), so a second run of the same
experiment (the bench, tests) reuses them; and across processes, JAX's persistent
compilation cache, which the ``motionflows`` command turns on (:func:`use_persistent_cache`).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax

PERSISTENT_CACHE_ENV = "MOTIONFLOWS_COMPILE_CACHE"

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


def use_persistent_cache() -> str | None:
    """Turn on JAX's persistent compilation cache for this process; returns its folder.

    The folder is ``$MOTIONFLOWS_COMPILE_CACHE`` if set, else ``~/.cache/motionflows/jax``
    (``$XDG_CACHE_HOME`` respected). ``MOTIONFLOWS_COMPILE_CACHE=0`` (or ``off``) leaves it
    off, and a ``JAX_COMPILATION_CACHE_DIR`` set by the user wins (JAX reads it itself).
    Every compilation is kept, also the sub-second ones of data initialisation, so a
    repeated ``train`` of the same configuration skips XLA (a 300-step quick MoGlow: 48 s ->
    33-38 s, docs/readme/speed.md). Results are identical: only compiled code is cached.
    The folder grows with every configuration and shape compiled (a few MB for the tests
    and presets) and can be deleted at any time. It has no size limit: JAX's
    (``jax_compilation_cache_max_size``) needs the ``filelock`` package and, with it, fails
    on every entry a cache without the limit wrote (a warning per compilation).
    """
    choice = os.environ.get(PERSISTENT_CACHE_ENV, "").strip()
    if choice.lower() in ("0", "off", "false", "no") or os.environ.get("JAX_COMPILATION_CACHE_DIR"):
        return None
    if choice:
        folder = Path(choice).expanduser()
    else:
        base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
        folder = Path(base) / "motionflows" / "jax"
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError:  # a read-only home: run without the cache rather than fail
        return None
    jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return str(folder)
