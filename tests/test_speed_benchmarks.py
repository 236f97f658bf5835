"""The speed benchmarks' --quick modes run and state every time against a measured floor.

Smoke tests only: no timing is asserted (CI machines differ and are shared). What is checked
is that each figure comes with its floor, the multiple, the peaks measured in the same run,
the load average at start and end, and the machine's CPU and ISA; and that the FLOP counter
behind the floors counts a scanned matmul once per iteration (XLA's cost analysis does not).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import pytest

from motionflows import roofline

ROOT = Path(__file__).resolve().parents[1]


def _run_quick(script: str, dtype: str, **env) -> dict:
    proc = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / script), "--quick", "--dtypes", dtype],
        capture_output=True,
        text=True,
        timeout=600,
        # the same backend as the suite (CPU, or a GPU if present); standard dtype promotion,
        # as the scripts call optax's Adam directly (its bias correction is float ** int32)
        env={**os.environ, "JAX_NUMPY_DTYPE_PROMOTION": "standard", **env},
        cwd=ROOT,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "multiple" not in proc.stdout.splitlines()[0]  # stdout is one JSON document
    assert "load average at start" in proc.stderr  # the people's summary goes to stderr
    return json.loads(proc.stdout)


def _check_common(out: dict, figures: list[str]) -> None:
    machine = out["machine"]
    assert machine["cpu"] and isinstance(machine["isa"], list)
    assert len(machine["load_average_1_5_15"]) == 3
    assert len(machine["load_average_after"]) == 3
    for dtype in ("float32", "bfloat16"):
        assert out["peaks"]["gemm"][dtype]["flops_per_s"] > 0
    assert out["peaks"]["memory"]["bytes_per_s"] > 0
    rows = {(r["dtype"], r["figure"]): r for r in out["summary"]}
    for res in out["results"]:
        assert res["train_flops"] > 0
        for name in figures:
            row = rows[(res["dtype"], name)]
            assert row["floor"] > 0 and row["bound"] in ("compute", "memory")
            assert row["multiple_of_floor"] == pytest.approx(row["value"] / row["floor"], rel=1e-6)


def test_moglow_speed_quick_reports_floors():
    out = _run_quick("moglow_speed.py", "bfloat16")
    assert [r["dtype"] for r in out["results"]] == ["bfloat16"]
    _check_common(
        out,
        [
            "train_step_s",
            "sample_ms_per_frame_b1",
            "sample_ms_per_frame_b64",
            "stream_step_ms_b1_median",
            "stream_step_ms_b64_median",
        ],
    )
    res = out["results"][0]
    # the floor of a batch-64 frame can't be below the batch-1 frame's
    assert res["sample_floor_b64"]["floor_s"] >= res["sample_floor_b1"]["floor_s"]
    assert res["stream_step_floor_b1"]["multiple_of_floor_p95"] > 0
    # the training layout's sampler and the bfloat16-stored copy are timed beside it
    for name in ("stacked_sample", "inference_copy_sample"):
        assert res[f"{name}_ms_per_frame_b1"] > 0 and res[f"{name}_ms_per_frame_b64"] > 0
    assert res["train_devices"] == len(jax.devices())  # data-parallel as the trainer is


@pytest.mark.skipif(jax.default_backend() != "cpu", reason="simulated devices are CPU devices")
def test_moglow_speed_trains_data_parallel_over_simulated_cpu_devices():
    """As the trainer: the batch split over every device (here 2 simulated CPU devices, each
    given its XLA threads first), the step timed, the devices named in the summary."""
    flags = " ".join([os.environ.get("XLA_FLAGS", ""), "--xla_force_host_platform_device_count=2"])
    env = {"XLA_FLAGS": flags.strip(), "PJRT_NPROC": "", "NPROC": ""}
    out = _run_quick("moglow_speed.py", "float32", **env)
    res = out["results"][0]
    assert res["train_devices"] == 2 and res["train_step_s"] > 0
    assert "2 x cpu" in out["machine"]["devices"]
    # the 2 simulated devices share the cores the measured peak used: the floor is its own
    assert res["train_peak_flops_per_s"] == out["peaks"]["gemm"]["float32"]["flops_per_s"]


def test_moglow_speed_training_floor_counts_every_accelerator(benchmark_script):
    # the measured GEMM peak is one device's: 4 GPUs train data-parallel at 4 times it (the
    # floor of a multi-GPU step was one GPU's, its multiple 4x too high)
    training_peak = benchmark_script("moglow_speed").training_peak
    assert training_peak(100.0, 4, "gpu") == 400.0
    assert training_peak(100.0, 1, "gpu") == 100.0
    assert training_peak(100.0, 4, "cpu") == 100.0  # simulated devices share the cores


def test_moglow_speed_step_donates_its_state_as_the_trainer_does(monkeypatch):
    """The timed step donates the parameters and Adam state (its peak memory is then the
    trainer's), and the model it samples from afterwards keeps its own parameters."""
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    import moglow_speed

    seen = {}
    timed = moglow_speed._time_training

    def spy(res, train_step, args, *rest):
        seen["state"] = args[:2]
        return timed(res, train_step, args, *rest)

    monkeypatch.setattr(moglow_speed, "_time_training", spy)
    with jax.numpy_dtype_promotion("standard"):
        peaks = roofline.measure_peaks(True)
        res = moglow_speed.bench(moglow_speed.QUICK, "float32", 1, jax.random.key(0), peaks)
    assert all(leaf.is_deleted() for leaf in jax.tree.leaves(seen["state"]))
    assert res["sample_ms_per_frame_b1"] > 0 and res["stream_step_ms_b1_median"] > 0


def test_glow_fixed_speed_quick_reports_floors():
    out = _run_quick("glow_fixed_speed.py", "float32")
    _check_common(out, ["train_step_s", "sample_s"])


def test_matmul_flops_counts_every_scan_iteration_and_the_backward_pass():
    x, w = jnp.ones((8, 16)), jnp.ones((16, 16))

    def f(x, w):
        y, _ = jax.lax.scan(lambda c, _: (jnp.tanh(c @ w), None), x, None, length=5)
        return y.sum()

    forward = 5 * 2 * 8 * 16 * 16
    assert roofline.matmul_flops(f, x, w) == forward
    # reverse mode: the forward products, then dx and dw per iteration
    assert roofline.matmul_flops(jax.grad(f, argnums=1), x, w) == 3 * forward


def test_matmul_flops_skips_the_products_whose_results_nothing_uses():
    # precision.matmul's hand-written VJP also computes dx = g @ w^T; for data x nothing uses
    # it and XLA drops it, so the floor must not count it (the bfloat16 MoGlow step's did)
    from motionflows.nets.precision import matmul

    x, w = jnp.ones((8, 16)), jnp.ones((16, 32))
    forward = 2 * 8 * 16 * 32

    def loss(w, x):
        return jnp.tanh(matmul(x, w, "bfloat16")).sum()

    assert roofline.matmul_flops(loss, w, x) == forward
    assert roofline.matmul_flops(jax.grad(loss), w, x) == 2 * forward  # forward + dw
    assert roofline.matmul_flops(jax.grad(loss, argnums=(0, 1)), w, x) == 3 * forward


def test_floor_entry_takes_the_larger_bound():
    compute = roofline.floor_entry(
        2.0, flops=10.0, peak_flops_per_s=10.0, bytes_read=1.0, bandwidth_bytes_per_s=10.0
    )
    assert compute == {"floor_s": 1.0, "multiple_of_floor": 2.0, "bound": "compute"}
    memory = roofline.floor_entry(
        2.0, flops=1.0, peak_flops_per_s=10.0, bytes_read=40.0, bandwidth_bytes_per_s=10.0
    )
    assert memory["bound"] == "memory" and memory["multiple_of_floor"] == 0.5


@pytest.mark.parametrize("nbytes", [295_436_224, 1 << 20, 1000])
def test_memory_bandwidth_takes_any_size(nbytes):
    # the paper MoGlow's weights (295 MB) are not a multiple of 2048 floats: this crashed
    read = roofline.memory_bandwidth(nbytes, repeats=1)
    assert 0 < read["bytes"] <= max(nbytes, 4 * 256)
    assert read["bytes"] >= min(nbytes, 4 * 256) - 4 * 2048
    assert read["bytes_per_s"] > 0


def test_gemv_layout_quick_reports_every_form_against_the_reference():
    proc = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "gemv_layout.py"), "--quick", "--repeats", "2"],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=ROOT,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads(proc.stdout)
    assert out["machine"]["cpu"] and len(out["machine"]["load_average_after"]) == 3
    forms = {r["form"]: r for r in out["rows"]}
    assert len(forms) == 8
    for row in forms.values():
        assert row["best_ms"] > 0 and row["read_gb_per_s"] > 0
    # every form computes the same product: float32 to rounding, bfloat16 to its precision
    for name, row in forms.items():
        assert row["max_abs_difference"] < (1e-4 if name.startswith("float32") else 5e-2), name


