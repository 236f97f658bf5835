"""What the bench trains: the registered models, the budgets, and the exact config of each.

The bench knows no model by name. Every experiment registered in the
``motionflows.experiments`` entry points (:func:`motionflows.runs.available_experiments`)
contributes the models of its optional ``BENCH_MODELS`` (bench name -> the ``Config`` fields
that select that model, e.g. the baselines' ``{"gaussian": {"model": "gaussian"}}``), else
one model named after the entry point. A budget names the preset every model starts from
(:data:`BUDGETS`), so each experiment declares its own ``smoke`` preset (a CI-sized model
and a few steps); the bench then replaces the preset's data section by its one
:class:`~motionflows.config.DataConfig`, so every model is validated and scored on identical
windows, keeping only the preset's training augmentation (:data:`TRAINING_AUGMENTATION`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NamedTuple

from motionflows.config import (
    SMOKE_DATA,
    DataConfig,
    apply_overrides,
    has_override_key,
    resolve_compute_dtype,
)
from motionflows.errors import RunError

BUDGETS: dict[str, str] = {"smoke": "smoke", "quick": "quick", "cpu": "cpu", "full": "paper"}
"""budget -> the experiment preset it starts from."""

BUDGET_NOTES = {
    "smoke": "each experiment's `smoke` preset: a CI-sized model trained for a few steps on "
    "a small synthetic set (numbers are not meaningful, only the pipeline is)",
    "quick": "each experiment's `quick` preset (minutes per model on a 2-core CPU)",
    "cpu": "each experiment's `cpu` preset (the best motion found for at most 60 minutes of "
    "training on 2 CPU cores; on Bandai data split by performer, so every table is on the "
    "performer the models never saw)",
    "full": "each experiment's `paper` preset (the papers' hyper-parameters)",
}


BUDGET_SIZES: dict[str, dict[str, int]] = {
    # windows scored for likelihood (test, and a train subset), windows sampled for motion
    # quality, samples drawn for diversity, frames per GIF, bootstrap resamples,
    # prefix lengths for per-frame NLL of causal models; frames sampled from each test take
    # shorter than a window (short_frames, default bench.short_takes.SHORT_FRAMES)
    "smoke": dict(eval_windows=32, train_windows=32, motion_windows=8, diversity=8,
                  gif_frames=12, bootstrap=200, speed_repeats=1, prefix_points=2,
                  short_frames=16),
    "quick": dict(eval_windows=512, train_windows=256, motion_windows=64, diversity=16,
                  gif_frames=80, bootstrap=1000, speed_repeats=3, prefix_points=10),
    "cpu": dict(eval_windows=100000, train_windows=512, motion_windows=256, diversity=32,
                gif_frames=80, bootstrap=1000, speed_repeats=3, prefix_points=10),
    "full": dict(eval_windows=100000, train_windows=1024, motion_windows=256, diversity=32,
                 gif_frames=80, bootstrap=2000, speed_repeats=3, prefix_points=20),
}  # fmt: skip

EVAL_CHUNK = 64
"""Windows per evaluation / sampling call (the last chunk is padded, so one compile each)."""


class BenchModel(NamedTuple):
    """One model of the bench: its registered experiment and the fields selecting it."""

    experiment: str
    fields: dict[str, Any]


def bench_models() -> dict[str, BenchModel]:
    """Every model the registered experiments offer, in entry-point order (then each
    experiment's ``BENCH_MODELS`` order): ``{model name: BenchModel}``."""
    from motionflows.runs import available_experiments, resolve_experiment

    models: dict[str, BenchModel] = {}
    for experiment in available_experiments():
        try:
            module = resolve_experiment(experiment)
        except (RunError, ImportError) as err:
            raise RunError(f"experiment {experiment!r} cannot be loaded ({err})") from err
        for name, fields in getattr(module, "BENCH_MODELS", {experiment: {}}).items():
            models[name] = BenchModel(experiment, dict(fields))
    return models


def all_models() -> tuple[str, ...]:
    """Names of every model the bench can run (:func:`bench_models`), in report order."""
    return tuple(bench_models())


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
    fields = parse_data(spec)
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
    """``"glow_fixed,moglow"`` or a sequence -> validated tuple of model names (None, ``""``
    or ``"all"``: every registered model)."""
    known = all_models()
    if models is None or models == "" or models == "all":
        return known
    names = models.split(",") if isinstance(models, str) else list(models)
    names = [n.strip() for n in names if n.strip()]
    unknown = [n for n in names if n not in known]
    if unknown:
        raise RunError(f"--models: unknown model(s) {unknown}; choose from {list(known)}")
    if not names:
        raise RunError(f"--models: give at least one of {list(known)}")
    return tuple(dict.fromkeys(names))


def _lookup(model: str) -> BenchModel:
    models = bench_models()
    if model not in models:
        raise RunError(f"unknown model {model!r}; choose from {list(models)}")
    return models[model]


def load_experiment(model: str):
    """The experiment module of bench model ``model`` (through the entry points)."""
    from motionflows.runs import resolve_experiment

    return resolve_experiment(_lookup(model).experiment)


def check_overrides(names: Sequence[str], budget: str, data: DataConfig, overrides) -> None:
    """RunError if one of the ``--set`` overrides names a field of none of the models (a
    typo would otherwise change nothing); bad values raise through :func:`bench_config`."""
    skipped = [set(bench_config(n, budget, data, None, overrides)[1]["overrides_skipped"])
               for n in names]  # fmt: skip
    unused = set(overrides).intersection(*skipped) if skipped else set()
    if unused:
        raise RunError(
            f"--set {' '.join(sorted(unused))}: no config of {', '.join(names)} has this key, "
            "or a bare name matches several fields (then give the dotted name, e.g. "
            "train.seed); the keys are the fields of each experiment's Config, as for "
            "`motionflows train --set`"
        )


AUGMENTATION_FIELDS: tuple[str, ...] = (
    "mirror",
    "reverse",
    "tempo",
    "tempo_replay",
    "foot_lock",
    "short_repeat",
)
"""The :class:`~motionflows.config.DataConfig` fields that augment the training takes only,
so a model may differ in them from the bench's data and still be validated and scored on
the same frames: each preset keeps its own, and ``motionflows bench --set`` may change them."""

TRAINING_AUGMENTATION: tuple[str, ...] = tuple(f"data.{k}" for k in AUGMENTATION_FIELDS)
"""The dotted names of :data:`AUGMENTATION_FIELDS`, as ``motionflows bench --set`` takes them."""

TRAINING_DATA_SETTABLE: tuple[str, ...] = (*TRAINING_AUGMENTATION, "data.train_fraction")
"""The data fields ``motionflows bench --set`` takes: they change the training split only
(its augmentation, and ``train_fraction``, the share of training takes a model sees), so the
model is still validated and scored on the bench's frames. A preset keeps its own
augmentation; every preset trains on all training takes unless ``--set`` says otherwise."""


def bench_config(
    model: str, budget: str, data: DataConfig, exp=None, overrides: Sequence[str] = ()
) -> tuple[Any, dict]:
    """The exact config the bench trains for ``model`` at ``budget`` on ``data``.

    The experiment's preset of the budget (:data:`BUDGETS`) with the model's selecting
    fields and the data section replaced by ``data`` (identical frames for every model)
    but for the preset's own training augmentation (:data:`TRAINING_AUGMENTATION`: the
    augmented takes only enter training, so a model trained with them is scored on the same
    frames in its own standardised units), then the ``key=value`` ``overrides``
    (``motionflows bench --set``) that name a field of this model's config; the others are
    listed in ``provenance["overrides_skipped"]``. Of the data fields only
    :data:`TRAINING_DATA_SETTABLE` may be set.
    Returns (config, provenance dict).
    """
    if budget not in BUDGETS:
        raise RunError(f"--budget {budget!r}: choose from {list(BUDGETS)}")
    entry = _lookup(model)
    exp = exp or load_experiment(model)
    preset = BUDGETS[budget]
    if preset not in exp.PRESETS:
        raise RunError(
            f"{exp.__name__} has no preset {preset!r} (has {list(exp.PRESETS)}); the "
            f"{budget} budget needs one"
        )
    own = exp.PRESETS[preset]
    augmentation = {k: getattr(own.data, k) for k in AUGMENTATION_FIELDS}
    try:
        config = dataclasses.replace(
            own, **entry.fields, data=dataclasses.replace(data, **augmentation)
        )
    except TypeError as err:
        raise RunError(f"{exp.__name__}.Config cannot select model {model!r}: {err}") from None
    for item in overrides:
        key = item.split("=", 1)[0].strip()
        if key.startswith("data.") and key not in TRAINING_DATA_SETTABLE:
            raise RunError(
                f"--set {item}: the bench gives every model the same data; choose them with "
                "--data and --test-data (of the data fields, --set takes only those of the "
                f"training split: {', '.join(TRAINING_DATA_SETTABLE)})"
            )
    applied = [item for item in overrides if has_override_key(config, item)]
    # "auto" precision resolved here: runs are found by the precision they were trained in
    config = resolve_compute_dtype(apply_overrides(config, applied))
    provenance = {
        "experiment": getattr(exp, "NAME", entry.experiment),
        "module": exp.__name__,
        "preset": preset,
        "overrides": {
            **entry.fields,
            "data": "the bench's data config with the preset's training augmentation",
        },
        "overrides_skipped": [item for item in overrides if item not in applied],
    }
    if applied:
        provenance["set"] = applied
    return config, provenance
