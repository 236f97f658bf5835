"""Fixed-length Glow speed: training step, sampling, compile times and memory; prints JSON.

Paper configuration by default (MoGlow paper Sec. 3 / issue: L = 4 levels, K = 32 steps,
512-wide coupling nets, windows of 80 frames of 63 + 3 dims, batch 64 windows), with the
coupling nets' convolutions in float32 and in bfloat16 (``compute_dtype``; the flow's
affine maps, log-dets and base log-probs stay float32). ``--quick`` runs a small
configuration for a smoke test.

    python benchmarks/glow_fixed_speed.py [--quick] [--dtypes float32,bfloat16] [--repeats N]

Timed: one jitted Adam training step (value_and_grad of the mean NLL per frame, clipping
as in the ``paper`` preset) and one jitted sampler call that draws the whole batch of
windows (B x T frames) given the control. Compile times are measured separately (AOT
``lower().compile()``). Memory: XLA's compiled temp/argument sizes, the device's
``memory_stats()`` peak where the backend reports one (GPU/TPU), and the process peak RSS
(``resource.getrusage``; on CPU that is where the arrays live). Parameters are freshly
initialised (no data-dependent ActNorm init: it does not change the cost of a step).

Floors (:mod:`motionflows.roofline`), measured in the same run: every time is also given as a
multiple of the least time this machine could take for it, the step's matrix-product FLOPs
(counted from its jaxpr) over the measured GEMM peak of its precision, or, when larger, the
bytes of the weights over the measured memory read bandwidth. The load average is printed at the
start and at the end (a load above the core count slows every figure).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import sys
import time

import jax
import jax.numpy as jnp
import optax
from flax import nnx

from motionflows import roofline
from motionflows.data.names import CONTROL_DIM, POSE_DIM
from motionflows.models.glow import Glow

PAPER = {"levels": 4, "steps": 32, "hidden": 512, "batch": 64, "window": 80}
QUICK = {"levels": 2, "steps": 2, "hidden": 32, "batch": 8, "window": 16}  # a smoke test


def _build(cfg: dict, dtype: str, k_model) -> tuple[Glow, float]:
    """(the Glow of ``cfg`` at the conditioner precision ``dtype``, seconds to build it)."""
    t0 = time.perf_counter()
    model = Glow(
        POSE_DIM,
        levels=cfg["levels"],
        K=cfg["steps"],
        hidden=cfg["hidden"],
        control_dim=CONTROL_DIM,
        compute_dtype=None if dtype == "float32" else dtype,
        rngs=nnx.Rngs(k_model),
    )
    return model, time.perf_counter() - t0


def _train_step(graph, rest, opt, t: int):
    """One Adam step on the mean NLL per frame of ``t``-frame windows: (params, state, loss)."""

    def train_step(p, s, pose, control):
        def loss(p):
            m = nnx.merge(graph, p, rest)
            return -jnp.mean(m.log_prob(pose, control)) / t

        value, grads = jax.value_and_grad(loss)(p)
        updates, s = opt.update(grads, s, p)
        return optax.apply_updates(p, updates), s, value

    return train_step


def _time_training(res: dict, train_step, args: tuple, peak: float, repeats: int):
    """Add the training step's FLOPs, compile, memory, times and floor; return trained params."""
    b, t = args[2].shape[:2]  # pose (B, T, D)
    res["train_flops"] = roofline.matmul_flops(train_step, *args)
    compiled, res["train_compile_s"] = roofline.compile_timed(
        jax.jit(train_step, donate_argnums=(0, 1)), *args
    )
    res["train_memory"] = roofline.compiled_memory(compiled)
    state = {"p": args[0], "s": args[1]}

    def run_train():
        state["p"], state["s"], value = compiled(state["p"], state["s"], *args[2:])
        return value

    first_loss = float(run_train())  # warm-up
    times = roofline.timings(run_train, repeats)
    res["train_step_s"], res["train_step_s_all"] = statistics.median(times), times
    res["train_frames_per_s"] = b * t / res["train_step_s"]
    res["train_step_floor"] = roofline.floor_entry(
        res["train_step_s"], flops=res["train_flops"], peak_flops_per_s=peak
    )
    res["train_loss_first_last"] = [first_loss, float(run_train())]
    return state["p"]


def _time_sampling(res: dict, model, control, key, repeats: int, peak: float) -> None:
    """Add the sampler's compile time, memory, times, FLOPs and floor (whole batch) to ``res``."""
    sampler = jax.jit(lambda m, c, k: m.sample(k, c))
    fn, res["sample_compile_s"] = roofline.compile_timed(sampler, model, control, key)
    res["sample_memory"] = roofline.compiled_memory(fn)
    out = fn(model, control, key)
    out.block_until_ready()
    res["sample_finite"] = bool(jnp.all(jnp.isfinite(out)))
    times = roofline.timings(lambda: fn(model, control, key), max(repeats, 3))
    res["sample_s"], res["sample_s_all"] = statistics.median(times), times
    res["sample_ms_per_frame"] = 1e3 * res["sample_s"] / (control.shape[0] * control.shape[1])
    res["sample_flops"] = roofline.matmul_flops(lambda m, c, k: m.sample(k, c), model, control, key)
    res["sample_floor"] = roofline.floor_entry(
        res["sample_s"],
        flops=res["sample_flops"],
        peak_flops_per_s=peak,
        bytes_read=res["weight_bytes"],
        bandwidth_bytes_per_s=res["weight_read"]["bytes_per_s"],
    )


