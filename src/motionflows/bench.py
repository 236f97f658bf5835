"""``motionflows bench``: train (or reuse) every model on one split and compare them honestly.

One command writes ``DIR/BENCHMARK.md``, ``DIR/results.json`` and plots::

    motionflows bench --data synthetic --models glow_fixed,moglow,vae_lstm,gaussian,linear_ar \\
        --budget quick --out runs/bench

What is compared, and how (every number names its unit and scope):

* **Likelihood** on the test split. Every model sees the *same* data configuration (one
  :class:`~motionflows.config.DataConfig` is forced onto every experiment's config), hence
  identical test windows x_1:T (metres) and controls c_1:T. Each experiment's ``evaluate``
  returns per-window log-likelihoods in nats in standardised space for the scopes in its
  ``SCOPES`` (``"window"`` = log p(x_1:T | c_1:T) over all T frames; MoGlow's ``official``
  scope scores frames tau..T-1 given the true first tau; bounds such as the VAE-LSTM's ELBO and
  IWAE-K are marked ``bound``). ``motionflows.evaluation.likelihood`` converts them to

  - NLL in nats/frame in metres:  -(log p_std + F * log_det_per_frame) / F, and
  - NLL in bits/frame standardised: -log p_std / (F * ln 2),

  with F the number of scored frames. Mean and a bootstrap 95% interval over windows are given
  for the test split and for (a deterministic subset of) the training split.
* **Motion quality** of samples drawn for the test controls at a stated temperature, with the
  metrics of ``motionflows.evaluation.motion``; the ground-truth test motion is scored the same
  way as a reference row.
* **Speed**: training frames/s (median over the run's ``metrics.jsonl``) and sampling frames/s
  at batch 1 and 64 (compile time excluded and reported separately), on the machine described.

Budgets: ``smoke`` = each experiment's ``quick`` preset shrunk to a CI-sized model and a few
steps (:data:`SMOKE_OVERRIDES`), ``quick`` = the ``quick`` preset, ``full`` = the ``paper``
preset. A finished run under ``runs/`` whose saved config equals the one the bench would train
is reused instead of retrained.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import platform
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from motionflows.config import DataConfig, to_dict
from motionflows.errors import MotionDataError, RunError

ALL_MODELS: tuple[str, ...] = ("glow_fixed", "moglow", "vae_lstm", "gaussian", "linear_ar")
"""Model names the bench knows, in report order."""

EXPERIMENTS: dict[str, tuple[str, dict[str, Any]]] = {
    "glow_fixed": ("experiments.glow_fixed", {}),
    "moglow": ("experiments.moglow", {}),
    "vae_lstm": ("experiments.vae_lstm", {}),
    "gaussian": ("experiments.baselines", {"model": "gaussian"}),
    "linear_ar": ("experiments.baselines", {"model": "linear_ar"}),
}
"""model name -> (experiment module, config fields that select the model)."""

BUDGETS: dict[str, str] = {"smoke": "quick", "quick": "quick", "cpu": "cpu", "full": "paper"}
"""budget -> the experiment preset it starts from."""

SMOKE_TRAIN: dict[str, Any] = {
    "train.steps": 30,
    "train.batch_size": 8,
    "train.eval_every": 1_000_000,  # validate once, at the last step
    "train.eval_batches": 1,
    "train.log_every": 5,
    "train.checkpoint_every": 1_000_000,
    "train.keep_checkpoints": 1,
}
"""Training overrides of the smoke budget (every trained model; closed-form fits keep theirs)."""

SMOKE_OVERRIDES: dict[str, dict[str, Any]] = {
    "glow_fixed": {"levels": 2, "K": 2, "hidden": 16},
    "moglow": {"K": 2, "hidden": 16, "layers": 1},
    "vae_lstm": {
        "latent_dim": 16, "control_hidden": 8, "control_features": 16, "pose_hidden": 16,
        "pose_features": 32, "decoder_hidden": 16, "kernel": 5, "iwae_samples": (1, 10),
    },
    "gaussian": {},
    "linear_ar": {},
}  # fmt: skip
"""Model-size overrides of the smoke budget: CI-sized networks (fields missing from a config
are skipped and listed in the report's provenance)."""

SMOKE_DATA = {"synthetic_clips": 16, "synthetic_seconds": 6.0, "window": 32, "hop": 8}
"""Data-config overrides of the smoke budget (a small synthetic set and short windows)."""

BUDGET_SIZES: dict[str, dict[str, int]] = {
    # windows scored for likelihood (test, and a train subset), windows sampled for motion
    # quality, samples drawn for diversity, frames per GIF, bootstrap resamples,
    # prefix lengths for per-frame NLL of causal models
    "smoke": dict(eval_windows=32, train_windows=32, motion_windows=8, diversity=8,
                  gif_frames=12, bootstrap=200, speed_repeats=1, prefix_points=2),
    "quick": dict(eval_windows=512, train_windows=256, motion_windows=64, diversity=16,
                  gif_frames=80, bootstrap=1000, speed_repeats=3, prefix_points=10),
    "cpu": dict(eval_windows=100000, train_windows=512, motion_windows=256, diversity=32,
                gif_frames=80, bootstrap=1000, speed_repeats=3, prefix_points=10),
    "full": dict(eval_windows=100000, train_windows=1024, motion_windows=256, diversity=32,
                 gif_frames=80, bootstrap=2000, speed_repeats=3, prefix_points=20),
}  # fmt: skip

EVAL_CHUNK = 64
"""Windows per evaluation / sampling call (the last chunk is padded, so one compile each)."""

# --------------------------------------------------------------------------------------------
# configuration: data spec, budget, experiment configs
# --------------------------------------------------------------------------------------------


def parse_data_spec(spec: str, budget: str = "quick") -> DataConfig:
    """The one :class:`DataConfig` every model of a bench trains and is scored on.

    ``spec``: ``"synthetic"`` (the embedded procedural locomotion), ``"bandai"`` (the Bandai-
    Namco locomotion folder; the data layer's default path), ``"bandai:DIR"``, or ``"bvh:DIR"``
    (any folder of BVH files with the bandai skeleton mapping); the grammar of ``motionflows
    train --data`` (:func:`motionflows.runs.parse_data`). The ``smoke`` budget shrinks the
    synthetic set and the window (:data:`SMOKE_DATA`); the ``cpu`` budget splits Bandai data
    by performer.
    """
    from motionflows.runs import parse_data

    if not isinstance(spec, str) or not spec:
        raise ValueError("--data must be 'synthetic', 'bandai', 'bandai:DIR' or 'bvh:DIR'")
    fields = parse_data(spec)  # the same --data grammar as `motionflows train`
    if fields.get("source") in ("bvh", "bandai") and fields.get("path"):
        if not Path(fields["path"]).is_dir():
            raise RunError(f"--data {spec}: {fields['path']!r} is not a folder of BVH files")
    data = DataConfig(**fields)
    if budget == "cpu" and data.source == "bandai":
        # the cpu budget's tables are on a performer no model saw (D2-C of the Bandai set)
        data = dataclasses.replace(data, split_by="performer")
    if budget == "smoke":
        changes = dict(SMOKE_DATA)
        if data.source != "synthetic":
            changes = {k: v for k, v in changes.items() if not k.startswith("synthetic")}
        data = dataclasses.replace(data, **changes)
    return data


def parse_models(models: str | Sequence[str] | None) -> tuple[str, ...]:
    """``"glow_fixed,moglow"`` or a sequence -> validated tuple of model names."""
    if models is None or models == "" or models == "all":
        return ALL_MODELS
    names = models.split(",") if isinstance(models, str) else list(models)
    names = [n.strip() for n in names if n.strip()]
    unknown = [n for n in names if n not in EXPERIMENTS]
    if unknown:
        raise RunError(f"--models: unknown model(s) {unknown}; choose from {list(ALL_MODELS)}")
    if not names:
        raise RunError(f"--models: give at least one of {list(ALL_MODELS)}")
    return tuple(dict.fromkeys(names))


def load_experiment(model: str):
    """The experiment module of ``model``, looked up in the ``motionflows.experiments``
    entry points (``motionflows.runs.resolve_experiment``)."""
    from motionflows.runs import resolve_experiment

    module_name = EXPERIMENTS[model][0]
    try:
        return resolve_experiment(module_name.split(".", 1)[1])
    except RunError as err:
        raise RunError(
            f"model {model!r}: cannot use {module_name} ({err}); install the motionflows "
            "checkout (`pip install -e .`), or leave this model out with --models"
        ) from err


def replace_fields(config: Any, values: dict[str, Any]) -> tuple[Any, dict, list[str]]:
    """``config`` with dotted-path fields replaced by python values; returns (config, the
    values applied, the paths that do not exist in this config)."""
    applied, missing = {}, []
    for path, value in values.items():
        parts = path.split(".")
        try:
            config = _replace(config, parts, value)
        except (AttributeError, TypeError):
            missing.append(path)
            continue
        applied[path] = value
    return config, applied, missing


def _replace(config: Any, parts: list[str], value: Any) -> Any:
    if not dataclasses.is_dataclass(config) or parts[0] not in {
        f.name for f in dataclasses.fields(config)
    }:
        raise AttributeError(parts[0])
    if len(parts) == 1:
        return dataclasses.replace(config, **{parts[0]: value})
    inner = _replace(getattr(config, parts[0]), parts[1:], value)
    return dataclasses.replace(config, **{parts[0]: inner})


def bench_config(model: str, budget: str, data: DataConfig, exp=None) -> tuple[Any, dict]:
    """The exact config the bench trains for ``model`` at ``budget`` on ``data``.

    Starts from the experiment's preset (:data:`BUDGETS`), selects the model, replaces the
    data section by ``data`` (identical frames for every model) and, for ``smoke``, applies
    :data:`SMOKE_TRAIN` and :data:`SMOKE_OVERRIDES`. Returns (config, provenance dict).
    """
    if budget not in BUDGETS:
        raise RunError(f"--budget {budget!r}: choose from {list(BUDGETS)}")
    exp = exp or load_experiment(model)
    preset = BUDGETS[budget]
    if preset not in exp.PRESETS:
        raise RunError(f"{exp.__name__} has no preset {preset!r} (has {list(exp.PRESETS)})")
    config = exp.PRESETS[preset]
    config, selected, missing = replace_fields(config, EXPERIMENTS[model][1])
    if missing:
        raise RunError(f"{exp.__name__}.Config lacks {missing}: cannot select model {model!r}")
    config = dataclasses.replace(config, data=data)
    applied: dict[str, Any] = {}
    skipped: list[str] = []
    if budget == "smoke":
        # closed-form fits (train.steps == 0, the baselines) keep their training settings
        values = dict(SMOKE_TRAIN) if config.train.steps > 0 else {}
        values.update(SMOKE_OVERRIDES[model])
        config, applied, skipped = replace_fields(config, values)
    provenance = {
        "experiment": getattr(exp, "NAME", exp.__name__.rsplit(".", 1)[-1]),
        "module": exp.__name__,
        "preset": preset,
        "overrides": {**selected, "data": "the bench's data config", **applied},
        "overrides_skipped": skipped,
    }
    return config, provenance


# --------------------------------------------------------------------------------------------
# machine
# --------------------------------------------------------------------------------------------


def describe_machine() -> dict:
    """CPU model, visible cores, memory, OS, and the JAX/Flax versions and backend."""
    import flax
    import jax

    cpu = platform.processor() or platform.machine()
    isa: list[str] = []  # the vector extensions that decide CPU matmul speed
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
        for line in lines:
            if line.lower().startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
        flags = set(next((ln for ln in lines if ln.startswith("flags")), "").split())
        isa = [x for x in ("avx2", "avx512f", "avx512_bf16", "amx_bf16") if x in flags]
    except OSError:
        pass
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:
        cores = os.cpu_count()
    memory = "memory unknown"
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal"):
                memory = f"{int(line.split()[1]) / 2**20:.0f} GiB RAM"
                break
    except OSError:
        pass
    devices = jax.devices()
    try:
        load = "load average {:.1f} / {:.1f} / {:.1f} (1 / 5 / 15 min)".format(*os.getloadavg())
    except OSError:
        load = "load unknown"
    return {
        "load": load,
        "cpu": cpu,
        "isa": isa,
        "cores": cores,
        "memory": memory,
        "platform": f"{platform.system()} {platform.release()}",
        "python": platform.python_version(),
        "jax": jax.__version__,
        "flax": flax.__version__,
        "backend": jax.default_backend(),
        "devices": f"{len(devices)} x {devices[0].device_kind}",
    }


# --------------------------------------------------------------------------------------------
# statistics helpers
# --------------------------------------------------------------------------------------------


def _finite_float(x: Any) -> float | None:
    try:
        v = float(np.asarray(x, dtype=np.float64).mean())
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def _jsonable(obj: Any) -> Any:
    """Recursively turn numpy / JAX values into JSON types (NaN/inf -> None)."""
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, str | bool) or obj is None:
        return obj
    if isinstance(obj, int | np.integer):
        return int(obj)
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return _jsonable(dataclasses.asdict(obj))
    try:
        arr = np.asarray(obj)
    except Exception:  # noqa: BLE001
        return str(obj)
    if arr.dtype.kind in "fc" or arr.dtype.kind in "iub":
        if arr.ndim == 0:
            v = float(arr)
            if arr.dtype.kind in "iu":
                return int(arr)
            return v if math.isfinite(v) else None
        return [_jsonable(v) for v in arr.tolist()]
    return str(obj)


