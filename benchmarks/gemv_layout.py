"""Batch-1 matrix-vector products on XLA:CPU: which weight layout and dtype read at memory speed.

Batch-1 sampling of the paper-size MoGlow reads every conditioner weight once per frame, so
its floor is the weights' bytes over the read bandwidth. This script times the product
``y[k] = x[k] @ W[k]`` over K stacked (in x out) weights (default: 16 x 1206 x 2048, the
paper-size coupling LSTMs' input projection) in several forms, each jitted, best and median
of ``--repeats`` calls, and prints the effective read bandwidth (weight bytes / best time)
and the largest difference from a float32 ``precision="highest"`` reference:

* float32, weights stored (in, out), as the models store them: ``einsum("kbi,kio->kbo")``;
* float32, weights stored (out, in): the same product with the contraction on the weights'
  contiguous axis;
* bfloat16 weights as a bfloat16 dot with float32 accumulation, as an upcast then a float32
  dot, and as a multiply-and-reduce over either axis.

Prints JSON (the machine, its load before and after, one row per form) on stdout and a table
on stderr. Used for docs/readme/speed.md::

    python benchmarks/gemv_layout.py [--quick]
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import sys

import jax
import jax.numpy as jnp
import numpy as np

from motionflows import roofline


def forms(W32: jax.Array) -> dict:
    """name -> (function of (x, W), the weights it reads)."""
    bf16, f32 = jnp.bfloat16, jnp.float32
    W16 = W32.astype(bf16)
    W32_t = jnp.swapaxes(W32, 1, 2)  # (K, out, in): the contraction on the contiguous axis
    W16_t = jnp.swapaxes(W16, 1, 2)
    return {
        "float32, W (in, out): einsum": (lambda x, W: jnp.einsum("kbi,kio->kbo", x, W), W32),
        "float32, W (out, in): einsum": (lambda x, W: jnp.einsum("kbi,koi->kbo", x, W), W32_t),
        "float32, W (in, out): multiply, sum over in": (
            lambda x, W: jnp.sum(x[:, 0, :, None] * W, axis=1)[:, None],
            W32,
        ),
        "float32, W (out, in): multiply, sum over in": (
            lambda x, W: jnp.sum(W * x, axis=-1)[:, None],
            W32_t,
        ),
        "bfloat16, W (in, out): bf16 dot, f32 accumulation": (
            lambda x, W: jnp.einsum("kbi,kio->kbo", x.astype(bf16), W, preferred_element_type=f32),
            W16,
        ),
        "bfloat16, W (in, out): upcast, f32 einsum": (
            lambda x, W: jnp.einsum("kbi,kio->kbo", x, W.astype(f32)),
            W16,
        ),
        "bfloat16, W (in, out): upcast, multiply, sum over in": (
            lambda x, W: jnp.sum(x[:, 0, :, None] * W.astype(f32), axis=1)[:, None],
            W16,
        ),
        "bfloat16, W (out, in): upcast, multiply, sum over in": (
            lambda x, W: jnp.sum(W.astype(f32) * x, axis=-1)[:, None],
            W16_t,
        ),
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="small weights (a smoke test only)")
    p.add_argument("--repeats", type=int, default=15)
    args = p.parse_args(argv)
    if args.repeats < 1:
        p.error(f"--repeats must be >= 1, got {args.repeats}")
    K, n_in, n_out = (2, 256, 512) if args.quick else (16, 1206, 2048)
    machine = roofline.machine()
    rng = np.random.default_rng(0)
    W32 = jnp.asarray(rng.standard_normal((K, n_in, n_out), dtype=np.float32) * 0.03)
    x = jnp.asarray(rng.standard_normal((K, 1, n_in), dtype=np.float32))
    reference = jnp.einsum("kbi,kio->kbo", x, W32, precision="highest")
    rows = []
    for name, (fn, W) in forms(W32).items():
        jitted = jax.jit(fn)
        y = jax.block_until_ready(jitted(x, W)).reshape(reference.shape)
        seconds = roofline.timings(functools.partial(jitted, x, W), args.repeats)
        best = min(seconds)
        weight_bytes = roofline.tree_bytes(W)
        rows.append(
            {
                "form": name,
                "best_ms": 1e3 * best,
                "median_ms": 1e3 * float(np.median(seconds)),
                "weight_bytes": weight_bytes,
                "read_gb_per_s": weight_bytes / best / 1e9,
                "max_abs_difference": float(jnp.max(jnp.abs(y - reference))),
            }
        )
    machine["load_average_after"] = list(os.getloadavg())
    out = {
        "shape": {"K": K, "in": n_in, "out": n_out, "batch": 1},
        "repeats": args.repeats,
        "machine": machine,
        "rows": rows,
    }
    print(json.dumps(out, indent=1))
    print(
        f"{K} x ({n_in} x {n_out}) weights, batch 1; {machine.get('cpu')}; load "
        f"{machine['load_average_1_5_15'][0]:.2f} -> {machine['load_average_after'][0]:.2f}",
        file=sys.stderr,
    )
    for r in rows:
        line = (
            f"  {r['form']:55s} best {r['best_ms']:7.2f} ms  median {r['median_ms']:7.2f} ms  "
            f"{r['read_gb_per_s']:5.1f} GB/s  max diff {r['max_abs_difference']:.1e}"
        )
        print(line, file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
