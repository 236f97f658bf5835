"""Machine floors for speed figures: measured matmul peak, memory bandwidth, counted FLOPs.

A time means little without the machine it ran on, so the speed benchmarks state each time
also as a multiple of its *floor*, the least time this machine could take for that work::

    floor_s = max(matmul_flops / peak_flops_per_s, bytes_read / bandwidth_bytes_per_s)
    multiple = measured_s / floor_s          (1.0 = at the machine's limit)

* :func:`gemm_peak` measures the peak: the best of N runs of one jitted matmul
  (m x k) @ (k x n), in float32 or with bfloat16 operands and float32 accumulation
  (``preferred_element_type``), the two precisions the models run their conditioners in.
  The default 7000 x 1206 x 2048 is the paper-size MoGlow's largest matmul (100 x 70
  frames, 31 + 663 inputs + 512 hidden, 4 x 512 gates).
* :func:`memory_bandwidth` measures read bandwidth: the best of N reads of a large float32
  array (a sum, and a matrix-vector product, which is how batch-1 sampling reads weights).
* :func:`matmul_flops` counts the matrix-product FLOPs (2 per multiply-add of every
  ``dot_general`` and convolution) in a function's jaxpr, nested ``scan`` bodies times their
  length, after dead-code elimination (a product whose result nothing uses is not run).
  XLA's own ``compiled.cost_analysis()`` counts a loop body once, so for the
  scanned flows it undercounts by the number of frames and steps. Elementwise work is not
  counted: on the models here it is a small fraction, and it makes the floor a lower bound.
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
from jax.extend import core as jex_core

__all__ = ["memory_bandwidth", "floor_entry", "gemm_peak", "matmul_flops", "tree_bytes"]

PAPER_GEMM = (7000, 1206, 2048)


def _best_seconds(fn: Callable[[], Any], repeats: int) -> float:
    jax.block_until_ready(fn())  # compile and warm the caches
    best = math.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        best = min(best, time.perf_counter() - t0)
    return best


def gemm_peak(
    shape: tuple[int, int, int] = PAPER_GEMM, dtype: str = "float32", repeats: int = 5
) -> dict:
    """Measured matmul throughput: {"dtype", "shape" (m, k, n), "seconds" (best), "flops_per_s"}.

    ``dtype`` "float32", or "bfloat16" for bfloat16 operands with float32 accumulation.
    """
    m, k, n = shape
    ka, kb = jax.random.split(jax.random.key(0))
    a = jax.random.normal(ka, (m, k), jnp.float32).astype(dtype)
    b = jax.random.normal(kb, (k, n), jnp.float32).astype(dtype)
    f = jax.jit(lambda a, b: jnp.matmul(a, b, preferred_element_type=jnp.float32))
    seconds = _best_seconds(lambda: f(a, b), repeats)
    return {
        "dtype": dtype,
        "shape": [m, k, n],
        "seconds": seconds,
        "flops_per_s": 2.0 * m * k * n / seconds,
    }


def memory_bandwidth(nbytes: int = 1 << 28, repeats: int = 5) -> dict:
    """Measured read bandwidth over a float32 array of ``nbytes``: {"bytes", "seconds",
    "bytes_per_s", "by"}, the best of a sum over the array and a matrix-vector product
    with it (the batch-1 sampler's access pattern: every weight read once).

    Why not a copy: ``x * 2`` writes a fresh output buffer each call, and first-touching it
    (page faults) made it ~5x slower than reading here, which would put the floor above
    times actually measured.
    """
    cols = 2048 if nbytes >= 4 * 2048 * 64 else 256
    rows = max(1, nbytes // (4 * cols))  # a whole number of rows: any size works
    x = jnp.ones((rows * cols,), jnp.float32)
    m, v = x.reshape(-1, cols), jnp.ones((cols,), jnp.float32)
    best = {}
    for name, f, args in (("sum", jnp.sum, (x,)), ("matvec", jnp.matmul, (m, v))):
        jitted = jax.jit(f)
        best[name] = _best_seconds(lambda jitted=jitted, args=args: jitted(*args), repeats)
    by = min(best, key=best.get)
    return {
        "bytes": int(x.nbytes),
        "seconds": best[by],
        "bytes_per_s": x.nbytes / best[by],
        "by": by,
    }


def tree_bytes(tree: Any) -> int:
    """Total bytes of the arrays in a pytree (e.g. a model's parameters)."""
    return int(sum(x.nbytes for x in jax.tree.leaves(tree) if hasattr(x, "nbytes")))


def _eqn_flops(eqn) -> int:
    name = eqn.primitive.name
    if name == "dot_general":
        (lhs_contract, _), _ = eqn.params["dimension_numbers"]
        lhs = eqn.invars[0].aval.shape
        out = eqn.outvars[0].aval.shape
        return 2 * math.prod(out) * math.prod(lhs[i] for i in lhs_contract)
    if name == "conv_general_dilated":
        rhs = eqn.invars[1].aval.shape  # kernel: out features x in / groups x spatial
        out = eqn.outvars[0].aval.shape
        per_output = math.prod(rhs) // rhs[eqn.params["dimension_numbers"].rhs_spec[0]]
        return 2 * math.prod(out) * per_output
    return 0


def _sub_jaxprs(value: Any):
    if isinstance(value, jex_core.ClosedJaxpr):
        yield value.jaxpr
    elif isinstance(value, jex_core.Jaxpr):
        yield value
    elif isinstance(value, tuple | list):
        for v in value:
            yield from _sub_jaxprs(v)


def _jaxpr_flops(jaxpr) -> int:
    total = 0
    for eqn in jaxpr.eqns:
        total += _eqn_flops(eqn)
        if eqn.primitive.name == "cond":  # one branch runs: count the dearest
            total += max(_jaxpr_flops(j) for j in _sub_jaxprs(eqn.params["branches"]))
            continue
        inner = sum(_jaxpr_flops(j) for v in eqn.params.values() for j in _sub_jaxprs(v))
        if eqn.primitive.name == "scan":
            inner *= int(eqn.params["length"])
        total += inner  # a while loop's trip count is unknown: its body counts once
    return total


def _live(jaxpr):
    """``jaxpr`` without the equations whose results nothing uses (JAX's own dead-code
    elimination, which recurses into scan bodies), as XLA compiles it: a hand-written VJP
    that also computes the cotangent of a data input (``nets.precision.matmul``) traces that
    product, and XLA drops it. JAX exposes the pass only privately; without it the count
    keeps such products, and a warning says so."""
    try:
        from jax._src.interpreters import partial_eval as pe

        return pe.dce_jaxpr(jaxpr, [True] * len(jaxpr.outvars))[0]
    except (ImportError, AttributeError, TypeError) as err:  # another JAX's internals
        warnings.warn(
            f"roofline.matmul_flops: JAX's dead-code elimination is unavailable ({err}); "
            "products whose results are unused are counted, so floors may be too high",
            RuntimeWarning,
            stacklevel=3,
        )
        return jaxpr


def matmul_flops(fn: Callable, *args, **kwargs) -> int:
    """Matrix-product FLOPs of one call ``fn(*args, **kwargs)`` (traced, not run): those of
    the products whose results are used, which are the ones XLA runs (before 2026-12-07 the
    count kept the unused ones: the bfloat16 MoGlow step's floor was ~11 % high at the paper
    size, 37 % in the quick configuration)."""
    return _jaxpr_flops(_live(jax.make_jaxpr(fn)(*args, **kwargs).jaxpr))


def floor_entry(
    seconds: float,
    *,
    flops: float = 0.0,
    peak_flops_per_s: float | None = None,
    bytes_read: float = 0.0,
    bandwidth_bytes_per_s: float | None = None,
) -> dict:
    """{"floor_s", "multiple_of_floor", "bound"} for a measured ``seconds``; "bound" says
    which limit sets the floor ("compute" or "memory")."""
    compute = flops / peak_flops_per_s if peak_flops_per_s else 0.0
    memory = bytes_read / bandwidth_bytes_per_s if bandwidth_bytes_per_s else 0.0
    floor = max(compute, memory)
    return {
        "floor_s": floor,
        "multiple_of_floor": seconds / floor if floor > 0 else None,
        "bound": "compute" if compute >= memory else "memory",
    }


def machine_lines(machine: dict, peaks: dict) -> list[str]:
    """The speed benchmarks' header for people: the machine, the load average at start and
    end, and the measured GEMM and memory peaks (``machine`` with ``load_average_after``)."""
    m = machine
    return [
        f"{m['cpu']} ({', '.join(m['isa']) or 'no AVX'}), {m['cores']} cores, {m['devices']}",
        "load average at start {:.2f} / {:.2f} / {:.2f}, at end {:.2f} / {:.2f} / {:.2f}".format(
            *m["load_average_1_5_15"], *m["load_average_after"]
        ),
        "measured peaks: GEMM {} float32 {:.0f} GFLOP/s, bfloat16 {:.0f} GFLOP/s; "
        "memory read {:.1f} GB/s".format(
            "x".join(map(str, peaks["gemm"]["float32"]["shape"])),
            peaks["gemm"]["float32"]["flops_per_s"] / 1e9,
            peaks["gemm"]["bfloat16"]["flops_per_s"] / 1e9,
            peaks["memory"]["bytes_per_s"] / 1e9,
        ),
    ]


def machine() -> dict:
    """The machine (:func:`motionflows.bench.describe_machine`) plus the raw load average."""
    import os

    from motionflows.bench import describe_machine

    return {**describe_machine(), "load_average_1_5_15": list(os.getloadavg())}


def measure_peaks(quick: bool) -> dict:
    """This machine's floors, measured now: GEMM peak per precision and memory read bandwidth."""
    shape = (1024, 512, 1024) if quick else PAPER_GEMM
    repeats = 3 if quick else 7
    return {
        "gemm": {dt: gemm_peak(shape, dt, repeats) for dt in ("float32", "bfloat16")},
        "memory": memory_bandwidth(1 << 25 if quick else 1 << 29, repeats),
        "memory_repeats": repeats,
    }


def device_peak_bytes() -> int | None:
    """Peak bytes in use on the first device, where the backend reports it (else None)."""
    try:
        stats = jax.devices()[0].memory_stats()
    except Exception:  # noqa: BLE001 - CPU backends may not implement it
        return None
    if not stats:
        return None
    return int(stats.get("peak_bytes_in_use", stats.get("bytes_in_use", 0)))


def weight_read(weight_bytes: int, repeats: int) -> dict:
    """Read bandwidth (:func:`memory_bandwidth`) over an array the size of the weights."""
    # weights that fit in a cache are read at the cache's speed: read an array of their size
    return memory_bandwidth(max(weight_bytes, 1 << 20), repeats)


def timings(fn: Callable[[], Any], repeats: int) -> list[float]:
    """Seconds of each of ``repeats`` calls of ``fn`` (each waited for until ready)."""
    out = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        out.append(time.perf_counter() - t0)
    return out


def compile_timed(jitted: Callable, *args) -> tuple[Any, float]:
    """(compiled, seconds) of the ahead-of-time ``jitted.lower(*args).compile()``."""
    t0 = time.perf_counter()
    compiled = jitted.lower(*args).compile()
    return compiled, time.perf_counter() - t0


def compiled_memory(compiled) -> dict:
    """XLA's temp, argument and output bytes of a compiled function ({} if not reported)."""
    try:
        mem = compiled.memory_analysis()
        return {
            "temp_bytes": int(mem.temp_size_in_bytes),
            "argument_bytes": int(mem.argument_size_in_bytes),
            "output_bytes": int(mem.output_size_in_bytes),
        }
    except Exception:  # noqa: BLE001 - not every backend reports it
        return {}
