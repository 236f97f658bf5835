"""A new model is one experiment module plus one entry point: no edit of the library.

The test installs a third-party distribution into a temporary folder on ``sys.path`` (a
``*.dist-info`` with an ``entry_points.txt`` registering ``toy`` in the group
``motionflows.experiments``, as ``pip install`` of a package declaring it would) and drives
it through ``motionflows train``, ``eval``, ``sample`` and ``bench --budget smoke``. The toy
model is a per-frame Gaussian whose mean is linear in the control,

    x_t ~ N(W c_t + b, diag(exp(2 s))),   log p(x_1:T | c_1:T) = sum_t log N(x_t; ...),

trained by gradient descent; it declares what the bench needs (``SCOPES``, ``CAUSAL``, a
``smoke`` preset) and nothing else.
"""

from __future__ import annotations

import json
import sys
import textwrap

import numpy as np
import pytest

from motionflows import bench, cli
from motionflows.runs import available_experiments

TOY = '''
"""Toy plug-in experiment: a per-frame Gaussian with a mean linear in the control."""

import dataclasses
import math

import jax
import jax.numpy as jnp
from flax import nnx

from motionflows.config import DataConfig, Scope, TrainConfig
from motionflows.data.names import CONTROL_DIM, POSE_DIM
from motionflows.models.validation import check_sample_args

NAME = "toy"
CAUSAL = True  # frames are independent given their own control


class ToyGaussian(nnx.Module):
    def __init__(self, *, key):
        self.weight = nnx.Param(0.01 * jax.random.normal(key, (CONTROL_DIM, POSE_DIM)))
        self.bias = nnx.Param(jnp.zeros((POSE_DIM,)))
        self.log_std = nnx.Param(jnp.zeros((POSE_DIM,)))

    def mean(self, control):
        return control @ self.weight[...] + self.bias[...]

    def log_prob(self, pose, control):
        z = (pose - self.mean(control)) * jnp.exp(-self.log_std[...])
        per_frame = -0.5 * jnp.sum(z**2, -1) - jnp.sum(self.log_std[...])
        return jnp.sum(per_frame - 0.5 * POSE_DIM * math.log(2 * math.pi), -1)


@dataclasses.dataclass(frozen=True)
class Config:
    data: DataConfig = DataConfig(window=16, hop=8, synthetic_clips=8, synthetic_seconds=4.0)
    train: TrainConfig = TrainConfig(
        steps=20, batch_size=8, lr=3e-2, eval_every=10, eval_batches=1, log_every=5,
        checkpoint_every=10, keep_checkpoints=1,
    )


PRESETS = {"quick": Config(), "smoke": Config()}
SCOPES = {"window": Scope("log p(x_1:T | c_1:T), all T frames")}


def build(config, *, key):
    return ToyGaussian(key=key)


def loss(model, batch, key):
    nll = -jnp.mean(model.log_prob(batch["pose"], batch["control"])) / batch["pose"].shape[1]
    return nll, {"nll_per_frame": nll}


def evaluate(model, batch, key):
    return {"window": model.log_prob(batch["pose"], batch["control"])}


def sample(model, key, control, *, temperature=1.0, seed_history=None):
    control, _ = check_sample_args(control, temperature, seed_history, "toy.sample")
    eps = jax.random.normal(key, control.shape[:-1] + (POSE_DIM,))
    return model.mean(control) + temperature * jnp.exp(model.log_std[...]) * eps
'''


@pytest.fixture
def toy_installed(tmp_path, monkeypatch):
    """``toy_motion_plugin`` installed in a temporary site folder, registered as ``toy``."""
    site = tmp_path / "site"
    (site / "toy_motion_plugin").mkdir(parents=True)
    (site / "toy_motion_plugin" / "__init__.py").write_text(TOY)
    info = site / "toy_motion_plugin-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: toy-motion-plugin\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(
        textwrap.dedent(
            """\
            [motionflows.experiments]
            toy = toy_motion_plugin
            """
        )
    )
    monkeypatch.syspath_prepend(str(site))
    yield tmp_path
    sys.modules.pop("toy_motion_plugin", None)


def _run(capsys, *argv):
    code = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    assert code == 0, err
    return out, err


def test_a_registered_experiment_runs_through_every_command(toy_installed, capsys):
    root = toy_installed
    assert "toy" in available_experiments() and "toy" in bench.ALL_MODELS
    runs = root / "runs"
    out, _ = _run(
        capsys, "train", "toy", "--preset", "smoke", "--runs-dir", runs, "--run-name", "r",
        "--no-progress",
    )  # fmt: skip
    run = runs / "toy" / "r"
    assert "window" in out and "nats/frame" in out  # the final test table
    assert json.loads((run / "config.json").read_text())["experiment"] == "toy"

    _run(capsys, "eval", run, "--split", "val")
    rows = json.loads((run / "eval_val.json").read_text())["rows"]
    assert [r["scope"] for r in rows] == ["window"]
    assert np.isfinite(rows[0]["nats_per_frame_metres"])

    _run(capsys, "sample", run, "--seconds", "2", "--num", "2", "--no-gif", "--out", root / "s")
    (npz,) = (root / "s").glob("*.npz")
    with np.load(npz) as saved:
        assert saved["pose"].shape == (2, 40, 63) and np.all(np.isfinite(saved["pose"]))
        assert str(saved["experiment"]) == "toy"

    out_dir = root / "bench"
    _run(
        capsys, "bench", "--budget", "smoke", "--models", "toy", "--runs-dir", runs,
        "--out", out_dir, "--no-gifs",
    )  # fmt: skip
    results = json.loads((out_dir / "results.json").read_text())
    entry = results["models"]["toy"]
    assert not any(k.endswith("error") for k in entry), entry
    assert entry["preset"] == "smoke" and entry["experiment"] == "toy"
    assert set(entry["likelihood"]) == {"window"}  # the scopes it declares
    assert entry["likelihood"]["window"]["frames"] == results["window"]
    # CAUSAL = True: NLL by frame position from prefix scores; they average to the window's
    pf = entry["per_frame_nll"]
    assert pf["available"] and pf["method"].startswith("prefix differences")
    window_nll = entry["likelihood"]["window"]["test"]["nats_per_frame_metres"]
    assert np.mean(pf["nats_per_frame_metres"]) == pytest.approx(window_nll, rel=1e-3)
    assert entry["motion"]["diverged"] == 0.0 and entry["speed"]["sample_frames_per_s_b1"] > 0
    assert "**toy**" in (out_dir / "BENCHMARK.md").read_text()
