"""Experiment configuration: frozen dataclasses, JSON round trip and ``key=value`` overrides.

An experiment's ``Config`` is a frozen dataclass with two nested sections, ``data``
(:class:`DataConfig`) and ``train`` (:class:`TrainConfig`), plus its own model fields.
Overrides use dotted paths (``train.lr=1e-3``) or, when unambiguous, a bare field name
(``lr=1e-3``).
"""

from __future__ import annotations

import dataclasses
import json
import math
import types
import typing
from typing import Any

from motionflows.data.augment import TEMPO_REPLAYS
from motionflows.data.features import HOLDEN_ROOT_SIGMA_S, ROOT_SIGMA_S
from motionflows.data.pipeline import SHORT_TAKES

COMPUTE_DTYPES = ("auto", "float32", "bfloat16")
"""Values of the flows' ``compute_dtype`` field, the precision of their conditioner matmuls
(float32 accumulation either way). "auto", the default, is bfloat16 on an NVIDIA GPU with
bfloat16 tensor cores (compute capability 8.0 or more) and float32 elsewhere: on an H200
bfloat16 trained the paper-size MoGlow 1.17x and the fixed-length Glow 1.09x faster than
float32 at the same validation NLL, while on CPUs float32 is the exact, tested path
(docs/readme/speed.md, GPU)."""


def check_compute_dtype(value: str) -> None:
    """Raise ``ValueError`` unless ``value`` is one of :data:`COMPUTE_DTYPES`."""
    if value not in COMPUTE_DTYPES:
        raise ValueError(
            f"compute_dtype must be one of {', '.join(map(repr, COMPUTE_DTYPES))}, got {value!r}"
        )


def auto_compute_dtype() -> str:
    """What "auto" means on this machine: "bfloat16" on a GPU of compute capability 8.0 or
    more (bfloat16 tensor cores), "float32" on CPUs, older GPUs and other backends."""
    import jax

    if jax.default_backend() != "gpu":
        return "float32"
    capability = str(getattr(jax.devices()[0], "compute_capability", ""))
    major = capability.split(".")[0]
    return "bfloat16" if major.isdigit() and int(major) >= 8 else "float32"


def resolve_compute_dtype(config: Any) -> Any:
    """``config`` with ``compute_dtype="auto"`` replaced by :func:`auto_compute_dtype`; a
    config with an explicit dtype, or without the field, comes back unchanged. Training
    saves the resolved config, so a run reloads and resumes in the precision it was
    trained in on any machine, and the bench compares runs by the precision they use."""
    if getattr(config, "compute_dtype", None) != "auto":
        return config
    return dataclasses.replace(config, compute_dtype=auto_compute_dtype())


def matmul_dtype(value: str) -> str | None:
    """The models' ``compute_dtype`` argument for a config's value: None (plain float32
    matmuls) or "bfloat16"; "auto" is resolved for this machine first."""
    value = auto_compute_dtype() if value == "auto" else value
    return None if value == "float32" else value


