"""Generic test fixtures shared by the whole suite (keep this file small)."""

from __future__ import annotations

import jax
import pytest


@pytest.fixture
def key() -> jax.Array:
    """A fixed PRNG key; tests split it for every draw."""
    return jax.random.key(0)


@pytest.fixture(scope="module")
def fast_compilation():
    """Switch off most XLA optimisation passes for one test module, then restore.

    On 2 CPU cores compilation dominates tests of many small jitted functions; this JAX
    switch (``jax_disable_most_optimizations``) makes compiling several times cheaper and
    running somewhat slower. Use it in modules that check values, never speed:
    ``pytestmark = pytest.mark.usefixtures("fast_compilation")``.
    """
    old = jax.config.read("jax_disable_most_optimizations")
    jax.config.update("jax_disable_most_optimizations", True)
    yield
    jax.config.update("jax_disable_most_optimizations", old)
