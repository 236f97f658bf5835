"""Generic test fixtures shared by the whole suite (keep this file small)."""

from __future__ import annotations

import os

import jax
import pytest

# The suite runs the CLI in-process: keep JAX's persistent compilation cache (which the
# ``motionflows`` command turns on) out of it, so tests neither read stale entries nor
# write to the user's cache; tests/test_compile_cache.py checks the cache itself.
os.environ.setdefault("MOTIONFLOWS_COMPILE_CACHE", "0")


def pytest_configure(config):
    config.addinivalue_line(
        "markers",
        "strict_dtypes: run under jax_numpy_dtype_promotion='strict' (no implicit dtype "
        "promotion: mixing float32 with int32 or bfloat16 raises instead of silently widening)",
    )
    config.addinivalue_line(
        "markers",
        "standard_dtypes: opt one test of a strict_dtypes module out (optax's Adam computes "
        "float ** int32 in its bias correction, which strict promotion refuses)",
    )


@pytest.fixture(autouse=True)
def _dtype_promotion(request):
    """Strict dtype promotion for tests marked ``strict_dtypes`` (and not ``standard_dtypes``).

    Opt-in per module (``pytestmark = pytest.mark.strict_dtypes``): JAX's own
    ``JAX_NUMPY_DTYPE_PROMOTION=strict`` applies it to everything, and optax's Adam fails then.
    """
    node = request.node
    if node.get_closest_marker("strict_dtypes") and not node.get_closest_marker("standard_dtypes"):
        with jax.numpy_dtype_promotion("strict"):
            yield
    else:
        yield


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