# --------------------------------------------------------------------------------------------
# runs: find a finished run with the same config, or train one
# --------------------------------------------------------------------------------------------


def _saved_config(run_dir: Path) -> tuple[str | None, dict | None]:
    """(experiment name, config dict) from a run's ``config.json``, or (None, None)."""
    try:
        saved = json.loads((run_dir / "config.json").read_text())
    except (OSError, ValueError):
        return None, None
    if isinstance(saved, dict) and isinstance(saved.get("config"), dict):
        return saved.get("experiment"), saved["config"]
    return None, saved if isinstance(saved, dict) else None


def run_finished(run_dir: Path, steps: int) -> bool:
    """Whether ``run_dir`` completed: its ``metrics.jsonl`` ends with status ``finished`` at
    step >= ``steps``, or ``fitted`` (closed-form baselines)."""
    status, step = None, -1
    try:
        with open(run_dir / "metrics.jsonl") as fh:
            for line in fh:
                try:
                    rec = json.loads(line)
                except ValueError:
                    continue
                if "status" in rec:
                    status, step = rec["status"], int(rec.get("step") or 0)
    except OSError:
        return False
    if status == "fitted":
        return True
    return status == "finished" and step >= steps


def find_run(runs_dir: str | Path, experiment: str, config: Any) -> Path | None:
    """The newest finished run under ``runs_dir/<experiment>/`` whose saved config equals
    ``config`` (same data, model and training settings), else None."""
    base = Path(runs_dir) / experiment
    if not base.is_dir():
        return None
    want = to_dict(config)
    steps = int(config.train.steps)
    hits = []
    for cfg in base.glob("*/config.json"):
        name, saved = _saved_config(cfg.parent)
        if name not in (None, experiment) or saved != want:
            continue
        if run_finished(cfg.parent, steps):
            hits.append(cfg.parent)
    if not hits:
        return None
    return max(hits, key=lambda p: p.stat().st_mtime)


