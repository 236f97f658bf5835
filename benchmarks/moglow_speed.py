"""MoGlow speed: training step, sampling ms/frame, compile times, memory; prints JSON.

Paper configuration by default (63 + 3 dims, tau 10, K 16, 2 x 512 LSTM, batch 100 windows of
80 frames = 70 targets), float32 and bfloat16 conditioner matmuls. ``--quick`` runs a small
configuration (for CI / a smoke test). Reference: the official PyTorch code (torch 2.13, 2
threads) on this project's 2-core AMD EPYC, measured for issue 16: 18.4 s per float32 training
step, 71.5 ms/frame at batch 1, 128 ms per frame-step at batch 64, 7.2 GiB peak memory.

Sampling and streaming are timed as the library does them: ``sample`` from
:func:`motionflows.inference.inference_copy` of the trained model (each flow step's weights
in their own buffers; the same poses), ``stream_step`` on
:func:`motionflows.inference.streaming_model` (that copy for float32, the model itself for
bfloat16 matmuls) through :func:`motionflows.inference.stream_stepper` (the module split
once; before 2026-12-04 each call passed the module itself). ``stacked_sample_*`` times
``sample`` on the model itself (the training layout, K steps stacked; what every sampler
used before 2026-12-03).
The training step is data-parallel over every device, as ``motionflows train`` runs it
(:mod:`motionflows.sharding`: parameters replicated, the batch split): one device unless
there are several GPUs or simulated CPU devices, e.g.
``XLA_FLAGS=--xla_force_host_platform_device_count=2`` (docs/readme/speed.md: on 2 CPU
cores this runs the time loops of the two halves of the batch side by side). Its floor
counts every accelerator's GEMM peak (N GPUs: N times the one measured, since 2026-12-07;
simulated CPU devices share the cores the peak used: ``training_peak``). The step
donates the parameters and the optimiser state, as the trainer's step does (since
2026-12-05; before, the benchmark kept both, which raised its peak memory:
docs/readme/speed.md).
The bfloat16 run trains and samples with bfloat16 conditioner matmuls (float32 weights); it
also times ``sample`` from ``inference_copy(model, "bfloat16")`` (the weights *stored* in
bfloat16, half the bytes a batch-1 frame reads): ``inference_copy_sample_*``.

Every time is also given as a multiple of its floor on this machine, measured in the same run
(:mod:`motionflows.roofline`): the matmul FLOPs of the step (counted from its jaxpr) over the
measured GEMM peak of its precision, or for sampling, when larger, the bytes of the weights
read per frame over the measured memory read bandwidth. The load average is printed at the start
and at the end: on a shared machine a load above the core count makes every time slower.

    python benchmarks/moglow_speed.py [--quick] [--dtypes float32,bfloat16] [--repeats N]
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
import numpy as np
import optax
from flax import nnx

from motionflows import roofline
from motionflows.bijectors import initialize_from_data
from motionflows.data.names import CONTROL_DIM, POSE_DIM
from motionflows.distributed import configure_cpu_threads
from motionflows.errors import RunError
from motionflows.inference import inference_copy, stream_stepper, streaming_model
from motionflows.models.moglow import MoGlow
from motionflows.sharding import batch_sharding, check_batch_size, data_mesh, replicate

PAPER = {
    "K": 16,
    "hidden": 512,
    "layers": 2,
    "tau": 10,
    "batch": 100,
    "window": 80,
    "sample_frames": 60,
}
QUICK = {  # a smoke test: seconds, not a speed figure
    "K": 2,
    "hidden": 32,
    "layers": 1,
    "tau": 10,
    "batch": 8,
    "window": 20,
    "sample_frames": 8,
}
REFERENCE = {  # official code, same machine (issue 16): first of its two passes
    "train_step_s": 18.4,
    "first_step_s": 41.0,
    "sample_ms_per_frame_b1": 71.5,
    "sample_ms_per_frame_b64": 128.0,
    "peak_rss_gib": 7.2,
}
TARGETS = {  # issue 16
    "train_step_s_float32": 18.4,
    "train_step_s_bfloat16": 9.0,
    "first_step_over_steady": 1.5,
    "sample_ms_per_frame_b1": 8.0,
    "sample_ms_per_frame_b64": 35.0,
    "peak_rss_gib": 7.2,
}


def _time_sample(model, control, key, repeats: int) -> tuple[float, float]:
    """(median ms per frame, compile seconds) of one jitted ``model.sample(key, control)``
    over control (B, T, C), after one untimed call."""
    sampler = jax.jit(lambda m, c, k: m.sample(k, c))
    fn, compile_s = roofline.compile_timed(sampler, model, control, key)
    fn(model, control, key).block_until_ready()
    times = roofline.timings(lambda: fn(model, control, key), repeats)
    return 1e3 * statistics.median(times) / control.shape[1], compile_s


def _model_and_data(cfg: dict, compute_dtype, k_model, k_data):
    """The MoGlow of ``cfg``, random pose/control windows, ActNorm initialised from them."""
    model = MoGlow(
        POSE_DIM,
        CONTROL_DIM,
        tau=cfg["tau"],
        K=cfg["K"],
        hidden=cfg["hidden"],
        num_layers=cfg["layers"],
        dropout=0.95,
        compute_dtype=compute_dtype,
        rngs=k_model,
    )
    b, t = cfg["batch"], cfg["window"]
    kp, kc = jax.random.split(k_data)
    pose = jax.random.normal(kp, (b, t, POSE_DIM))
    control = jax.random.normal(kc, (b, t, CONTROL_DIM))
    model = initialize_from_data(model, pose[:8], context=control[:8])
    return model, pose, control


def _train_step(graph, rest, opt, n_targets: int):
    """One Adam step on the mean NLL per target frame: (params, opt state, loss)."""

    def train_step(p, s, pose, control, key):
        def loss(p):
            m = nnx.merge(graph, p, rest)
            return -jnp.mean(m.log_prob(pose, control, key=key)) / n_targets

        value, grads = jax.value_and_grad(loss)(p)
        updates, s = opt.update(grads, s, p)
        return optax.apply_updates(p, updates), s, value

    return train_step


def _time_training(res: dict, train_step, args: tuple, peak: float, repeats: int, warmup: int):
    """Add the training step's FLOPs, compile time, memory, step times and floor to ``res``."""
    res["train_flops"] = roofline.matmul_flops(train_step, *args)
    # params and optimiser state donated, as the trainer's step donates them
    # (motionflows.optim.make_train_step): the update may then overwrite them in place
    step = jax.jit(train_step, donate_argnums=(0, 1))
    compiled, res["train_compile_s"] = roofline.compile_timed(step, *args)
    mem = roofline.compiled_memory(compiled)
    for name in ("temp_bytes", "argument_bytes"):
        if name in mem:
            res[f"train_{name}"] = mem[name]
    state = {"p": args[0], "s": args[1], "value": None}

    def run_train():
        state["p"], state["s"], state["value"] = compiled(state["p"], state["s"], *args[2:])
        return state["value"]

    first = roofline.timings(run_train, warmup)
    res["first_step_s"] = first[0] if first else None
    times = roofline.timings(run_train, repeats)
    res["train_step_s"] = statistics.median(times)
    res["train_step_s_all"] = times
    res["train_step_floor"] = roofline.floor_entry(
        res["train_step_s"], flops=res["train_flops"], peak_flops_per_s=peak
    )
    res["train_loss"] = float(state["value"])
    if first:
        res["first_step_over_steady"] = first[0] / res["train_step_s"]
    res["peak_rss_mb_after_training"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    # returning frees the training buffers before sampling


def _time_other_samplers(res: dict, model, compute_dtype, n: int, key, repeats: int) -> None:
    """Add the sampling ms/frame of the model itself (stacked steps) and, with
    ``compute_dtype``, of a copy with the weights *stored* in it."""
    samplers = {"stacked_sample": model}
    if compute_dtype is not None:
        low = inference_copy(model, compute_dtype)
        res["inference_copy_weight_bytes"] = roofline.tree_bytes(nnx.state(low, nnx.Param))
        samplers["inference_copy_sample"] = low
    for name, sampler in samplers.items():
        for batch in (1, 64):
            ctrl = jax.random.normal(key, (batch, n, CONTROL_DIM))
            ms, _ = _time_sample(sampler, ctrl, key, max(repeats, 3))
            res[f"{name}_ms_per_frame_b{batch}"] = ms


def _time_sampling(res: dict, model, ctrl, key, repeats: int, bounds: dict) -> dict:
    """Add ``sample``'s compile time, ms/frame and floor to ``res``; return the floor's terms."""
    batch, n = ctrl.shape[:2]
    ms, compile_s = _time_sample(model, ctrl, key, max(repeats, 3))
    res[f"sample_compile_s_b{batch}"] = compile_s
    res[f"sample_ms_per_frame_b{batch}"] = ms
    # floor per frame: the frame's matmuls at the peak, or all weights read once
    frame_flops = roofline.matmul_flops(lambda m, c, k: m.sample(k, c), model, ctrl, key)
    floor = dict(flops=frame_flops / n, **bounds)
    res[f"sample_floor_b{batch}"] = roofline.floor_entry(
        res[f"sample_ms_per_frame_b{batch}"] / 1e3, **floor
    )
    return floor


def _time_streaming(res: dict, model, ctrl, key, floor: dict) -> None:
    """Add the latency of one jitted ``stream_step`` per frame from the host (game loop)."""
    batch, n = ctrl.shape[:2]
    step = stream_stepper(model)  # as motionflows play calls it
    stream = model.init_stream(batch)
    frames = [ctrl[:, i] for i in range(n)]  # sliced before: the loop times the steps alone
    jax.block_until_ready(frames)
    x_t, stream = step(stream, frames[0], key)
    x_t.block_until_ready()
    lat = []
    for c_t in frames[1:]:
        t0 = time.perf_counter()
        x_t, stream = step(stream, c_t, key)
        x_t.block_until_ready()
        lat.append(time.perf_counter() - t0)
    res[f"stream_step_ms_b{batch}_median"] = 1e3 * statistics.median(lat)
    res[f"stream_step_ms_b{batch}_p95"] = 1e3 * float(np.percentile(lat, 95))
    res[f"stream_step_floor_b{batch}"] = roofline.floor_entry(
        res[f"stream_step_ms_b{batch}_median"] / 1e3, **floor
    )
    stream_floor = res[f"stream_step_floor_b{batch}"]
    stream_floor["multiple_of_floor_p95"] = (
        res[f"stream_step_ms_b{batch}_p95"] / 1e3 / stream_floor["floor_s"]
    )


def training_peak(peak: float, devices: int, backend: str) -> float:
    """The GEMM peak of the data-parallel training step: the measured peak is one device's,
    so separate accelerators add theirs (``devices`` times it); simulated CPU devices share
    the cores that the peak already used (the peak itself)."""
    return peak * devices if backend != "cpu" else peak


def bench(cfg: dict, dtype: str, repeats: int, key, peaks: dict, warmup: int = 1) -> dict:
    """Time training, sampling and streaming at one conditioner precision."""
    cd = None if dtype == "float32" else dtype
    k_model, k_data, k_drop, k_sample = jax.random.split(key, 4)
    model, pose, control = _model_and_data(cfg, cd, k_model, k_data)
    graph, params, rest = nnx.split(model, nnx.Param, ...)
    opt = optax.chain(optax.clip(5.0), optax.clip_by_global_norm(100.0), optax.adam(1e-3))
    opt_state = opt.init(params)
    train_step = _train_step(graph, rest, opt, cfg["window"] - cfg["tau"])

    peak = peaks["gemm"][dtype]["flops_per_s"]
    weight_bytes = roofline.tree_bytes(params)
    read = roofline.weight_read(weight_bytes, peaks["memory_repeats"])
    res: dict = {"dtype": dtype, "weight_bytes": weight_bytes, "weight_read": read}
    mesh = data_mesh()  # as the trainer: data-parallel over every device (usually one)
    check_batch_size(cfg["batch"], mesh)
    res["train_devices"] = int(mesh.devices.size)
    train_peak = training_peak(peak, res["train_devices"], jax.default_backend())
    res["train_peak_flops_per_s"] = train_peak
    shard = batch_sharding(mesh)
    # a copy of the parameters for the donated step: the model keeps its own for sampling
    trained = jax.tree.map(jnp.copy, params)
    args = (*replicate((trained, opt_state), mesh), jax.device_put(pose, shard),
            jax.device_put(control, shard), k_drop)  # fmt: skip
    _time_training(res, train_step, args, train_peak, repeats, warmup)
    print(
        f"{dtype:>9} training step {res['train_step_s']:.4f} s (compile "
        f"{res['train_compile_s']:.1f} s); timing the samplers next",
        file=sys.stderr,
        flush=True,
    )

    n = cfg["sample_frames"]
    _time_other_samplers(res, model, cd, n, k_sample, repeats)
    sampler, streamer = inference_copy(model), streaming_model(model)  # as the library does

    def bounds(module) -> dict:  # a bfloat16 model's copy holds bfloat16 weights: half the bytes
        return dict(
            peak_flops_per_s=peak,
            bytes_read=roofline.tree_bytes(nnx.state(module, nnx.Param)),
            bandwidth_bytes_per_s=read["bytes_per_s"],
        )

    sampler_bounds, streamer_bounds = bounds(sampler), bounds(streamer)
    for batch in (1, 64):
        ctrl = jax.random.normal(k_sample, (batch, n, CONTROL_DIM))
        floor = _time_sampling(res, sampler, ctrl, k_sample, repeats, sampler_bounds)
        _time_streaming(res, streamer, ctrl, k_sample, dict(floor, **streamer_bounds))
    res["peak_rss_mb_so_far"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    res["device_peak_bytes"] = roofline.device_peak_bytes()  # GPU/TPU; None on CPU (see peak RSS)
    return res


FIGURES = [  # (result key, its floor's key, unit scale from seconds, unit)
    ("train_step_s", "train_step_floor", 1.0, "s"),
    ("sample_ms_per_frame_b1", "sample_floor_b1", 1e3, "ms"),
    ("sample_ms_per_frame_b64", "sample_floor_b64", 1e3, "ms"),
    ("stream_step_ms_b1_median", "stream_step_floor_b1", 1e3, "ms"),
    ("stream_step_ms_b64_median", "stream_step_floor_b64", 1e3, "ms"),
]


def summary(results: list[dict]) -> list[dict]:
    """One row per (dtype, figure): the measured value, its floor and the multiple."""
    rows = []
    for res in results:
        for name, floor_key, scale, unit in FIGURES:
            floor = res[floor_key]
            rows.append(
                {
                    "dtype": res["dtype"],
                    "figure": name,
                    "value": res[name],
                    "unit": unit,
                    "floor": floor["floor_s"] * scale,
                    "bound": floor["bound"],
                    "multiple_of_floor": floor["multiple_of_floor"],
                }
            )
    return rows


def summary_text(out: dict) -> str:
    """The summary as lines for people (stderr; stdout stays one JSON document)."""
    lines = roofline.machine_lines(out["machine"], out["peaks"])
    for row in out["summary"]:
        lines.append(
            f"{row['dtype']:>9} {row['figure']:<27} {row['value']:9.3f} {row['unit']:<2}  "
            f"floor {row['floor']:9.3f} ({row['bound']})  x{row['multiple_of_floor']:.2f}"
        )
    for res in out["results"]:
        if res.get("first_step_s") is not None:
            lines.append(
                f"{res['dtype']:>9} first step after compile {res['first_step_s']:.2f} s = "
                f"x{res['first_step_over_steady']:.2f} a steady step; stream_step p95 b1 "
                f"{res['stream_step_ms_b1_p95']:.1f} ms, b64 {res['stream_step_ms_b64_p95']:.1f} ms"
            )
        lines.append(
            f"{res['dtype']:>9} sample from the stacked model (training layout): b1 "
            f"{res['stacked_sample_ms_per_frame_b1']:.2f} ms/frame, b64 "
            f"{res['stacked_sample_ms_per_frame_b64']:.2f} ms/frame-step"
        )
        if "inference_copy_sample_ms_per_frame_b1" in res:
            lines.append(
                f"{res['dtype']:>9} sample from inference_copy (bfloat16 weights): b1 "
                f"{res['inference_copy_sample_ms_per_frame_b1']:.2f} ms/frame, b64 "
                f"{res['inference_copy_sample_ms_per_frame_b64']:.2f} ms/frame-step"
            )
        if res["train_devices"] > 1:
            lines.append(
                f"{res['dtype']:>9} training data-parallel over {res['train_devices']} devices"
            )
        lines.append(
            f"{res['dtype']:>9} peak RSS after its training "
            f"{res['peak_rss_mb_after_training'] / 1024:.2f} GiB (process maximum so far)"
        )
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="small configuration")
    ap.add_argument("--dtypes", default="float32,bfloat16")
    ap.add_argument("--repeats", type=int, default=None, help="timed training steps")
    ap.add_argument("--warmup", type=int, default=1, help="untimed training steps first")
    args = ap.parse_args(argv)
    dtypes = [d.strip() for d in args.dtypes.split(",")]
    if not dtypes or any(d not in ("float32", "bfloat16") for d in dtypes):
        ap.error(f"--dtypes takes float32 and/or bfloat16, comma-separated; got {args.dtypes!r}")
    if args.repeats is not None and args.repeats < 1:
        ap.error(f"--repeats must be >= 1 (timed steps), got {args.repeats}")
    if args.warmup < 0:
        ap.error(f"--warmup must be >= 0, got {args.warmup}")
    cfg = QUICK if args.quick else PAPER
    repeats = (3 if args.quick else 2) if args.repeats is None else args.repeats
    try:  # before the first JAX computation: simulated CPU devices need 2 threads each
        configure_cpu_threads()
    except RunError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    mesh = data_mesh()
    try:  # before the peaks: bench() would refuse it only after them
        check_batch_size(cfg["batch"], mesh)
    except ValueError:  # its fix (--set train.batch_size) is the trainer's, not this script's
        print(
            f"error: the training step's batch of {cfg['batch']} windows does not split over "
            f"the {mesh.devices.size} devices JAX sees; run on a device count that divides "
            f"{cfg['batch']} (XLA_FLAGS=--xla_force_host_platform_device_count=N on the CPU)",
            file=sys.stderr,
        )
        return 2
    out = {
        "benchmark": "moglow_speed",
        "config": {
            **cfg,
            "pose_dim": POSE_DIM,
            "control_dim": CONTROL_DIM,
            "targets_per_window": cfg["window"] - cfg["tau"],
        },
        "quick": args.quick,
        "machine": roofline.machine(),
        "reference_official_pytorch": REFERENCE,
        "targets": TARGETS,
        "results": [],
    }
    out["peaks"] = roofline.measure_peaks(args.quick)
    print(json.dumps({"peaks": out["peaks"]}), file=sys.stderr, flush=True)
    key = jax.random.key(0)
    for dtype in dtypes:
        out["results"].append(bench(cfg, dtype, repeats, key, out["peaks"], args.warmup))
        print(json.dumps(out["results"][-1]), file=sys.stderr, flush=True)
    out["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    out["machine"]["load_average_after"] = list(os.getloadavg())
    out["summary"] = summary(out["results"])
    print(summary_text(out), file=sys.stderr)
    print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