@dataclasses.dataclass(frozen=True)
class DataConfig:
    """Which motion data to train on and how to cut it (see ``motionflows.data``)."""

    source: str = "synthetic"  # "synthetic", "bandai" or "bvh"
    path: str | None = None  # folder for "bandai" / "bvh"; None = the source's default
    skeleton: str = "bandai"  # skeleton mapping for "bvh"
    fps: float = 20.0
    window: int = 80  # frames per training window (4 s at 20 fps)
    hop: int = 10  # frames between window starts
    split_by: str = "take"  # "take" or "performer"
    mirror: bool = True  # augmentation of the training split
    reverse: bool = False  # time-reversal augmentation (changes the motion's physics)
    synthetic_clips: int = 120
    synthetic_seconds: float = 12.0
    seed: int = 0
    root_sigma_s: float = ROOT_SIGMA_S  # root smoothing, s (features.py; Holden's: 0.05)
    # tempo augmentation: every training take also played at 1/tempo and tempo times its
    # speed (data/augment.py; 1 = off); tempo_replay "slower" or "faster" keeps one of them
    tempo: float = 1.0
    tempo_replay: str = "both"
    # the training takes' planted feet held where they stand (data/augment.py, lock_clip:
    # the footskate clean-up of motionflows.foot_lock) before the other augmentations;
    # validation and test takes stay as recorded
    foot_lock: bool = False
    # keep only the takes of these styles, in every split (metadata "style"; None = all)
    styles: tuple[str, ...] | None = None
    # keep this share of each performer's, content's and style's training takes (nested
    # shares, for learning curves over data size; validation and test keep every take)
    train_fraction: float = 1.0
    # a take shorter than the window: "pad" it with its last pose frozen (valid False
    # there; training sees the frozen tail, scoring uses complete windows only) or "drop" it
    short: str = "pad"
    # each padded training window (a take shorter than the window: on Bandai, most runs)
    # enters the training split this many times; a frame of a longer take is in about
    # window / hop windows, a short take's in one (1 = as cut)
    short_repeat: int = 1

    def __post_init__(self):
        check_fields(self, DATA_LIMITS)
        if self.source not in ("synthetic", "bandai", "bvh"):
            raise ValueError(
                f"data.source must be 'synthetic', 'bandai' or 'bvh', got {self.source!r}"
            )
        if self.split_by not in ("take", "performer"):
            raise ValueError(f"data.split_by must be 'take' or 'performer', got {self.split_by!r}")
        if self.tempo_replay not in TEMPO_REPLAYS:
            raise ValueError(
                f"data.tempo_replay must be one of {list(TEMPO_REPLAYS)}, got {self.tempo_replay!r}"
            )
        if self.short not in SHORT_TAKES:
            raise ValueError(f"data.short must be 'pad' or 'drop', got {self.short!r}")

    def load(self):
        """Build the dataset this config describes (cached on disk by the data layer)."""
        from motionflows.data import load_dataset

        return load_dataset(
            self.source,
            path=self.path,
            skeleton=self.skeleton,
            fps=self.fps,
            window=self.window,
            hop=self.hop,
            split_by=self.split_by,
            mirror=self.mirror,
            reverse=self.reverse,
            n_clips=self.synthetic_clips,
            seconds=self.synthetic_seconds,
            seed=self.seed,
            root_sigma_s=self.root_sigma_s,
            tempo=self.tempo,
            tempo_replay=self.tempo_replay,
            styles=self.styles,
            train_fraction=self.train_fraction,
            short=self.short,
            short_repeat=self.short_repeat,
            foot_lock=self.foot_lock,
        )


SCHEDULES: tuple[str, ...] = ("constant", "cosine", "noam")
"""Learning-rate schedules of :class:`TrainConfig` (see ``training.learning_rate_schedule``)."""


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """The shared optimisation and bookkeeping settings of ``motionflows.training``."""

    steps: int = 1000
    batch_size: int = 32
    lr: float = 1e-3
    warmup_steps: int = 0
    schedule: str = "constant"  # "constant", "cosine" (after warm-up) or "noam" (MoGlow's)
    clip_value: float | None = None  # element-wise gradient clipping, applied first
    clip_norm: float | None = None  # then global-norm clipping
    weight_decay: float = 0.0  # "adam": L2 on the gradient (torch's); "adamw": decoupled
    eval_every: int = 200
    eval_batches: int = 8
    log_every: int = 10
    checkpoint_every: int = 500
    keep_checkpoints: int = 3
    max_nonfinite: int = 10  # consecutive non-finite steps before the run stops
    seed: int = 0
    optimizer: str = "adam"  # "adam" or "adamw"
    b1: float = 0.9
    b2: float = 0.999
    eps: float = 1e-8
    min_lr_ratio: float = 0.0  # cosine: final lr = lr * min_lr_ratio; noam: the floor
    val_batch_size: int | None = None  # None = batch_size
    # Polyak averaging: the debiased exponential average of the iterates (decay d,
    # optim.parameter_average); validation, the checkpoints' "params" (sampling, eval,
    # export) use it. None: the last iterate.
    ema_decay: float | None = None

    def __post_init__(self):
        check_fields(self, TRAIN_LIMITS)
        if self.schedule not in SCHEDULES:
            raise ValueError(
                f"train.schedule must be one of {', '.join(SCHEDULES)}, got {self.schedule!r}"
            )
        if self.optimizer not in ("adam", "adamw"):
            raise ValueError(f"train.optimizer must be 'adam' or 'adamw', got {self.optimizer!r}")