def test_gpu_speed_script_parses_and_asks_for_its_output_folder():
    """benchmarks/gpu_speed.sh runs only where a GPU is lent: here it must at least be valid
    bash and stop with its usage line when OUTDIR is missing (before any work)."""
    script = ROOT / "benchmarks" / "gpu_speed.sh"
    assert subprocess.run(["bash", "-n", str(script)], capture_output=True).returncode == 0
    proc = subprocess.run(["bash", str(script)], capture_output=True, text=True, timeout=30)
    assert proc.returncode != 0 and "usage: benchmarks/gpu_speed.sh OUTDIR" in proc.stderr


def test_moglow_speed_refuses_a_device_count_that_does_not_divide_its_batch():
    # 3 simulated devices and the quick batch of 8: a raw ValueError after the peaks before
    proc = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "moglow_speed.py"), "--quick"],
        capture_output=True,
        text=True,
        timeout=120,
        env={
            **os.environ,
            "XLA_FLAGS": "--xla_force_host_platform_device_count=3",
            "JAX_PLATFORMS": "cpu",
        },
        cwd=ROOT,
    )
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "batch of 8 windows" in proc.stderr and "3 devices" in proc.stderr
    assert "Traceback" not in proc.stderr and proc.stdout == ""


@pytest.mark.parametrize(
    "script, argv",
    [
        ("moglow_speed", ["--repeats", "0"]),  # was the default, silently
        ("moglow_speed", ["--repeats", "-1"]),  # was a StatisticsError after the peaks
        ("moglow_speed", ["--warmup", "-1"]),
        ("glow_fixed_speed", ["--repeats", "0"]),
        ("gemv_layout", ["--repeats", "0"]),  # was min() of an empty sequence
    ],
)
def test_speed_scripts_refuse_a_count_that_times_nothing(benchmark_script, script, argv, capsys):
    with pytest.raises(SystemExit) as exit_info:
        benchmark_script(script).main(["--quick", *argv])
    assert exit_info.value.code == 2 and "must be >=" in capsys.readouterr().err
