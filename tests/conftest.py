"""Generic test fixtures shared by the whole suite (keep this file small)."""

from __future__ import annotations

import jax
import pytest


@pytest.fixture
def key() -> jax.Array:
    """A fixed PRNG key; tests split it for every draw."""
    return jax.random.key(0)
