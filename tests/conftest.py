"""Generic test fixtures shared by the whole suite (keep this file small)."""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path

import jax
import pytest

# The suite runs the CLI in-process: keep JAX's persistent compilation cache (which the
# ``motionflows`` command turns on) out of it, so tests neither read stale entries nor
# write to the user's cache; tests/test_compile_cache.py checks the cache itself.
os.environ.setdefault("MOTIONFLOWS_COMPILE_CACHE", "0")
# Commands the suite starts in a subprocess run under the same strict dtype promotion as the
# tests themselves (this process read its JAX config at the import above).
os.environ.setdefault("JAX_NUMPY_DTYPE_PROMOTION", "strict")


def pytest_configure(config):
    config.addinivalue_line(
        "markers",
        "standard_dtypes: run one test under JAX's standard dtype promotion instead of the "
        "suite's strict one (for tests that call a third-party transform directly, such as "
        "optax's Adam, whose bias correction computes float ** int32)",
    )


@pytest.fixture(autouse=True)
def _dtype_promotion(request):
    """Every test runs under ``jax.numpy_dtype_promotion("strict")``: mixing float32 with
    int32 or bfloat16 raises instead of silently widening, so an implicit promotion in the
    library fails the suite. Mark a test ``standard_dtypes`` to opt it out.
    """
    mode = "standard" if request.node.get_closest_marker("standard_dtypes") else "strict"
    with jax.numpy_dtype_promotion(mode):
        yield


@pytest.fixture
def benchmark_script():
    """``load(name)``: the script ``benchmarks/<name>.py`` imported as a module (the scripts
    are not a package), so a test can call its functions."""

    def load(name: str):
        path = Path(__file__).resolve().parents[1] / "benchmarks" / f"{name}.py"
        spec = importlib.util.spec_from_file_location(name, path)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module

    return load


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