def bench(cfg: dict, dtype: str, repeats: int, key: jax.Array, peaks: dict) -> dict:
    """Time one configuration at one conditioner precision."""
    k_model, k_pose, k_ctrl, k_sample = jax.random.split(key, 4)
    model, build_s = _build(cfg, dtype, k_model)
    b, t = cfg["batch"], cfg["window"]
    pose = jax.random.normal(k_pose, (b, t, POSE_DIM))
    control = jax.random.normal(k_ctrl, (b, t, CONTROL_DIM))
    graph, params, rest = nnx.split(model, nnx.Param, ...)
    n_params = sum(int(x.size) for x in jax.tree.leaves(params))
    opt = optax.chain(optax.clip(5.0), optax.clip_by_global_norm(100.0), optax.adam(1e-3))
    opt_state = opt.init(params)
    train_step = _train_step(graph, rest, opt, t)

    res: dict = {"dtype": dtype, "params": n_params, "build_s": build_s}
    peak = peaks["gemm"][dtype]["flops_per_s"]
    res["weight_bytes"] = roofline.tree_bytes(params)
    res["weight_read"] = roofline.weight_read(res["weight_bytes"], peaks["memory_repeats"])
    trained = _time_training(res, train_step, (params, opt_state, pose, control), peak, repeats)
    print(
        f"{dtype:>9} training step {res['train_step_s']:.4f} s (compile "
        f"{res['train_compile_s']:.1f} s); timing the sampler next",
        file=sys.stderr,
        flush=True,
    )
    model = nnx.merge(graph, trained, rest)
    _time_sampling(res, model, control, k_sample, repeats, peak)
    res["device_peak_bytes"] = roofline.device_peak_bytes()
    res["peak_rss_mb_so_far"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return res


FIGURES = [  # (result key, its floor's key)
    ("train_step_s", "train_step_floor"),
    ("sample_s", "sample_floor"),
]


def summary(results: list[dict]) -> list[dict]:
    """One row per (dtype, figure): the measured seconds, their floor and the multiple."""
    return [
        {
            "dtype": res["dtype"],
            "figure": name,
            "value": res[name],
            "unit": "s",
            "floor": res[floor_key]["floor_s"],
            "bound": res[floor_key]["bound"],
            "multiple_of_floor": res[floor_key]["multiple_of_floor"],
        }
        for res in results
        for name, floor_key in FIGURES
    ]


def summary_text(out: dict) -> str:
    """The summary as lines for people (stderr; stdout stays one JSON document)."""
    lines = roofline.machine_lines(out["machine"], out["peaks"])
    for row in out["summary"]:
        lines.append(
            f"{row['dtype']:>9} {row['figure']:<13} {row['value']:9.4f} s  "
            f"floor {row['floor']:9.4f} s ({row['bound']})  x{row['multiple_of_floor']:.2f}"
        )
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="small configuration")
    ap.add_argument("--dtypes", default="float32,bfloat16")
    ap.add_argument("--repeats", type=int, default=None, help="timed training steps")
    args = ap.parse_args(argv)
    dtypes = [d.strip() for d in args.dtypes.split(",")]
    if not dtypes or any(d not in ("float32", "bfloat16") for d in dtypes):
        ap.error(f"--dtypes takes float32 and/or bfloat16, comma-separated; got {args.dtypes!r}")
    if args.repeats is not None and args.repeats < 1:
        ap.error(f"--repeats must be >= 1 (timed steps), got {args.repeats}")
    cfg = QUICK if args.quick else PAPER
    repeats = (5 if args.quick else 2) if args.repeats is None else args.repeats
    out = {
        "benchmark": "glow_fixed_speed",
        "config": {**cfg, "pose_dim": POSE_DIM, "control_dim": CONTROL_DIM},
        "quick": args.quick,
        "units": {
            "train_step_s": "seconds per Adam step on one batch of windows (median)",
            "sample_s": "seconds to sample the whole batch of windows (median)",
            "sample_ms_per_frame": "sample_s / (batch * window) in ms",
            "compile_s": "XLA compile seconds (lower + compile)",
            "bytes": "bytes",
        },
        "machine": roofline.machine(),
        "results": [],
    }
    out["peaks"] = roofline.measure_peaks(args.quick)
    print(json.dumps({"peaks": out["peaks"]}), file=sys.stderr, flush=True)
    key = jax.random.key(0)
    for dtype in dtypes:
        out["results"].append(bench(cfg, dtype, repeats, key, out["peaks"]))
        print(json.dumps(out["results"][-1]), file=sys.stderr, flush=True)
    out["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    out["machine"]["load_average_after"] = list(os.getloadavg())
    out["summary"] = summary(out["results"])
    print(summary_text(out), file=sys.stderr)
    print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