SMOKE_DATA: dict[str, Any] = dict(synthetic_clips=16, synthetic_seconds=6.0, window=32, hop=8)
"""Data fields of the experiments' ``smoke`` presets and the bench's smoke budget: a small
synthetic set and 1.6 s windows."""


def smoke_train(train: TrainConfig) -> TrainConfig:
    """``train`` cut to a ``smoke`` preset's CI-sized run: 30 steps of batch 8, one
    evaluation (one batch) and one kept checkpoint at the end."""
    return dataclasses.replace(
        train, steps=30, batch_size=8, eval_every=30, eval_batches=1, log_every=5,
        checkpoint_every=30, keep_checkpoints=1,
    )  # fmt: skip


# field -> (lowest, highest, lowest allowed?, highest allowed?); None values are left to the
# field's "X | None" type. Every number must also be finite.
_Limit = tuple[float, float, bool, bool]
INF = math.inf
DATA_LIMITS: dict[str, _Limit] = {
    "fps": (0.0, 1000.0, False, True),
    "window": (2, INF, True, True),
    "hop": (1, INF, True, True),
    "synthetic_clips": (1, INF, True, True),
    "synthetic_seconds": (0.0, 3600.0, False, True),
    "root_sigma_s": (0.0, 60.0, True, True),
    "tempo": (0.1, 10.0, True, True),
    "train_fraction": (0.0, 1.0, False, True),
    "short_repeat": (1, INF, True, True),
}
SEED_RANGE = (-(2**63), 2**63 - 1)
"""The seeds ``jax.random.key`` takes (a 64-bit integer), both ends included."""
TRAIN_LIMITS: dict[str, _Limit] = {
    "steps": (0, INF, True, True),
    "batch_size": (1, INF, True, True),
    "lr": (0.0, 1e3, False, True),
    "warmup_steps": (0, INF, True, True),
    "clip_value": (0.0, INF, False, False),
    "clip_norm": (0.0, INF, False, False),
    "weight_decay": (0.0, 1e3, True, True),
    "eval_every": (1, INF, True, True),
    "eval_batches": (1, INF, True, True),
    "log_every": (1, INF, True, True),
    "checkpoint_every": (1, INF, True, True),
    "keep_checkpoints": (1, INF, True, True),
    "max_nonfinite": (1, INF, True, True),
    "b1": (0.0, 1.0, True, False),
    "b2": (0.0, 1.0, True, False),
    "eps": (0.0, 1.0, False, True),
    "min_lr_ratio": (0.0, 1.0, True, True),
    "val_batch_size": (1, INF, True, True),
    "ema_decay": (0.0, 1.0, False, False),
    "seed": (*SEED_RANGE, True, True),
}


def check_fields(config: Any, limits: dict[str, _Limit]) -> None:
    """Raise ``ValueError`` naming the first field of ``config`` outside its limits
    (``{field: (lowest, highest, lowest allowed?, highest allowed?)}``; an int lowest means an
    integer field; None values pass). The experiments' configs check their model fields
    with it in ``__post_init__``, as :class:`DataConfig` and :class:`TrainConfig` do."""
    section = {"DataConfig": "data", "TrainConfig": "train"}.get(type(config).__name__, "")
    for name, (lo, hi, lo_ok, hi_ok) in limits.items():
        value = getattr(config, name)
        if value is None:
            continue
        path = f"{section}.{name}" if section else name
        integer = isinstance(lo, int)
        kind = "an integer" if integer else "a finite number"
        if isinstance(value, bool) or not isinstance(value, int if integer else int | float):
            raise ValueError(f"{path} must be {kind}, got {value!r}")
        above = value > lo if not lo_ok else value >= lo
        below = value < hi if not hi_ok else value <= hi
        if not (math.isfinite(value) and above and below):
            low = f">= {lo:g}" if lo_ok else f"> {lo:g}"
            high = "" if math.isinf(hi) else (f" and <= {hi:g}" if hi_ok else f" and < {hi:g}")
            raise ValueError(f"{path} must be {kind} {low}{high}, got {value!r}")


