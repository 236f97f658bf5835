"""``motionflows bench --estimate``: project a budget's training time on this machine."""

from __future__ import annotations

import dataclasses
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from motionflows.bench.budgets import (
    bench_config,
    check_overrides,
    load_experiment,
    parse_data_spec,
    parse_models,
)
from motionflows.bench.reuse import log
from motionflows.bench.speed import describe_machine


def estimate_training(
    data: str = "synthetic",
    models: str | Sequence[str] | None = None,
    budget: str = "full",
    *,
    probe_steps: int = 4,
    progress=print,
    overrides: Sequence[str] = (),
) -> dict:
    """Project the training time of a budget on this machine without running it.

    For each model, trains ``probe_steps`` steps of the exact config the bench would train
    (in a temporary folder, through ``motionflows.training.train``) and projects

        hours = (steps x seconds per step + validations x seconds per validation) / 3600

    with the median steady-state seconds per step (the first step, which compiles, is
    dropped), ``validations`` = the passes the run makes (every ``train.eval_every`` steps
    and at the last), and the wall time of the probe's second validation pass of the
    config's ``train.eval_batches`` (the first compiles). Checkpoint writes are not counted.
    Returns ``{"models": {model: {"seconds_per_step", "steps", "validation_seconds",
    "validations", "projected_hours", ...}}, "total_hours": ...}``.
    """
    data_cfg = parse_data_spec(data, budget)
    names = parse_models(models)
    check_overrides(names, budget, data_cfg, overrides)  # a typo'd key is refused, as in bench
    dataset = data_cfg.load()
    out: dict[str, Any] = {"budget": budget, "data": data, "machine": describe_machine()}
    out["models"] = {}
    for name in names:
        exp = load_experiment(name)
        config, prov = bench_config(name, budget, data_cfg, exp, overrides)
        entry = _probe(exp, config, prov["preset"], dataset, probe_steps, progress, name)
        out["models"][name] = entry
        log(progress, f"{name}: {entry}")
    out["total_hours"] = sum(e["projected_hours"] for e in out["models"].values())
    return out


def _probe(exp, config, preset: str, dataset, probe_steps: int, progress, name: str) -> dict:
    """Time a few training steps of ``config`` (all of a closed-form fit)."""
    from motionflows import training
    from motionflows.runs import read_metrics

    steps = int(config.train.steps)
    probe_steps = max(probe_steps, 2)  # two validations: half-way (compiles) and at the end
    probe = dataclasses.replace(
        config,
        train=dataclasses.replace(
            config.train,
            steps=probe_steps if steps > 0 else 0,
            log_every=1,
            eval_every=probe_steps // 2,
            checkpoint_every=10**9,
        ),
    )
    log(progress, f"{name}: timing {probe.train.steps} steps of the {preset} config")
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        training.train(
            exp, probe, run_dir=Path(tmp) / "probe", preset=preset, dataset=dataset, progress=False
        )
        wall = time.perf_counter() - t0
        rows = read_metrics(Path(tmp) / "probe")
    if steps == 0:
        return {
            "steps": 0,
            "seconds_per_step": None,
            "projected_hours": wall / 3600,
            "note": "closed-form fit (timed in full)",
        }
    rates = [r["steps_per_s"] for r in rows if isinstance(r.get("steps_per_s"), int | float)]
    sec = 1.0 / float(np.median(rates[1:] or rates))
    val_sec = [r["val_seconds"] for r in rows if "val_seconds" in r][-1]
    validations = -(-steps // int(config.train.eval_every))  # ceil: the last step validates
    return {
        "steps": steps,
        "seconds_per_step": sec,
        "validation_seconds": val_sec,
        "validations": validations,
        "batch_size": int(config.train.batch_size),
        "projected_hours": (sec * steps + validations * val_sec) / 3600,
        "probe_wall_s": wall,
    }
