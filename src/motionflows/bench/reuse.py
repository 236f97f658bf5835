"""The bench's runs: reuse a finished run whose saved config equals the one it would train,
else train it (through :func:`motionflows.training.train`) under ``runs/<experiment>/``."""

from __future__ import annotations

import functools
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

from motionflows.config import (
    DataConfig,
    config_from_json,
    read_config_json,
    saved_device_counts,
    to_dict,
)
from motionflows.errors import RunError
from motionflows.runs import MetricsWarning, read_metrics


def log(progress, msg: str) -> None:
    """One time-stamped progress line through ``progress`` (None: silent)."""
    if progress:
        progress(f"[bench {time.strftime('%H:%M:%S')}] {msg}")


def _rows(run_dir: Path) -> list[dict]:
    """``metrics.jsonl`` rows; damaged lines are skipped silently here (``motionflows
    runs`` reports them)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", MetricsWarning)
        return read_metrics(run_dir)


def run_finished(run_dir: Path, steps: int) -> bool:
    """Whether ``run_dir`` completed: its last ``status`` row is ``finished`` at step >=
    ``steps``, or ``fitted`` (closed-form baselines)."""
    status = [r for r in _rows(run_dir) if "status" in r]
    if not status:
        return False
    last = status[-1]
    if last["status"] == "fitted":
        return True
    return last["status"] == "finished" and int(last.get("step") or 0) >= steps


def _without(config: dict | None, fields: tuple[str, ...]) -> dict | None:
    return None if config is None else {k: v for k, v in config.items() if k not in fields}


def find_run(
    runs_dir: str | Path,
    experiment: str,
    config: Any,
    *,
    sampling_fields: tuple[str, ...] = (),
    devices: int | None = None,
    standardizer: Callable[[], Any] | None = None,
) -> Path | None:
    """The newest finished run under ``runs_dir/<experiment>/`` whose saved config equals
    ``config`` (same data, model and training settings) but for ``sampling_fields`` (the
    experiment's ``SAMPLING_FIELDS``: fields that change how a trained model samples, not
    how it trains), else None. With ``devices``, only a run trained data-parallel on that
    many devices in every segment (its ``config.json``'s ``"device_counts"``;
    :func:`motionflows.config.saved_device_counts`): another count sums each batch in
    another order, so a run trained on it, even for part of its steps after a resume, is
    another training, as another seed would be. With ``standardizer`` (called once, when a run
    matches the config: the standardiser of the data ``config`` trains on, loaded now),
    only a run whose ``standardizer.json`` equals it: the same config on a folder whose
    takes changed is another training set."""
    base = Path(runs_dir) / experiment
    if not base.is_dir():
        return None
    want, steps = _without(to_dict(config), sampling_fields), int(config.train.steps)
    hits = []
    for path in base.glob("*/config.json"):
        try:
            saved = read_config_json(path)
            if saved.get("experiment", experiment) != experiment:
                continue
            # rebuilt through the config class: a field added since the run was saved
            # takes its default (the behaviour the run was trained with)
            saved_config = to_dict(config_from_json(path, type(config), saved))
        except RunError:
            continue
        if _without(saved_config, sampling_fields) != want:
            continue
        if devices is not None and saved_device_counts(saved) != {devices}:
            continue
        if run_finished(path.parent, steps):
            hits.append(path.parent)
    if standardizer is not None and hits:
        from motionflows.run import standardizer_changes

        now = standardizer()

        def same_data(run_dir: Path) -> bool:
            try:
                return not standardizer_changes(run_dir, now)
            except RunError:  # no readable standardizer.json: cannot be scored either
                return False

        hits = [run for run in hits if same_data(run)]
    return max(hits, key=lambda p: p.stat().st_mtime) if hits else None


def sampling_fields_of(exp) -> tuple[str, ...]:
    """The experiment's ``SAMPLING_FIELDS`` (config fields that change only sampling)."""
    return tuple(getattr(exp, "SAMPLING_FIELDS", ()))


def data_tag(data: DataConfig) -> str:
    """Short name of a data config in bench run names (``synthetic``, ``bvh-DIR``, ...)."""
    tag = data.source if data.source != "bvh" else "bvh-" + Path(str(data.path)).name
    return tag if data.split_by == "take" else f"{tag}-{data.split_by}"


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
    training_bars: bool = True,
) -> tuple[Path, bool, float]:
    """(run_dir, reused, training seconds): reuse a finished identical run or train one;
    ``training_bars=False`` trains without the progress bar (``progress`` lines stay)."""
    experiment = provenance["experiment"]

    @functools.cache
    def training_data():  # loaded once, and only when a reuse check or a training needs it
        return config.data.load() if dataset is None else dataset

    if not retrain:
        import jax

        found = find_run(
            runs_dir,
            experiment,
            config,
            sampling_fields=sampling_fields_of(exp),
            devices=jax.device_count(),
            standardizer=lambda: training_data().standardizer,
        )
        if found is not None:
            log(progress, f"{model_name}: reusing finished run {found}")
            return found, True, 0.0
    name = f"bench-{model_name}-{budget}-{data_tag}-{time.strftime('%Y%m%d-%H%M%S')}"
    run_dir = Path(runs_dir) / experiment / name
    log(
        progress,
        f"{model_name}: training {provenance['preset']} preset "
        f"({config.train.steps} steps) -> {run_dir}",
    )
    t0 = time.perf_counter()
    dataset = training_data()
    log(progress, f"{model_name}: data: {dataset.summary()}")
    bars = progress if training_bars else None
    train_run(exp, config, run_dir, preset=provenance["preset"], progress=bars, dataset=dataset)
    return run_dir, False, time.perf_counter() - t0


def train_run(exp, config, run_dir: Path, *, preset: str, progress, dataset=None) -> None:
    """Train through ``motionflows.training.train``; RunError unless it finished."""
    from motionflows import training

    result = training.train(
        exp, config, run_dir=run_dir, preset=preset, progress=bool(progress), dataset=dataset
    )
    if result.status not in ("finished", "fitted"):
        raise RunError(
            f"training {run_dir} ended with status {result.status!r}; see its metrics.jsonl"
        )


def fit_seconds(run_dir: Path) -> float | None:
    """Seconds of a closed-form fit (``fit_seconds`` in ``metrics.jsonl``), else None."""
    values = [r["fit_seconds"] for r in _rows(run_dir) if _number(r.get("fit_seconds"))]
    return float(values[0]) if values else None


def train_speed(run_dir: Path) -> float | None:
    """Median training frames/s logged in ``metrics.jsonl`` (the first logged record is
    dropped when there are more than two: it includes compilation)."""
    import numpy as np

    values = [float(r["frames_per_s"]) for r in _rows(run_dir) if _number(r.get("frames_per_s"))]
    values = [v for v in values if v > 0]
    if len(values) > 2:
        values = values[1:]
    return float(np.median(values)) if values else None


def _number(x: Any) -> bool:
    import math

    return isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)