@dataclasses.dataclass(frozen=True)
class Scope:
    """What one ``evaluate()`` entry scores: a description, and whether it is a bound."""

    description: str
    bound: bool = False
    skip: int | str = 0
    """Frames at the start of the window the score leaves out (they are conditioned on, not
    scored): an int, or the name of a config field holding it (e.g. ``"tau"`` for MoGlow's
    official scope of frames tau..T-1). The scored frames per window are ``T - skip``."""

    def scored_frames(self, window: int, config: Any = None) -> int:
        """Number of frames this score covers in a window of ``window`` frames."""
        skip = self.skip
        if isinstance(skip, str):
            if config is None or not hasattr(config, skip):
                raise ValueError(
                    f"Scope {self.description!r} skips the config field {skip!r}, "
                    "but no config with that field was given"
                )
            skip = int(getattr(config, skip))
        frames = int(window) - int(skip)
        if frames <= 0:
            raise ValueError(f"Scope {self.description!r} scores {frames} frames of {window}")
        return frames


def to_dict(config: Any) -> dict:
    """A JSON-able dict of a (nested) config dataclass; tuples become lists."""
    return json.loads(json.dumps(dataclasses.asdict(config)))


def from_dict(cls: type, values: dict, _prefix: str = "") -> Any:
    """Rebuild ``cls`` from :func:`to_dict` output. Unknown keys and values of the wrong
    type raise ``ValueError`` naming the field."""
    if not isinstance(values, dict):
        raise ValueError(f"{_prefix or cls.__name__} must be a JSON object, got {values!r}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = set(values) - names
    if unknown:
        raise ValueError(
            f"{cls.__name__} has no field(s) {sorted(unknown)}; valid fields: {sorted(names)}"
        )
    kwargs = {}
    for name, value in values.items():
        kind, path = hints[name], f"{_prefix}{name}"
        if dataclasses.is_dataclass(kind):
            kwargs[name] = from_dict(kind, value, path + ".")
        else:
            kwargs[name] = _typed(value, kind, path)
    return cls(**kwargs)


def _typed(value: Any, kind: Any, path: str) -> Any:
    """``value`` (from JSON) checked against the field type ``kind``; lists become tuples."""
    origin, args = typing.get_origin(kind), typing.get_args(kind)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        non_none = [a for a in args if a is not type(None)]
        return _typed(value, non_none[0], path) if len(non_none) == 1 else value
    ok = True
    if kind is bool:
        ok = isinstance(value, bool)
    elif kind is int:
        ok = isinstance(value, int) and not isinstance(value, bool)
    elif kind is float:
        ok = isinstance(value, int | float) and not isinstance(value, bool)
        value = float(value) if ok else value
    elif kind is str:
        ok = isinstance(value, str)
    elif origin in (tuple, list):
        if not isinstance(value, list | tuple):
            ok = False
        else:
            inner = args[0] if len(args) == 2 and args[1] is Ellipsis else None
            value = tuple(_typed(v, inner, path) if inner else v for v in value)
    elif isinstance(value, list):
        value = tuple(value)
    if not ok:
        name = getattr(kind, "__name__", str(kind))
        raise ValueError(f"config field {path} must be {name}, got {value!r}")
    return value


def _field_paths(cls: type, prefix: str = "") -> dict[str, tuple[str, type]]:
    """Map dotted path -> (path, type) for every leaf field of a config class."""
    hints = typing.get_type_hints(cls)
    paths: dict[str, tuple[str, type]] = {}
    for f in dataclasses.fields(cls):
        kind = hints[f.name]
        path = f"{prefix}{f.name}"
        if dataclasses.is_dataclass(kind):
            paths.update(_field_paths(kind, path + "."))
        else:
            paths[path] = (path, kind)
    return paths


def _parse(text: str, kind: Any, key: str) -> Any:
    """Parse an override value with the field's type; JSON for containers.

    ``int``/``float``/``str``/``bool`` fields take plain text; ``X | None`` also takes
    ``none``/``null``; ``tuple[...]`` fields take a JSON list (``[1,10]``) or a bare
    comma-separated list (``1,10``), each element converted to the declared element type.
    """
    args = typing.get_args(kind)
    origin = typing.get_origin(kind)
    if origin in (typing.Union, types.UnionType):
        if type(None) in args and text.lower() in ("none", "null"):
            return None
        non_none = [a for a in args if a is not type(None)]
        if len(non_none) == 1:
            return _parse(text, non_none[0], key)
        kind, origin, args = Any, None, ()
    try:
        if kind is bool:
            if text.lower() in ("1", "true", "yes", "on"):
                return True
            if text.lower() in ("0", "false", "no", "off"):
                return False
            raise ValueError(text)
        if kind in (int, float, str):
            return kind(text)
        if origin in (tuple, list):
            stripped = text.strip()
            if stripped.startswith("["):
                items = json.loads(stripped)
            else:
                items = [part.strip() for part in stripped.split(",") if part.strip()]
            if not isinstance(items, list):
                raise ValueError(text)
            if len(args) == 2 and args[1] is Ellipsis:
                element_types = [args[0]] * len(items)
            elif args:
                if len(args) != len(items):
                    raise ValueError(f"expected {len(args)} values, got {len(items)}")
                element_types = list(args)
            else:
                element_types = [Any] * len(items)
            return tuple(
                item if t is Any else _parse(str(item), t, key)
                for item, t in zip(items, element_types, strict=True)
            )
        value = json.loads(text)
        return tuple(value) if isinstance(value, list) else value
    except ValueError as err:
        raise ValueError(f"--set {key}={text}: cannot read {text!r} as {_kind_name(kind)}") from err


_KIND_NAMES = {
    int: "a whole number (int)",
    float: "a number (float)",
    bool: "true or false (bool)",
    str: "text (str)",
}


def _kind_name(kind) -> str:
    """A config field's type as a person reads it: ``int`` -> "a whole number (int)",
    ``tuple[int, ...]`` -> "tuple[int, ...]" (not "<class 'int'>")."""
    if kind in _KIND_NAMES:
        return _KIND_NAMES[kind]
    return kind.__name__ if isinstance(kind, type) else str(kind)


def _matching_fields(paths: dict[str, tuple[str, type]], key: str) -> list[str]:
    """The dotted paths an override ``key`` names: itself if it is one, else every field
    whose bare name it is (one match applies, several are ambiguous, none is unknown)."""
    if key in paths:
        return [key]
    return [p for p in paths if p.rsplit(".", 1)[-1] == key]


def has_override_key(config: Any, item: str) -> bool:
    """Whether the ``key`` of ``key=value`` names one field of ``config`` (dotted path or a
    unique bare name), i.e. whether :func:`apply_overrides` can apply it."""
    key = item.split("=", 1)[0].strip()
    return len(_matching_fields(_field_paths(type(config)), key)) == 1


def apply_overrides(config: Any, overrides: list[str] | tuple[str, ...]) -> Any:
    """Return ``config`` with ``key=value`` overrides applied (dotted or unique bare names;
    the last of a repeated key wins). The result is built and validated once, with every
    override in place, so fields that must change together can be given in any order."""
    paths = _field_paths(type(config))
    changes: dict[tuple[str, ...], Any] = {}
    for item in overrides:
        if "=" not in item:
            raise ValueError(f"--set expects key=value, got {item!r}")
        key, text = item.split("=", 1)
        key = key.strip()
        matches = _matching_fields(paths, key)
        if len(matches) != 1:
            hint = f"ambiguous: {matches}" if matches else f"valid keys: {sorted(paths)}"
            raise ValueError(f"--set {key}: unknown config key ({hint})")
        path, kind = paths[matches[0]]
        changes[tuple(path.split("."))] = _parse(text.strip(), kind, key)
    return _replace_paths(config, changes)


def _replace_paths(config: Any, changes: dict[tuple[str, ...], Any]) -> Any:
    """``config`` with each (field path -> value) of ``changes`` set: one
    ``dataclasses.replace`` per dataclass, the nested ones first."""
    direct = {path[0]: value for path, value in changes.items() if len(path) == 1}
    nested: dict[str, dict[tuple[str, ...], Any]] = {}
    for path, value in changes.items():
        if len(path) > 1:
            nested.setdefault(path[0], {})[path[1:]] = value
    for name, inner in nested.items():
        direct[name] = _replace_paths(getattr(config, name), inner)
    return dataclasses.replace(config, **direct) if direct else config


def save_config(
    path: Any,
    *,
    experiment: str,
    preset: str | None,
    config: Any,
    devices: int | None = None,
    device_counts: Any = (),
) -> None:
    """Write ``config.json``: ``{"experiment", "preset", "config"}`` (see :func:`load_config`),
    and, when ``devices`` is given, ``"devices"``, the number of devices the run trains
    data-parallel on now, and ``"device_counts"``, every count it has trained on (``devices``
    with ``device_counts``, the earlier segments' counts of a resumed run), sorted."""
    from pathlib import Path

    payload = {"experiment": experiment, "preset": preset, "config": to_dict(config)}
    if devices is not None:
        payload["devices"] = int(devices)
        payload["device_counts"] = sorted({int(devices), *map(int, device_counts)})
    Path(path).write_text(json.dumps(payload, indent=2) + "\n")


def saved_device_counts(payload: dict) -> set[int]:
    """Every device count a run's ``config.json`` payload says it trained on: its
    ``"device_counts"``, else its ``"devices"`` (a run saved before the history was kept),
    else 1 (a run saved before the count was recorded)."""
    if "device_counts" in payload:
        return {int(n) for n in payload["device_counts"]}
    return {int(payload.get("devices", 1))}


def read_config_json(path: Any) -> dict:
    """The payload of a run's ``config.json``, checked for its ``experiment`` and ``config``
    keys; a missing, unreadable or damaged file raises ``RunError`` naming it."""
    from pathlib import Path

    from motionflows.errors import RunError

    path = Path(path)
    fix = "restore it from a backup or train the run again"
    try:
        payload = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise RunError(f"{path}: not found; {fix}") from None
    except (OSError, UnicodeDecodeError) as err:
        raise RunError(f"{path}: cannot read it ({err}); {fix}") from None
    except json.JSONDecodeError as err:
        raise RunError(
            f"{path}:{err.lineno}: not valid JSON ({err.msg}; the file may be truncated); {fix}"
        ) from None
    if not isinstance(payload, dict):
        raise RunError(f"{path}: expected a JSON object with 'experiment' and 'config'; {fix}")
    for key, kind in (("experiment", str), ("config", dict)):
        if not isinstance(payload.get(key), kind):
            what = "is missing" if key not in payload else f"is {payload[key]!r}"
            raise RunError(f"{path}: the field {key!r} {what}; {fix}")
    return payload


def _saved_before_root_sigma(values: dict) -> dict:
    """A saved config whose ``data`` has no ``root_sigma_s`` was trained on the features of
    that time, Holden's root smoothing: it keeps them (a copy with the field set)."""
    data = values.get("data")
    if isinstance(data, dict) and "root_sigma_s" not in data:
        return {**values, "data": {**data, "root_sigma_s": HOLDEN_ROOT_SIGMA_S}}
    return values


def config_from_json(path: Any, cls: type, payload: dict | None = None) -> Any:
    """``cls`` rebuilt from the ``config`` of a ``config.json``; a bad field raises
    ``RunError`` naming the file and the field."""
    from motionflows.errors import RunError

    payload = read_config_json(path) if payload is None else payload
    try:
        return from_dict(cls, _saved_before_root_sigma(payload["config"]))
    except (ValueError, TypeError) as err:
        raise RunError(f"{path}: {err}; fix the field or train the run again") from None


def load_config(path: Any, cls: type) -> tuple[str, str | None, Any]:
    """Read a ``config.json`` written by :func:`save_config` -> (experiment, preset, config)."""
    payload = read_config_json(path)
    return payload["experiment"], payload.get("preset"), config_from_json(path, cls, payload)
