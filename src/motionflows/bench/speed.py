"""The bench's speed numbers and the machine they were measured on.

Sampling speed: generated frames per second of wall time at a batch size, the best of a
few repeats after a first (compiling) call, whose extra time is reported as compile time.
"""

from __future__ import annotations

import math
import os
import platform
import time
from pathlib import Path

import numpy as np

from motionflows.bench.budgets import EVAL_CHUNK
from motionflows.runs import experiment_sample


def describe_machine() -> dict:
    """CPU model and vector extensions, visible cores, memory, load, OS, and the
    Python / JAX / Flax versions, backend and devices."""
    import flax
    import jax

    cpu, isa = _cpu()
    devices = jax.devices()
    try:
        load = "load average {:.1f} / {:.1f} / {:.1f} (1 / 5 / 15 min)".format(*os.getloadavg())
    except OSError:
        load = "load unknown"
    return {
        "load": load,
        "cpu": cpu,
        "isa": isa,
        "cores": _cores(),
        "memory": _memory(),
        "platform": f"{platform.system()} {platform.release()}",
        "python": platform.python_version(),
        "jax": jax.__version__,
        "flax": flax.__version__,
        "backend": jax.default_backend(),
        "devices": f"{len(devices)} x {devices[0].device_kind}",
    }


def _cpu() -> tuple[str, list[str]]:
    """(model name, the vector extensions that decide CPU matmul speed)."""
    cpu = platform.processor() or platform.machine()
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
    except OSError:
        return cpu, []
    names = [ln.split(":", 1)[1].strip() for ln in lines if ln.lower().startswith("model name")]
    cpu = names[0] if names else cpu
    flags = set(next((ln for ln in lines if ln.startswith("flags")), "").split())
    return cpu, [x for x in ("avx2", "avx512f", "avx512_bf16", "amx_bf16") if x in flags]


def _cores() -> int | None:
    """CPU cores this process may run on."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count()


def _memory() -> str:
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal"):
                return f"{int(line.split()[1]) / 2**20:.0f} GiB RAM"
    except OSError:
        pass
    return "memory unknown"


def make_sampler(exp, temperature: float):
    """A jitted ``(model, key, control) -> pose`` (standardised) from the experiment's
    ``sample``; falls back to the un-jitted function if the sampler cannot be traced."""
    import jax

    def sample(model, key, control):
        return experiment_sample(exp, model, key, control, temperature=temperature)

    jitted = jax.jit(sample)

    def call(model, key, control):
        nonlocal jitted
        try:
            return jitted(model, key, control)
        except (
            jax.errors.ConcretizationTypeError,
            jax.errors.TracerBoolConversionError,
            jax.errors.TracerArrayConversionError,
        ):
            jitted = sample
            return sample(model, key, control)

    return call


def time_sampler(sampler, model, control: np.ndarray, batch: int, key, repeats: int) -> dict:
    """Sampling speed at ``batch``: frames/s (compile excluded) and compile seconds."""
    import jax

    from motionflows.sharding import data_parallel, shard_batch

    reps = int(math.ceil(batch / len(control)))
    c = np.concatenate([control] * reps)[:batch]
    model, mesh = data_parallel(model, batch)  # placed once, outside the timing
    if mesh is not None:
        c = shard_batch(c, mesh)
    t0 = time.perf_counter()
    jax.block_until_ready(sampler(model, key, c))
    first = time.perf_counter() - t0
    times = []
    for r in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(sampler(model, jax.random.fold_in(key, r + 1), c))
        times.append(time.perf_counter() - t0)
    best = min(times)
    frames = batch * c.shape[1]
    return {"frames_per_s": frames / best, "seconds": best, "compile_s": max(first - best, 0.0)}


def sample_in_chunks(sampler, model, control: np.ndarray, key) -> np.ndarray:
    """Samples (standardised) for every control window (N, T, 3) -> (N, T, D), in padded
    chunks of EVAL_CHUNK (one compiled batch shape); chunk b draws with ``fold_in(key, b)``.
    (``motionflows.run.draw_samples`` is the other sampler: one control in data units.)"""
    import jax

    from motionflows.sharding import data_parallel, shard_batch

    out = []
    n = len(control)
    model, mesh = data_parallel(model, EVAL_CHUNK)
    for b, start in enumerate(range(0, n, EVAL_CHUNK)):
        idx = np.arange(start, start + EVAL_CHUNK) % n
        chunk = control[idx]
        if mesh is not None:
            chunk = shard_batch(chunk, mesh)
        x = sampler(model, jax.random.fold_in(key, b), chunk)
        out.append(np.asarray(x, np.float32)[: min(EVAL_CHUNK, n - start)])
    return np.concatenate(out)


def count_params(model) -> int:
    """Number of parameter values (``nnx.Param`` leaves) of ``model``."""
    import jax
    from flax import nnx

    leaves = jax.tree_util.tree_leaves(nnx.state(model, nnx.Param))
    return int(sum(np.size(x) for x in leaves))
