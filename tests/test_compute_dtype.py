"""The flows' ``compute_dtype="auto"``: bfloat16 on a recent NVIDIA GPU, float32 elsewhere,
resolved before a run saves its config and before the bench looks for runs to reuse."""

import importlib
import json
import types

import jax
import pytest

from motionflows import bench, training
from motionflows import config as cfg

FLOWS = ("moglow", "glow_fixed")


def _gpu(monkeypatch, capability):
    device = types.SimpleNamespace(device_kind="fake GPU")
    if capability is not None:
        device.compute_capability = capability
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    monkeypatch.setattr(jax, "devices", lambda *a: [device])


@pytest.mark.parametrize(
    "capability, expected",
    [("9.0", "bfloat16"), ("8.0", "bfloat16"), ("7.5", "float32"), (None, "float32")],
)
def test_auto_is_bfloat16_only_on_gpus_with_bfloat16_tensor_cores(
    monkeypatch, capability, expected
):
    _gpu(monkeypatch, capability)
    assert cfg.auto_compute_dtype() == expected
    assert cfg.matmul_dtype("auto") == (None if expected == "float32" else "bfloat16")


def test_auto_is_float32_on_the_cpu_and_explicit_choices_stay():
    assert jax.default_backend() == "cpu"
    assert cfg.auto_compute_dtype() == "float32" and cfg.matmul_dtype("auto") is None
    assert cfg.matmul_dtype("float32") is None and cfg.matmul_dtype("bfloat16") == "bfloat16"
    for name in FLOWS:
        module = importlib.import_module(f"experiments.{name}")
        assert module.PRESETS["paper"].compute_dtype == "auto"
        assert module.PRESETS["cpu"].compute_dtype == "float32"  # a CPU budget, as shipped
        assert cfg.resolve_compute_dtype(module.PRESETS["paper"]).compute_dtype == "float32"
        chosen = cfg.apply_overrides(module.PRESETS["quick"], ["compute_dtype=bfloat16"])
        assert cfg.resolve_compute_dtype(chosen) is chosen
        with pytest.raises(ValueError, match="compute_dtype must be one of"):
            cfg.apply_overrides(module.PRESETS["quick"], ["compute_dtype=float16"])
    vae = importlib.import_module("experiments.vae_lstm").PRESETS["quick"]  # no such field
    assert cfg.resolve_compute_dtype(vae) is vae


@pytest.mark.parametrize("machine", ["float32", "bfloat16"])
def test_a_run_saves_the_precision_it_trains_in(tmp_path, monkeypatch, machine):
    """config.json names the resolved dtype (so the run reloads and resumes in it anywhere)
    and the model is built with it."""
    moglow = importlib.import_module("experiments.moglow")
    monkeypatch.setattr(cfg, "auto_compute_dtype", lambda: machine)
    built = []

    class Built(Exception):
        pass

    def build(config, *, key):
        built.append(config.compute_dtype)
        raise Built

    monkeypatch.setattr(moglow, "build", build)
    config = moglow.PRESETS["smoke"]
    assert config.compute_dtype == "auto"
    with pytest.raises(Built):
        training.train(moglow, config, run_dir=tmp_path / "run", progress=False)
    saved = json.loads((tmp_path / "run" / "config.json").read_text())
    assert saved["config"]["compute_dtype"] == machine and built == [machine]


def test_the_bench_looks_for_runs_of_the_resolved_precision():
    """Runs trained before "auto" existed saved "float32": the bench's CPU config must equal
    theirs, or it would retrain every shipped and earlier run."""
    data = bench.parse_data_spec("synthetic", "smoke")
    for name in FLOWS:
        config, _ = bench.bench_config(name, "smoke", data)
        assert config.compute_dtype == "float32"


def test_float32_by_name_is_plain_float32_in_both_flows():
    """MoGlow kept the string "float32" (the Glow maps it to None): its products then took
    the low-precision custom-VJP path (no forward mode) and ``streaming_model`` treated it
    as a low-precision model. Both flows now store None for float32 and refuse other names."""
    from flax import nnx

    from motionflows.inference import streaming_model
    from motionflows.models.glow import Glow
    from motionflows.models.moglow import MoGlow

    moglow = MoGlow(6, 2, tau=2, K=1, hidden=4, compute_dtype="float32", rngs=nnx.Rngs(0))
    glow = Glow(6, levels=1, K=1, hidden=4, control_dim=2, compute_dtype="float32",
                rngs=nnx.Rngs(0))  # fmt: skip
    assert moglow.compute_dtype is None and glow.compute_dtype is None
    assert streaming_model(moglow) is not moglow  # the float32 inference copy
    x, c = jax.numpy.ones((1, 4, 6)), jax.numpy.ones((1, 4, 2))
    jax.jvp(lambda x: moglow.log_prob(x, c), (x,), (x,))  # forward mode works
    with pytest.raises(ValueError, match="MoGlow: compute_dtype must be"):
        MoGlow(6, 2, tau=2, K=1, hidden=4, compute_dtype="float64", rngs=nnx.Rngs(0))
    with pytest.raises(ValueError, match="Glow: compute_dtype must be"):
        Glow(6, levels=1, K=1, hidden=4, compute_dtype="float64", rngs=nnx.Rngs(0))
