"""Experiment configuration: frozen dataclasses, JSON round trip and ``key=value`` overrides.

An experiment's ``Config`` is a frozen dataclass with two nested sections, ``data``
(:class:`DataConfig`) and ``train`` (:class:`TrainConfig`), plus its own model fields.
Overrides use dotted paths (``train.lr=1e-3``) or, when unambiguous, a bare field name
(``lr=1e-3``).
"""

from __future__ import annotations

import dataclasses
import json
import types
import typing
from typing import Any


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
        )


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """The shared optimisation and bookkeeping settings of ``motionflows.training``."""

    steps: int = 1000
    batch_size: int = 32
    lr: float = 1e-3
    warmup_steps: int = 0
    schedule: str = "constant"  # "constant" or "cosine" (after warm-up)
    clip_value: float | None = None  # element-wise gradient clipping, applied first
    clip_norm: float | None = None  # then global-norm clipping
    weight_decay: float = 0.0
    eval_every: int = 200
    eval_batches: int = 8
    log_every: int = 10
    checkpoint_every: int = 500
    keep_checkpoints: int = 3
    max_nonfinite: int = 10  # consecutive non-finite steps before the run stops
    seed: int = 0
    optimizer: str = "adam"  # "adam" or "adamw" (weight_decay applies to "adamw")
    b1: float = 0.9
    b2: float = 0.999
    eps: float = 1e-8
    min_lr_ratio: float = 0.0  # cosine schedule: final lr = lr * min_lr_ratio
    val_batch_size: int | None = None  # None = batch_size


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


def from_dict(cls: type, values: dict) -> Any:
    """Rebuild ``cls`` from :func:`to_dict` output. Unknown keys raise ``ValueError``."""
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = set(values) - names
    if unknown:
        raise ValueError(
            f"{cls.__name__} has no field(s) {sorted(unknown)}; valid fields: {sorted(names)}"
        )
    kwargs = {}
    for name, value in values.items():
        kind = hints[name]
        if dataclasses.is_dataclass(kind) and isinstance(value, dict):
            value = from_dict(kind, value)
        elif isinstance(value, list):
            value = tuple(value)
        kwargs[name] = value
    return cls(**kwargs)


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
        raise ValueError(f"--set {key}={text}: cannot read {text!r} as {kind}") from err


def apply_overrides(config: Any, overrides: list[str] | tuple[str, ...]) -> Any:
    """Return ``config`` with ``key=value`` overrides applied (dotted or unique bare names)."""
    paths = _field_paths(type(config))
    for item in overrides:
        if "=" not in item:
            raise ValueError(f"--set expects key=value, got {item!r}")
        key, text = item.split("=", 1)
        key = key.strip()
        if key in paths:
            path, kind = paths[key]
        else:
            matches = [p for p in paths if p.rsplit(".", 1)[-1] == key]
            if len(matches) != 1:
                hint = f"ambiguous: {matches}" if matches else f"valid keys: {sorted(paths)}"
                raise ValueError(f"--set {key}: unknown config key ({hint})")
            path, kind = paths[matches[0]]
        config = _replace_path(config, path.split("."), _parse(text.strip(), kind, key))
    return config


def _replace_path(config: Any, parts: list[str], value: Any) -> Any:
    if len(parts) == 1:
        return dataclasses.replace(config, **{parts[0]: value})
    inner = getattr(config, parts[0])
    return dataclasses.replace(config, **{parts[0]: _replace_path(inner, parts[1:], value)})


def save_config(path: Any, *, experiment: str, preset: str | None, config: Any) -> None:
    """Write ``config.json``: ``{"experiment", "preset", "config"}`` (see :func:`load_config`)."""
    from pathlib import Path

    payload = {"experiment": experiment, "preset": preset, "config": to_dict(config)}
    Path(path).write_text(json.dumps(payload, indent=2) + "\n")


def load_config(path: Any, cls: type) -> tuple[str, str | None, Any]:
    """Read a ``config.json`` written by :func:`save_config` -> (experiment, preset, config)."""
    from pathlib import Path

    payload = json.loads(Path(path).read_text())
    return payload["experiment"], payload.get("preset"), from_dict(cls, payload["config"])