# --------------------------------------------------------------------------------------------
# likelihood
# --------------------------------------------------------------------------------------------


def _subset(n: int, limit: int, seed: int) -> np.ndarray:
    """All indices if n <= limit, else a sorted deterministic random subset of ``limit``."""
    if n <= limit:
        return np.arange(n)
    return np.sort(np.random.default_rng(seed).choice(n, size=limit, replace=False))


def complete_windows(windows) -> np.ndarray:
    """Indices of the windows without padding (every frame recorded): only these are scored,
    since a padded tail (a frozen last pose) is not motion."""
    valid = getattr(windows, "valid", None)
    if valid is None:
        return np.arange(len(windows.pose))
    return np.flatnonzero(np.asarray(valid).all(axis=1))


def _pick(windows, limit: int, seed: int) -> np.ndarray:
    """A deterministic subset (at most ``limit``) of the complete windows of a split."""
    full = complete_windows(windows)
    return full[_subset(len(full), limit, seed)]


def _standardized(dataset, windows, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    st = dataset.standardizer
    pose = np.asarray(st.normalize_pose(np.asarray(windows.pose)[idx]), np.float32)
    control = np.asarray(st.normalize_control(np.asarray(windows.control)[idx]), np.float32)
    return pose, control


def score_likelihood(
    exp,
    model,
    config,
    dataset,
    split: str,
    *,
    limit: int,
    key,
    num_bootstrap: int,
    evaluate_fn=None,
    chunk: int = EVAL_CHUNK,
) -> dict:
    """Likelihood table rows of one split: ``{scope: row}`` (see ``likelihood_rows``)."""
    from motionflows.evaluation.likelihood import likelihood_rows, scored_frames

    windows = dataset.split(split)
    idx = _pick(windows, limit, seed=1)
    if len(idx) == 0:
        raise RunError(
            f"the {split} split has no complete windows; use more data or a shorter window"
        )
    pose, control = _standardized(dataset, windows, idx)
    lls = _evaluate_windows(
        exp, model, pose, control, key=key, evaluate_fn=evaluate_fn, chunk=chunk
    )
    scopes = getattr(exp, "SCOPES", {}) or {}
    if scopes:
        lls = {k: v for k, v in lls.items() if k in scopes}
    window = pose.shape[1]
    frames = {k: int(scored_frames(scopes, k, window, config)) for k in lls}
    rows = likelihood_rows(
        lls,
        frames,
        float(dataset.standardizer.log_det_per_frame),
        scopes=scopes,
        num_bootstrap=num_bootstrap,
        seed=0,
    )
    return {r["scope"]: r for r in rows}


def _evaluate_windows(exp, model, pose, control, *, key, evaluate_fn=None, chunk: int = EVAL_CHUNK):
    from motionflows.evaluation.likelihood import evaluate_windows

    return evaluate_windows(
        exp, model, pose, control, batch_size=chunk, key=key, evaluate_fn=evaluate_fn
    )


def merge_splits(test: dict, train: dict) -> dict:
    """``{scope: {description, bound, frames, test: row, train: row}}``."""
    out = {}
    for scope, row in test.items():
        out[scope] = {
            "description": row.get("description", ""),
            "bound": row.get("bound", False),
            "frames": row.get("scored_frames_per_window"),
            "test": row,
            "train": train.get(scope),
        }
    return out


def per_frame_nll(
    exp,
    model,
    dataset,
    *,
    limit: int,
    key,
    points: int,
    causal: bool,
    evaluate_fn=None,
    chunk: int = EVAL_CHUNK,
    window_scorer=None,
    full_window_mean: float | None = None,
) -> dict:
    """Test NLL (nats/frame, metres) against the frame position in the window.

    Exact in both routes used: the model's own per-frame log-densities (``frame_log_prob``,
    e.g. the baselines and MoGlow), or, for a causal model (the score of frames 1..t does not
    depend on later frames), differences of whole-window scores of prefixes 1..t:
    log p(x_s..t | x_<s, c) = log p(x_1:t | c_1:t) - log p(x_1:s-1 | c_1:s-1), averaged over the
    frames of each block. Not available for a non-causal model (the fixed-length Glow scores a
    window jointly; no per-frame factorisation is exact) nor for a bound (VAE-LSTM).
    """
    windows = dataset.test
    idx = _pick(windows, limit, seed=1)
    pose, control = _standardized(dataset, windows, idx)
    t_len = pose.shape[1]
    log_det = float(dataset.standardizer.log_det_per_frame)
    frame_fn = getattr(model, "frame_log_prob", None)
    if callable(frame_fn):
        import jax

        def frames(m, p, c):
            try:
                return m.frame_log_prob(p, c)
            except TypeError:
                return m.frame_log_prob(p)

        fn = jax.jit(frames)
        parts = []
        for start in range(0, len(pose), EVAL_CHUNK):
            parts.append(
                np.asarray(
                    fn(
                        model, pose[start : start + EVAL_CHUNK], control[start : start + EVAL_CHUNK]
                    ),
                    np.float64,
                )
            )
        ll = np.concatenate(parts)  # (N, T)
        if ll.shape == pose.shape[:2]:
            nll = -(ll.mean(0) + log_det)
            return {
                "available": True,
                "method": "exact per frame",
                "positions": list(range(t_len)),
                "nats_per_frame_metres": nll.tolist(),
            }
    if not causal:
        return {"available": False, "method": "none"}
    ends = sorted(set(np.linspace(0, t_len, points + 1).round().astype(int).tolist()) - {0})
    totals = [0.0]
    if window_scorer is not None:
        import jax

        scorer = jax.jit(window_scorer)

        def window_fn(m, batch, k):
            return {"window": scorer(m, batch["pose"], batch["control"])}

        evaluate_fn = window_fn
    for end in ends:
        if end == t_len and full_window_mean is not None:
            totals.append(float(full_window_mean))  # already scored on these windows
            continue
        lls = _evaluate_windows(
            exp,
            model,
            pose[:, :end],
            control[:, :end],
            key=key,
            evaluate_fn=evaluate_fn,
            chunk=chunk,
        )
        totals.append(float(np.mean(lls["window"])))
    positions, nll = [], []
    starts = [0] + ends[:-1]
    for k, (s, e) in enumerate(zip(starts, ends, strict=True)):
        per = -((totals[k + 1] - totals[k]) / (e - s) + log_det)
        positions.append((s + e - 1) / 2)
        nll.append(per)
    return {
        "available": True,
        "method": f"prefix differences, {len(ends)} blocks",
        "positions": positions,
        "nats_per_frame_metres": nll,
    }


# --------------------------------------------------------------------------------------------
# sampling: speed and motion quality
# --------------------------------------------------------------------------------------------


def make_sampler(exp, temperature: float):
    """A jitted ``(model, control, key) -> pose`` (standardised) from the experiment's
    ``sample``; falls back to the un-jitted function if the sampler cannot be traced."""
    import jax

    def sample(model, control, key):
        return exp.sample(model, control, key, temperature=temperature)

    jitted = jax.jit(sample)

    def call(model, control, key):
        nonlocal jitted
        try:
            return jitted(model, control, key)
        except (
            jax.errors.ConcretizationTypeError,
            jax.errors.TracerBoolConversionError,
            jax.errors.TracerArrayConversionError,
        ):
            jitted = sample
            return sample(model, control, key)

    return call


def _block(x):
    import jax

    return jax.block_until_ready(x)


def time_sampler(sampler, model, control: np.ndarray, batch: int, key, repeats: int) -> dict:
    """Sampling speed at ``batch``: frames/s (compile excluded) and compile seconds."""
    import jax

    reps = int(math.ceil(batch / len(control)))
    c = np.concatenate([control] * reps)[:batch]
    t0 = time.perf_counter()
    _block(sampler(model, c, key))
    first = time.perf_counter() - t0
    times = []
    for r in range(repeats):
        t0 = time.perf_counter()
        _block(sampler(model, c, jax.random.fold_in(key, r + 1)))
        times.append(time.perf_counter() - t0)
    best = min(times)
    frames = batch * c.shape[1]
    return {"frames_per_s": frames / best, "seconds": best, "compile_s": max(first - best, 0.0)}


def draw_samples(sampler, model, control: np.ndarray, key) -> np.ndarray:
    """Samples (standardised) for every control window, in padded chunks of EVAL_CHUNK."""
    import jax

    out = []
    n = len(control)
    for b, start in enumerate(range(0, n, EVAL_CHUNK)):
        idx = np.arange(start, start + EVAL_CHUNK) % n
        x = sampler(model, control[idx], jax.random.fold_in(key, b))
        out.append(np.asarray(x, np.float32)[: min(EVAL_CHUNK, n - start)])
    return np.concatenate(out)


def count_params(model) -> int | None:
    import jax

    try:
        from flax import nnx

        state = nnx.state(model, nnx.Param)
        leaves = jax.tree_util.tree_leaves(state)
    except Exception:  # noqa: BLE001
        leaves = jax.tree_util.tree_leaves(model)
    try:
        return int(sum(np.size(x) for x in leaves if hasattr(x, "shape")))
    except Exception:  # noqa: BLE001
        return None


def fit_seconds(run_dir: Path) -> float | None:
    """Seconds of a closed-form fit (``fit_seconds`` in ``metrics.jsonl``), else None."""
    try:
        for line in open(run_dir / "metrics.jsonl"):
            rec = json.loads(line)
            if isinstance(rec.get("fit_seconds"), int | float):
                return float(rec["fit_seconds"])
    except (OSError, ValueError):
        return None
    return None


def train_speed(run_dir: Path) -> float | None:
    """Median training frames/s logged in ``metrics.jsonl`` (first logged record dropped:
    it includes compilation)."""
    values = []
    try:
        with open(run_dir / "metrics.jsonl") as fh:
            for line in fh:
                try:
                    rec = json.loads(line)
                except ValueError:
                    continue
                for k in ("frames_per_s", "frames/s", "frames_per_sec", "train_frames_per_s"):
                    v = rec.get(k)
                    if isinstance(v, int | float) and math.isfinite(v) and v > 0:
                        values.append(float(v))
                        break
    except OSError:
        return None
    if len(values) > 2:
        values = values[1:]
    return float(np.median(values)) if values else None


# --------------------------------------------------------------------------------------------
# orchestration
# --------------------------------------------------------------------------------------------

CAUSAL_MODELS = frozenset({"moglow", "gaussian", "linear_ar"})
"""Models whose score of frames 1..t ignores later frames (per-frame NLL by prefixes)."""

WINDOW_SCORERS = {
    # MoGlow's whole-window score alone (its evaluate() also scores the official scope, which
    # needs more than tau frames, so it cannot score short prefixes)
    "moglow": lambda model, pose, control: model.log_prob(pose, control, scope="window"),
}
"""model name -> (model, pose, control) -> (B,) window log-likelihood, for prefix scoring."""

PER_FRAME_UNAVAILABLE = {
    "glow_fixed": "not available: the fixed-length Glow scores a window jointly "
    "(non-causal), so no per-frame split of its likelihood is exact",
    "vae_lstm": "not available: the VAE-LSTM gives only bounds on the whole window",
}


def _log(progress, msg: str) -> None:
    if progress:
        progress(f"[bench {time.strftime('%H:%M:%S')}] {msg}")


def obtain_run(
    model_name: str,
    exp,
    config,
    provenance: dict,
    *,
    runs_dir: Path,
    budget: str,
    data_tag: str,
    retrain: bool,
    progress,
    dataset=None,
) -> tuple[Path, bool, float]:
    """(run_dir, reused, training seconds): reuse a finished identical run or train one."""
    experiment = provenance["experiment"]
    if not retrain:
        found = find_run(runs_dir, experiment, config)
        if found is not None:
            _log(progress, f"{model_name}: reusing finished run {found}")
            return found, True, 0.0
    name = f"bench-{model_name}-{budget}-{data_tag}-{time.strftime('%Y%m%d-%H%M%S')}"
    run_dir = runs_dir / experiment / name
    _log(
        progress,
        f"{model_name}: training {provenance['preset']} preset "
        f"({config.train.steps} steps) -> {run_dir}",
    )
    t0 = time.perf_counter()
    _train(exp, config, run_dir, preset=provenance["preset"], progress=progress, dataset=dataset)
    return run_dir, False, time.perf_counter() - t0


def _train(exp, config, run_dir: Path, *, preset: str, progress, dataset=None) -> None:
    """Train through ``motionflows.training.train`` (its Python API)."""
    from motionflows import training

    result = training.train(
        exp, config, run_dir=run_dir, preset=preset, progress=bool(progress), dataset=dataset
    )
    if result.status not in ("finished", "fitted"):
        raise RunError(
            f"training {run_dir} ended with status {result.status!r}; see its metrics.jsonl"
        )


def _load(run_dir: Path, dataset=None):
    """(module, config, model, dataset) rebuilt from the run directory (best checkpoint by
    validation NLL; the last one if the run never validated)."""
    from motionflows import training

    return training.load_run(run_dir, checkpoint="best", dataset=dataset)


class _Section:
    """Run one part of a model's benchmark; record a failure instead of aborting (unless
    ``strict``), so one broken model or metric does not lose the whole report."""

    def __init__(self, entry: dict, key: str, strict: bool, progress):
        self.entry, self.key, self.strict, self.progress = entry, key, strict, progress

    def __enter__(self):
        self.t0, self.c0 = time.perf_counter(), time.process_time()
        return self

    def __exit__(self, kind, err, tb):
        timings = self.entry.setdefault("timings", {})
        name = self.key.replace("_error", "") if self.key != "error" else "train+likelihood"
        timings[name] = {
            "wall_s": time.perf_counter() - self.t0,
            "cpu_s": time.process_time() - self.c0,
        }
        if err is None or not isinstance(err, Exception):
            return False
        import traceback

        text = f"{kind.__name__}: {err}"
        self.entry[self.key] = text
        _log(
            self.progress,
            f"FAILED ({self.key}): {text}\n"
            + "".join(traceback.format_exception(kind, err, tb))[-2000:],
        )
        return not self.strict


def _frames_label(row: dict, window: int) -> str:
    n = int(row["scored_frames_per_window"])
    return f"{n} (frames {window - n + 1}..{window})"


def bench_model(
    name: str,
    *,
    data: DataConfig,
    budget: str,
    sizes: dict,
    runs_dir: Path,
    temperature: float,
    seed: int,
    retrain: bool,
    strict: bool,
    progress,
    motion_idx: np.ndarray | None = None,
    likelihood_only: bool = False,
    dataset=None,
) -> dict:
    """Everything the report holds about one model; ``entry["_samples"]`` (metres, not saved
    to JSON) keeps the motion samples for the GIFs."""
    import jax

    entry: dict[str, Any] = {}
    key = jax.random.key(seed)
    with _Section(entry, "error", strict, progress):
        exp = load_experiment(name)
        config, prov = bench_config(name, budget, data, exp)
        entry.update(prov)
        entry["config"] = to_dict(config)
        c0 = time.process_time()
        run_dir, reused, secs = obtain_run(
            name,
            exp,
            config,
            prov,
            runs_dir=Path(runs_dir),
            budget=budget,
            data_tag=_data_tag(data),
            retrain=retrain,
            progress=progress,
            dataset=dataset,
        )
        entry.setdefault("timings", {})["train"] = {
            "wall_s": secs,
            "cpu_s": time.process_time() - c0,
        }
        entry.update(
            run_dir=str(run_dir), reused=reused, train_seconds=secs, steps=int(config.train.steps)
        )
        _, run_config, model, dataset = _load(run_dir, dataset)
        entry["params"] = count_params(model)
        if int(run_config.train.steps) > 0:
            # place the model as the training loop does (replicated over the data mesh), so
            # the evaluate compiled for its validation is reused (same shapes and shardings)
            from motionflows.sharding import data_mesh, replicate

            model = replicate(model, data_mesh())
        # the same jitted function and batch shape as the trainer's validation: one compile
        evaluate_fn = jax.jit(exp.evaluate)
        tc = run_config.train
        chunk = min(
            getattr(tc, "val_batch_size", None) or tc.batch_size or EVAL_CHUNK,
            len(complete_windows(dataset.test)),
            sizes["eval_windows"],
            len(complete_windows(dataset.train)),
            sizes["train_windows"],
        )
        _log(progress, f"{name}: likelihood on test and train windows")
        test = score_likelihood(
            exp,
            model,
            run_config,
            dataset,
            "test",
            limit=sizes["eval_windows"],
            key=jax.random.fold_in(key, 1),
            num_bootstrap=sizes["bootstrap"],
            evaluate_fn=evaluate_fn,
            chunk=chunk,
        )
        train = score_likelihood(
            exp,
            model,
            run_config,
            dataset,
            "train",
            limit=sizes["train_windows"],
            key=jax.random.fold_in(key, 2),
            num_bootstrap=sizes["bootstrap"],
            evaluate_fn=evaluate_fn,
            chunk=chunk,
        )
        window = int(np.asarray(dataset.test.pose).shape[1])
        entry["likelihood"] = merge_splits(test, train)
        for lik in entry["likelihood"].values():
            lik["frames_label"] = _frames_label(lik["test"], window)
        if likelihood_only:
            return entry
        # mean log-likelihood (nats, standardised) of the scored test windows: the prefix
        # route of per_frame_nll reuses it for the whole window
        window_row = test.get("window")
        full_mean = None
        if window_row is not None:
            n = window_row["scored_frames_per_window"]
            full_mean = (
                -(
                    window_row["nats_per_frame_metres"]
                    + float(dataset.standardizer.log_det_per_frame)
                )
                * n
            )
        entry["speed"] = {
            "train_frames_per_s": train_speed(run_dir),
            "fit_seconds": fit_seconds(run_dir),
        }
    if "error" in entry:
        return entry

    with _Section(entry, "per_frame_error", strict, progress):
        if name in PER_FRAME_UNAVAILABLE and not callable(getattr(model, "frame_log_prob", 0)):
            entry["per_frame_nll"] = {"available": False, "method": PER_FRAME_UNAVAILABLE[name]}
        else:
            entry["per_frame_nll"] = per_frame_nll(
                exp,
                model,
                dataset,
                limit=sizes["eval_windows"],
                key=jax.random.fold_in(key, 3),
                points=sizes["prefix_points"],
                causal=name in CAUSAL_MODELS,
                evaluate_fn=evaluate_fn,
                chunk=chunk,
                window_scorer=WINDOW_SCORERS.get(name),
                full_window_mean=full_mean,
            )

    sampler = make_sampler(exp, temperature)
    with _Section(entry, "speed_error", strict, progress):
        _log(progress, f"{name}: sampling speed at batch 1 and 64")
        _, ctrl = _standardized(dataset, dataset.test, motion_idx)
        for b in (1, EVAL_CHUNK):
            sp = time_sampler(
                sampler, model, ctrl, b, jax.random.fold_in(key, 10 + b), sizes["speed_repeats"]
            )
            entry["speed"][f"sample_frames_per_s_b{b}"] = sp["frames_per_s"]
            entry["speed"][f"compile_s_b{b}"] = sp["compile_s"]

    with _Section(entry, "motion_error", strict, progress):
        _log(progress, f"{name}: samples for {len(motion_idx)} test controls, motion metrics")
        st = dataset.standardizer
        _, ctrl = _standardized(dataset, dataset.test, motion_idx)
        samples = draw_samples(sampler, model, ctrl, jax.random.fold_in(key, 20))
        samples_m = np.asarray(st.denormalize_pose(samples), np.float32)
        one = np.repeat(ctrl[:1], EVAL_CHUNK, axis=0)
        div = draw_samples(sampler, model, one, jax.random.fold_in(key, 21))
        div_m = np.asarray(st.denormalize_pose(div), np.float32)[: sizes["diversity"]]
        gt_m = np.asarray(dataset.test.pose, np.float32)[motion_idx]
        control_m = np.asarray(dataset.test.control, np.float32)[motion_idx]
        fps = float(data.fps)
        entry["motion"] = motion_metrics(samples_m, control_m, gt_m, div_m, fps)
        entry["_samples"] = samples_m
    return entry


def _data_tag(data: DataConfig) -> str:
    tag = data.source if data.source != "bvh" else "bvh-" + Path(str(data.path)).name
    return tag if data.split_by == "take" else f"{tag}-{data.split_by}"


# --------------------------------------------------------------------------------------------
# motion metrics and GIFs (thin adapters over motionflows.evaluation.motion and render)
# --------------------------------------------------------------------------------------------

DIVERGED_METRES = 10.0
"""A sample with a root-relative coordinate beyond this (or NaN/inf) counts as diverged."""

MOTION_METRICS: dict[str, dict[str, str]] = {
    "foot_sliding": {"label": "foot sliding", "unit": "m/s"},
    "skate_ratio": {"label": "skate ratio", "unit": "fraction"},
    "contact_rate": {"label": "foot contact rate", "unit": "fraction"},
    "bone_length_std": {"label": "bone-length std", "unit": "m"},
    "jerk": {"label": "jerk (world)", "unit": "m/s^3"},
    "fd_pose": {"label": "FD poses", "unit": "m^2"},
    "fd_window3": {"label": "FD 3-frame windows", "unit": "m^2"},
    "diversity": {"label": "diversity, one control", "unit": "m"},
    "pose_error": {"label": "pose error", "unit": "m"},
    "motion_error": {"label": "motion error", "unit": "m"},
    "diverged": {"label": "diverged samples", "unit": "fraction"},
}
"""Motion metrics in report order (all from ``motionflows.evaluation.motion``)."""

MOTION_NOTE = (
    "Foot sliding: mean horizontal world speed of a foot (mean of ankle and toe) while its "
    "lowest joint is within 1.5 cm of the window's floor (the 5th percentile of the feet's "
    "heights, clipped to +-5 cm) at two consecutive frames, with the contact rate beside it "
    "(height only: a foot dragged along the floor slides); skate ratio: the fraction of those "
    "contact steps faster than 0.5 m/s (2.5 cm/frame at 20 fps); bone-length std: the std "
    "over time of each bone's length, mean over bones; jerk: mean |d^3x/dt^3| of the joints in "
    "world coordinates (root trajectory integrated from the control); FD: Frechet distance "
    "between Gaussians fitted to real and generated poses (63-d) and 3-frame pose windows "
    "(189-d), against the same test windows; diversity: mean per-joint distance between pairs "
    "of samples drawn for one control (the first sampled test control); for the ground truth, "
    "the natural diversity: the mean per-joint distance between each real test window and "
    "the window of another take whose control is closest (RMS over frames, channels "
    "divided by their std); pose / motion error: "
    "Habibie et al.'s errors (root-relative joints / world joints after integrating the "
    "control) between one sample and the test motion, averaged over the report times "
    "(their frames 70, 90, 120, 160, 210 at 60 fps, at this frame rate, those inside the "
    "window). The ground-truth row scores the test motion itself (errors and FD are 0 by "
    "construction). Diverged samples: the fraction holding NaN/inf or a joint more than "
    f"{DIVERGED_METRES:g} m from the root (a flow's inverse can blow up far from its training "
    "data); the other metrics are over the remaining samples."
)


def diverged(samples_m) -> np.ndarray:
    """(N,) bool: sample n holds NaN/inf or a root-relative coordinate beyond
    :data:`DIVERGED_METRES`."""
    x = np.asarray(samples_m, np.float64).reshape(len(samples_m), -1)
    return ~np.all(np.isfinite(x) & (np.abs(x) <= DIVERGED_METRES), axis=1)


def natural_diversity_of(windows) -> float | None:
    """The ground-truth row's diversity: :func:`motionflows.evaluation.motion.natural_diversity`
    of every complete window of a split, each paired with the window of another take whose
    control is closest (None when the split has fewer than two takes)."""
    from motionflows.evaluation import motion as mm

    idx = complete_windows(windows)
    takes = getattr(windows, "take", None)
    takes = None if takes is None else np.asarray(takes)[idx]
    try:
        return mm.natural_diversity(
            np.asarray(windows.pose)[idx], np.asarray(windows.control)[idx], takes=takes
        )
    except ValueError:
        return None


def motion_metrics(samples_m, control_m, reference_m, diversity_m, fps: float) -> dict:
    """Motion-quality metrics of ``samples_m`` (N, T, 63) metres for controls ``control_m``
    against the ground truth ``reference_m`` (N, T, 63); ``diversity_m`` (M, T, 63) are M
    samples under one control (None for the ground truth, which has one motion per control).

    Returns the scalars of :data:`MOTION_METRICS` plus ``"prediction"``: the per-time errors.
    Diverged samples (see :func:`diverged`) are counted in ``"diverged"`` and left out of
    every other metric; ValueError when all diverged.
    """
    from motionflows.evaluation import motion as mm

    samples_m = np.asarray(samples_m, np.float64)
    ok = ~diverged(samples_m)
    if not ok.any():
        raise ValueError(
            f"all {len(samples_m)} samples diverged (NaN/inf or beyond {DIVERGED_METRES:g} m); "
            "no motion metrics"
        )
    frac = 1.0 - float(ok.mean())
    samples_m = samples_m[ok]
    control_m = np.asarray(control_m)[ok]
    reference_m = np.asarray(reference_m)[ok]
    if diversity_m is not None:
        diversity_m = np.asarray(diversity_m)[~diverged(diversity_m)]
    out: dict[str, Any] = dict(mm.motion_quality(samples_m, control_m, fps=fps))
    out["diverged"] = frac
    out["fd_pose"] = mm.frechet_pose_distance(reference_m, samples_m)
    out["fd_window3"] = mm.frechet_window_distance(reference_m, samples_m, frames=3)
    out["diversity"] = (
        None
        if diversity_m is None or len(diversity_m) < 2
        else mm.diversity(np.asarray(diversity_m)[:, None])
    )
    window = samples_m.shape[1]
    frames = [f for f in mm.prediction_frames(fps) if f < window]
    if not frames:
        frames = [window - 1]
    pose_err = mm.pose_error(samples_m, reference_m, frames=frames)
    motion_err = mm.motion_error(samples_m, reference_m, control_m, frames=frames)
    out["pose_error"] = float(np.mean(pose_err))
    out["motion_error"] = float(np.mean(motion_err))
    out["prediction"] = {
        "frames": frames,
        "seconds": [f / fps for f in frames],
        "pose_error": pose_err.tolist(),
        "motion_error": motion_err.tolist(),
        "num_samples": 1,
    }
    return out


def render_gif(sample_m, reference_m, control_m, path: Path, fps: float, title: str) -> None:
    """One GIF: the model's sample beside the ground truth (a second panel, same camera) for
    the same test control, both moved along the trajectory integrated from that control."""
    from motionflows import render

    render.animate(sample_m, control_m, path, fps=fps, title=title, compare=reference_m)


# --------------------------------------------------------------------------------------------
# the benchmark
# --------------------------------------------------------------------------------------------

BUDGET_NOTES = {
    "smoke": "each experiment's `quick` preset shrunk to a CI-sized model trained for a few "
    "steps on a small synthetic set (numbers are not meaningful, only the pipeline is)",
    "quick": "each experiment's `quick` preset (minutes per model on a 2-core CPU)",
    "cpu": "each experiment's `cpu` preset (the best motion found for at most 60 minutes of "
    "training on 2 CPU cores; on Bandai data split by performer, so every table is on the "
    "performer the models never saw)",
    "full": "each experiment's `paper` preset (the papers' hyper-parameters)",
}


def _command(data: str, models: Sequence[str], budget: str, out: str, extra: str = "") -> str:
    return (
        f"motionflows bench --data {data} --models {','.join(models)} --budget {budget} "
        f"--out {out}{extra}"
    )


def run_benchmark(
    data: str = "synthetic",
    models: str | Sequence[str] = ALL_MODELS,
    budget: str = "smoke",
    out: str | Path = "runs/bench",
    runs_dir: str | Path = "runs",
    *,
    temperature: float = 1.0,
    seed: int = 0,
    performer_split: bool | None = None,
    retrain: bool = False,
    gifs: bool = True,
    strict: bool = False,
    command: str | None = None,
    progress=print,
    test_data: str | None = None,
) -> dict:
    """Train (or reuse) every model on one data configuration, score, sample, time and report.

    Writes ``out/BENCHMARK.md``, ``out/results.json``, ``out/nll_per_frame.png``,
    ``out/motion_metrics.png`` and ``out/gifs/<model>.gif``; returns the results dict (the
    content of ``results.json``). ``performer_split`` (default: on for Bandai data) also trains
    every model on a split by performer and reports its train/test NLL. ``strict`` raises on
    the first failure instead of recording it in the report. ``test_data`` (``bvh:DIR``,
    ``bandai:DIR``, a folder) replaces the test split: every table is computed on the
    complete windows of those takes (cut at the bench's fps, window and hop, standardised
    with the training standardiser).
    """
    from motionflows import bench_report

    wall0 = time.perf_counter()
    if budget not in BUDGETS:
        raise RunError(f"--budget {budget!r}: choose from {list(BUDGETS)}")
    if not (
        isinstance(temperature, int | float) and math.isfinite(temperature) and temperature >= 0
    ):
        raise ValueError(f"--temperature must be a finite number >= 0, got {temperature!r}")
    names = parse_models(models)
    data_cfg = parse_data_spec(data, budget)
    sizes = BUDGET_SIZES[budget]
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    runs_dir = Path(runs_dir)
    command = command or _command(data, names, budget, str(out))
    _log(progress, f"loading {data} data ({data_cfg.source}, window {data_cfg.window})")
    dataset = data_cfg.load()
    test_info = {"spec": None, "note": "the test split of --data"}
    if test_data:
        from motionflows.data.takes import load_takes

        takes = load_takes(
            test_data,
            fps=float(data_cfg.fps),
            window=int(data_cfg.window),
            hop=int(data_cfg.hop),
            skeleton=data_cfg.skeleton,
        )
        dataset = dataset.with_test(takes.windows, test_data=str(test_data))
        test_info = {
            "spec": str(test_data),
            "label": takes.label,
            "takes": sorted(set(np.asarray(takes.windows.take).tolist())),
            "skipped": takes.skipped,
            "windows": len(takes.windows),
            "note": f"every complete window of the takes of {test_data} (not the test split)",
        }
        _log(progress, f"test data: {len(takes.windows)} windows of {test_data}")
    if len(complete_windows(dataset.test)) < 2:
        raise RunError(
            f"--data {data}: the test split has fewer than 2 complete windows; "
            "use more takes or a shorter window"
        )
    motion_idx = _pick(dataset.test, sizes["motion_windows"], seed=2)
    gt_m = np.asarray(dataset.test.pose, np.float32)[motion_idx]
    control_m = np.asarray(dataset.test.control, np.float32)[motion_idx]

    results: dict[str, Any] = {
        "command": command,
        "created": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "budget": budget,
        "budget_note": BUDGET_NOTES[budget],
        "data": {"spec": data, "config": to_dict(data_cfg), "info": _dataset_info(dataset)},
        "test_data": test_info,
        "window": int(np.asarray(dataset.test.pose).shape[1]),
        "temperature": float(temperature),
        "seed": int(seed),
        "bootstrap": sizes["bootstrap"],
        "motion_windows": len(motion_idx),
        "diversity_samples": sizes["diversity"],
        "train_windows_note": (
            f"at most {sizes['train_windows']} training windows (a fixed random subset; "
            "mirrored copies included where the pipeline augments)"
        ),
        "machine": describe_machine(),
        "model_order": list(names),
        "models": {},
    }
    gt_motion = None
    with _Section(results, "ground_truth_error", strict, progress):
        gt_motion = motion_metrics(gt_m, control_m, gt_m, None, float(data_cfg.fps))
        gt_motion["diversity"] = natural_diversity_of(dataset.test)
    results["ground_truth"] = {"motion": gt_motion}
    results["motion_metrics"] = dict(MOTION_METRICS)
    results["motion_note"] = MOTION_NOTE

    samples = {}
    for name in names:
        _log(progress, f"== {name}")
        t0 = time.perf_counter()
        entry = bench_model(
            name,
            data=data_cfg,
            budget=budget,
            sizes=sizes,
            runs_dir=runs_dir,
            dataset=dataset,
            temperature=temperature,
            seed=seed,
            retrain=retrain,
            strict=strict,
            progress=progress,
            motion_idx=motion_idx,
        )
        if "_samples" in entry:
            samples[name] = entry.pop("_samples")
        entry["bench_seconds"] = time.perf_counter() - t0
        results["models"][name] = entry

    if performer_split is None:  # (the cpu budget's main split already is by performer)
        performer_split = data_cfg.source == "bandai" and data_cfg.split_by == "take"
    if performer_split:
        results["performer_split"] = _performer_split(
            names, data_cfg, budget, sizes, runs_dir, temperature, seed, retrain, strict, progress
        )

    plots: dict[str, Any] = {}
    per_frame_notes = {}
    for name in names:
        pf = results["models"][name].get("per_frame_nll")
        if pf and not pf.get("available"):
            per_frame_notes[name] = pf["method"]
    results["per_frame_notes"] = per_frame_notes
    if bench_report.plot_per_frame_nll(results, out / "nll_per_frame.png"):
        plots["per_frame_nll"] = "nll_per_frame.png"
    if bench_report.plot_metric_bars(results, out / "motion_metrics.png"):
        plots["metrics"] = "motion_metrics.png"
    if gifs and samples:
        (out / "gifs").mkdir(exist_ok=True)
        plots["gifs"] = {}
        n_frames = min(sizes["gif_frames"], gt_m.shape[1])
        for name, s in samples.items():
            with _Section(results["models"][name], "gif_error", strict, progress):
                path = out / "gifs" / f"{name}.gif"
                render_gif(
                    s[0, :n_frames],
                    gt_m[0, :n_frames],
                    control_m[0, :n_frames],
                    path,
                    float(data_cfg.fps),
                    f"{name} sample (T={temperature:g}), beside the ground truth",
                )
                plots["gifs"][name] = f"gifs/{name}.gif"
    results["plots"] = plots
    results["wall_seconds"] = time.perf_counter() - wall0
    results = _jsonable(results)
    (out / "results.json").write_text(json.dumps(results, indent=2) + "\n")
    bench_report.write_markdown(results, out / "BENCHMARK.md")
    _log(
        progress,
        f"wrote {out / 'BENCHMARK.md'} and {out / 'results.json'} "
        f"in {results['wall_seconds']:.0f} s",
    )
    return results


def _dataset_info(dataset) -> dict:
    info = dict(getattr(dataset, "info", {}) or {})
    for split in ("train", "val", "test"):
        ws = dataset.split(split)
        info[f"windows_{split}"] = int(len(ws.pose))
        info[f"complete_windows_{split}"] = int(len(complete_windows(ws)))
    return _jsonable(info)


def _performer_split(
    names, data_cfg, budget, sizes, runs_dir, temperature, seed, retrain, strict, progress
) -> dict:
    """Retrain every model on a split by performer and score train/test likelihood."""
    data_p = dataclasses.replace(data_cfg, split_by="performer")
    split: dict[str, Any] = {"config": to_dict(data_p), "models": {}}
    try:
        ds = data_p.load()
        info = _dataset_info(ds)
        split["info"] = info
        performers = info.get("performers") or {}
        split["train"] = ", ".join(performers.get("train", [])) or "?"
        split["test"] = ", ".join(performers.get("test", [])) or "?"
    except Exception as err:  # noqa: BLE001
        if strict:
            raise
        return {"skipped": f"the data do not allow a split by performer ({err})"}
    for name in names:
        _log(progress, f"== {name} (split by performer)")
        split["models"][name] = bench_model(
            name,
            data=data_p,
            budget=budget,
            sizes=sizes,
            runs_dir=runs_dir,
            temperature=temperature,
            seed=seed,
            retrain=retrain,
            strict=strict,
            progress=progress,
            likelihood_only=True,
            dataset=ds,
        )
    return split


def estimate_training(
    data: str = "synthetic",
    models: str | Sequence[str] = ALL_MODELS,
    budget: str = "full",
    *,
    probe_steps: int = 4,
    progress=print,
) -> dict:
    """Project the training time of a budget on this machine without running it.

    For each model, trains ``probe_steps`` steps of the exact config the bench would train
    (in a temporary folder, through ``motionflows.training.train``) and multiplies the median
    steady-state seconds per step (the first step, which compiles, is dropped) by the
    config's ``train.steps``. Validation passes during training are not included. Returns
    ``{model: {"seconds_per_step", "steps", "projected_hours", ...}, "total_hours": ...}``.
    """
    import tempfile

    from motionflows import training
    from motionflows.runs import read_metrics

    names = parse_models(models)
    data_cfg = parse_data_spec(data, budget)
    dataset = data_cfg.load()
    out: dict[str, Any] = {
        "budget": budget,
        "data": data,
        "machine": describe_machine(),
        "models": {},
    }
    total = 0.0
    for name in names:
        exp = load_experiment(name)
        config, prov = bench_config(name, budget, data_cfg, exp)
        steps = int(config.train.steps)
        probe, _, _ = replace_fields(
            config,
            {
                "train.steps": max(probe_steps, 2) if steps > 0 else 0,
                "train.log_every": 1,
                "train.eval_every": 10**9,
                "train.eval_batches": 1,
                "train.checkpoint_every": 10**9,
            },
        )
        _log(progress, f"{name}: timing {probe.train.steps} steps of the {prov['preset']} config")
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            training.train(
                exp,
                probe,
                run_dir=Path(tmp) / "probe",
                preset=prov["preset"],
                dataset=dataset,
                progress=False,
            )
            wall = time.perf_counter() - t0
            rows = read_metrics(Path(tmp) / "probe")
        rates = [r["steps_per_s"] for r in rows if isinstance(r.get("steps_per_s"), int | float)]
        if steps == 0:
            entry = {
                "steps": 0,
                "seconds_per_step": None,
                "projected_hours": wall / 3600,
                "note": "closed-form fit (timed in full)",
            }
        else:
            steady = rates[1:] or rates
            sec = 1.0 / float(np.median(steady))
            entry = {
                "steps": steps,
                "seconds_per_step": sec,
                "batch_size": int(config.train.batch_size),
                "projected_hours": sec * steps / 3600,
                "probe_wall_s": wall,
            }
        total += entry["projected_hours"]
        out["models"][name] = entry
        _log(progress, f"{name}: {entry}")
    out["total_hours"] = total
    return out


# --------------------------------------------------------------------------------------------
# command line
# --------------------------------------------------------------------------------------------


def build_parser(parser: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    """The ``motionflows bench`` arguments (added to ``parser`` if given)."""
    p = parser or argparse.ArgumentParser(
        prog="motionflows bench",
        description="Train (or reuse) every model on one split and write a comparison report.",
    )
    p.add_argument("--data", default="synthetic", help="synthetic (default) | bandai | bvh:DIR")
    p.add_argument(
        "--models",
        default=",".join(ALL_MODELS),
        help=f"comma-separated subset of {','.join(ALL_MODELS)}",
    )
    p.add_argument(
        "--budget",
        default="quick",
        choices=list(BUDGETS),
        help="smoke: CI-sized; quick: the quick presets; cpu: the cpu presets (<= 60 min of "
        "training per model on 2 cores); full: the paper presets",
    )
    p.add_argument("--out", default="runs/bench", help="report folder")
    p.add_argument(
        "--test-data",
        default=None,
        help="score every table on these takes instead of the test split: bvh:DIR, "
        "bandai:DIR or a folder (e.g. a performer the models never saw)",
    )
    p.add_argument("--runs-dir", default="runs", help="where runs are found and trained")
    p.add_argument("--temperature", type=float, default=1.0, help="sampling temperature")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--performer-split",
        dest="performer_split",
        action="store_true",
        default=None,
        help="also train and score a split by performer (default: on for bandai)",
    )
    p.add_argument("--no-performer-split", dest="performer_split", action="store_false")
    p.add_argument("--retrain", action="store_true", help="train even if a finished run exists")
    p.add_argument("--no-gifs", dest="gifs", action="store_false", help="skip the GIFs")
    p.add_argument(
        "--estimate",
        action="store_true",
        help="only time a few training steps per model and print the projected "
        "training time of the budget on this machine (writes OUT/estimate.json)",
    )
    return p


def main(args: argparse.Namespace | Sequence[str] | None = None) -> int:
    """``motionflows bench``: ``args`` is a parsed Namespace (from the CLI) or an argv list."""
    if args is None or isinstance(args, list | tuple):
        args = build_parser().parse_args(list(args) if args is not None else None)
    ns = vars(args)
    data = ns.get("data") or "synthetic"
    models = ns.get("models") or ",".join(ALL_MODELS)
    budget = ns.get("budget") or "quick"
    out = ns.get("out") or "runs/bench"
    try:
        names = parse_models(models)
        if ns.get("estimate"):
            est = estimate_training(data, names, budget)
            Path(out).mkdir(parents=True, exist_ok=True)
            (Path(out) / "estimate.json").write_text(json.dumps(_jsonable(est), indent=2))
            for name, e in est["models"].items():
                sps = e["seconds_per_step"]
                per = f"{sps:.3f} s/step x {e['steps']} steps" if sps else e.get("note", "")
                print(f"{name:>10}: {per} = {e['projected_hours']:.2f} h")
            print(
                f"{'total':>10}: {est['total_hours']:.2f} h of training ({budget} budget, "
                f"{est['machine']['cpu']}, {est['machine']['cores']} cores)"
            )
            return 0
        run_benchmark(
            data=data,
            models=names,
            budget=budget,
            out=out,
            runs_dir=ns.get("runs_dir") or "runs",
            temperature=ns.get("temperature", 1.0) if ns.get("temperature") is not None else 1.0,
            seed=ns.get("seed") or 0,
            performer_split=ns.get("performer_split"),
            retrain=bool(ns.get("retrain", False)),
            gifs=ns.get("gifs", True) is not False,
            command=_command(data, names, budget, out)
            + (f" --test-data {ns['test_data']}" if ns.get("test_data") else "")
            + (
                f" --temperature {ns['temperature']:g}"
                if ns.get("temperature") not in (None, 1.0)
                else ""
            ),
            test_data=ns.get("test_data"),
        )
    except (RunError, ValueError, MotionDataError) as err:
        print(f"motionflows bench: error: {err}", file=sys.stderr)
        return 2
    print(f"report: {Path(out) / 'BENCHMARK.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
