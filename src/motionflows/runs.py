"""Run directories, experiment lookup, metrics files, progress bar and loss plot.

A run lives in ``runs/<experiment>/<run-name>/`` with ``config.json``,
``standardizer.json``, ``metrics.jsonl``, ``checkpoints/``, ``samples/``, ``loss.png`` and
``eval_<split>.json``.
"""

from __future__ import annotations

import inspect
import json
import math
import sys
import time
import warnings
from pathlib import Path
from typing import Any, TextIO

from motionflows.errors import RunError

REQUIRED = ("NAME", "Config", "PRESETS", "build", "loss", "evaluate", "SCOPES", "sample")


ENTRY_POINT_GROUP = "motionflows.experiments"
"""Entry-point group through which experiment modules register (``pyproject.toml``)."""


def _entry_points() -> dict:
    from importlib.metadata import entry_points

    return {ep.name: ep for ep in entry_points(group=ENTRY_POINT_GROUP)}


def available_experiments() -> list[str]:
    """Names of the experiments registered in the ``motionflows.experiments`` entry points."""
    return sorted(_entry_points())


def _unknown(name: Any) -> RunError:
    names = available_experiments()
    hint = (
        f"available: {', '.join(names)}"
        if names
        else "none is registered: install motionflows with `pip install -e .` from its checkout"
    )
    return RunError(f"unknown experiment {name!r}; {hint}")


def resolve_experiment(name: str):
    """The experiment module registered as ``name`` (a module object passes through).

    Experiments are found through the ``motionflows.experiments`` entry points only, never
    by importing from a path or the working directory; a module already imported as
    ``experiments.<name>`` (tests, notebooks) is used as it is.
    """
    if not isinstance(name, str):
        return name
    module = sys.modules.get(f"experiments.{name}") if name.isidentifier() else None
    if module is None:
        ep = _entry_points().get(name)
        if ep is None:
            raise _unknown(name)
        module = ep.load()
    missing = [a for a in REQUIRED if not hasattr(module, a)]
    if missing:
        raise RunError(
            f"experiment {name!r} ({module.__name__}) lacks {missing} (see docs/ARCHITECTURE.md)"
        )
    return module


def _control_before_key(sample) -> bool:
    """Whether an experiment's ``sample`` is written in the old order ``(model, control,
    key)`` (its parameters are named so), not ``(model, key, control)``."""
    try:
        names = list(inspect.signature(sample).parameters)
    except (TypeError, ValueError):
        return False
    return {"control", "key"} <= set(names) and names.index("control") < names.index("key")


def experiment_sample(module, model, key, control, **options):
    """``module.sample(model, key, control, **options)``: how the library calls an
    experiment's sampler. An experiment written against the old contract ``sample(model,
    control, key)`` (its parameters named so) is called in its own order, with a
    ``DeprecationWarning`` asking it to move to ``(model, key, control)``."""
    if _control_before_key(module.sample):
        warnings.warn(
            f"{module.__name__}.sample(model, control, key): this argument order is "
            "deprecated, define sample(model, key, control, ...) (the order of "
            "model.sample(key, control))",
            DeprecationWarning,
            stacklevel=2,
        )
        return module.sample(model, control, key, **options)
    return module.sample(model, key, control, **options)


def window_scope_evaluate(module):
    """An ``evaluate``-shaped function ``(model, batch, key) -> {"window": (B,)}`` scoring the
    ``window`` scope alone through the experiment's ``window_log_prob`` (jitted), or None
    when it has none. For windows its full ``evaluate`` cannot take (MoGlow's ``official``
    scopes need more than tau frames) and to skip scopes nobody reads."""
    scorer = getattr(module, "window_log_prob", None)
    if scorer is None:
        return None
    import jax

    jitted = jax.jit(scorer)

    def evaluate(model, batch, key):
        del key
        return {"window": jitted(model, batch["pose"], batch["control"])}

    return evaluate


def fixed_length(module) -> bool:
    """Whether an experiment samples only its training window (``FIXED_LENGTH = True``)."""
    return bool(getattr(module, "FIXED_LENGTH", False))


def warn_if_not_window(module, config, frames: int, where: str, *, stacklevel: int = 3) -> None:
    """Warn (``UserWarning``) when a fixed-length experiment (``FIXED_LENGTH = True``: the
    Glow) is asked for ``frames`` other than its training window: its convolutions run on
    any multiple of 2**L frames, but a length it never saw is outside what it learnt.
    ``stacklevel`` as :func:`warnings.warn`'s, counted from this function (3: the line that
    called its caller)."""
    window = int(config.data.window)
    if fixed_length(module) and int(frames) != window:
        fps = float(config.data.fps)
        warnings.warn(
            f"{where}: {module.NAME} is a fixed-length model trained on {window}-frame windows "
            f"({window / fps:g} s); {int(frames)} frames is outside what it learnt (its samples "
            f"may not move well, its likelihoods are not the window's). Use {window} frames, "
            "or a causal model (moglow) for other lengths",
            UserWarning,
            stacklevel=stacklevel,
        )


def frame_multiple(model) -> int:
    """The number of frames every length a model draws must be a multiple of: 2**L for the
    L-level Glow (``Glow.frame_multiple``), 4 for the VAE-LSTM, 1 (any length) otherwise."""
    return int(getattr(model, "frame_multiple", 1))


def check_frames(model, name: str, frames: int, fps: float, fix: str) -> None:
    """Refuse (:class:`RunError`) a length of ``frames`` that ``model`` cannot draw, naming
    the nearest lengths that work in frames and seconds. ``fix`` is how the caller sets the
    length: ``"--seconds"`` (the CLI: the message offers those seconds) or a phrase such as
    ``"a control of"`` (the message offers those frame counts)."""
    from motionflows.models.validation import nearest_lengths

    m = frame_multiple(model)
    frames = int(frames)
    if frames >= m and frames % m == 0:
        return
    options = nearest_lengths(frames, m)
    if fix == "--seconds":
        offer = "--seconds " + " or ".join(f"{n / fps:g}" for n in options)
    else:
        offer = f"{fix} " + " or ".join(f"{n}" for n in options) + " frames"
    raise RunError(
        f"{name} draws lengths that are a multiple of {m} frames ({m / fps:g} s at {fps:g} "
        f"fps); {frames} frames ({frames / fps:g} s) is not one: use {offer}"
    )


FAR_CONTROL_SD = 15.0
"""How many training standard deviations from the training mean a control channel may go
before sampling warns. The Bandai takes reach 6 (forward), 9 (sideways) and 11 (turn) with
the shipped MoGlow's standardiser; a control written per second instead of per frame lands
fps times (20x) further from zero."""


def warn_if_control_unseen(
    module, config, standardizer, control, where: str, *, stacklevel: int = 3
) -> None:
    """Warn (``UserWarning``) when a control (..., T, 3) in m/frame, m/frame, rad/frame goes
    more than :data:`FAR_CONTROL_SD` training standard deviations (``standardizer``, the
    run's) from the training mean in any frame: the model extrapolates there without a sign
    of it in its output, and the usual cause is a control in m/s or rad/s. Names the worst
    channel and frame; ``stacklevel`` as :func:`warn_if_not_window`'s."""
    import numpy as np

    from motionflows.data.names import CONTROL_NAMES, CONTROL_UNITS

    fps = float(config.data.fps)
    control = np.asarray(control, np.float64)
    z = np.abs(np.asarray(standardizer.normalize_control(control), np.float64))
    if not z.size or z.max() <= FAR_CONTROL_SD:
        return
    worst = np.unravel_index(int(np.argmax(z)), z.shape)
    value, frame, channel = float(control[worst]), int(worst[-2]), int(worst[-1])
    label, unit = CONTROL_NAMES[channel], CONTROL_UNITS[channel].removesuffix("/frame")
    mean, sd = float(standardizer.control_mean[channel]), float(standardizer.control_std[channel])
    warnings.warn(
        f"{where}: control frame {frame} has {label} {value:.3g} {unit}/frame ({value * fps:.3g} "
        f"{unit}/s at {fps:g} fps), {z.max():.0f} standard deviations from what {module.NAME} was "
        f"trained on ({mean:.3f} +- {sd:.3f} {unit}/frame); the model extrapolates there and its "
        f"motion means little. Controls are per frame: divide m/s and rad/s by the fps",
        UserWarning,
        stacklevel=stacklevel,
    )


def check_sample_control(module, config, model, standardizer, control, where: str, fix: str):
    """The checks every sampler runs on a control array (..., T, 3) in m/frame, m/frame,
    rad/frame before it draws: a length ``model`` cannot draw is refused
    (:func:`check_frames`, whose ``fix`` this is); a fixed-length model's length other than
    its window and a control far outside the training data are warned about
    (:func:`warn_if_not_window`, :func:`warn_if_control_unseen`), the warnings pointing at
    the line that called the sampler. ``where`` names the sampler in the warnings."""
    frames = int(control.shape[-2])
    check_frames(model, module.NAME, frames, float(config.data.fps), fix)
    warn_if_not_window(module, config, frames, where, stacklevel=4)
    warn_if_control_unseen(module, config, standardizer, control, where, stacklevel=4)


def new_run_name(preset: str | None) -> str:
    return f"{preset or 'custom'}-{time.strftime('%Y%m%d-%H%M%S')}"


def latest_run(root: str | Path, experiment: str) -> Path | None:
    """The most recently modified run directory of ``experiment`` under ``root``."""
    base = Path(root) / experiment
    runs = [p for p in base.glob("*") if (p / "config.json").is_file()]
    return max(runs, key=lambda p: p.stat().st_mtime) if runs else None


def check_run_dir(run_dir: str | Path) -> Path:
    run_dir = Path(run_dir)
    if not (run_dir / "config.json").is_file():
        raise RunError(
            f"{run_dir} is not a run directory (no config.json); runs live in "
            "runs/<experiment>/<run-name>/ — list them with `motionflows runs`"
        )
    return run_dir


def resolve_run_dir(text: str | Path) -> Path:
    """A run directory from a path, or from ``pretrained:NAME`` (a model shipped with the
    package, :func:`motionflows.pretrained.path`); raises ``RunError`` when it is neither."""
    text = str(text)
    if text.startswith("pretrained:"):
        from motionflows import pretrained

        return pretrained.path(text.split(":", 1)[1])
    return check_run_dir(text)


def _metrics_row(line: str) -> dict | None:
    """One ``metrics.jsonl`` line as a row, or None if it is damaged (not a JSON object, or
    a ``step`` that is not a non-negative integer)."""
    try:
        row = json.loads(line)
    except (json.JSONDecodeError, RecursionError):
        return None
    if not isinstance(row, dict):
        return None
    step = row.get("step", 0)
    if isinstance(step, bool) or not isinstance(step, int) or step < 0:
        return None
    return row


def read_metrics(run_dir: str | Path) -> list[dict]:
    """The rows of ``run_dir/metrics.jsonl``; damaged lines (a crash, a broken disk) are
    skipped with one warning naming the file, their count and the first line number."""
    path = Path(run_dir) / "metrics.jsonl"
    if not path.is_file():
        return []
    rows, bad = [], []
    text = path.read_bytes().decode("utf-8", errors="replace")
    for number, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if line:
            row = _metrics_row(line)
            if row is None:
                bad.append(number)
            else:
                rows.append(row)
    if bad:
        warnings.warn(
            f"{path}: skipped {len(bad)} damaged line(s) (first: line {bad[0]}); the other "
            "rows are used",
            MetricsWarning,
            stacklevel=2,
        )
    return rows


class MetricsWarning(UserWarning):
    """A ``metrics.jsonl`` line could not be read and was skipped."""


def truncate_metrics(run_dir: str | Path, step: int) -> None:
    """Drop metric rows after ``step`` (written after the checkpoint a resume starts from)."""
    rows = [r for r in read_metrics(run_dir) if r.get("step", 0) <= step and "status" not in r]
    path = Path(run_dir) / "metrics.jsonl"
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))


def append_metrics(run_dir: str | Path, row: dict) -> None:
    with open(Path(run_dir) / "metrics.jsonl", "a") as f:
        f.write(json.dumps(row) + "\n")


def best_val(rows: list[dict], key: str = "val_nll") -> tuple[float | None, int | None]:
    """(lowest finite ``key``, its step) over metric ``rows``, or (None, None)."""
    vals = [
        (r[key], r.get("step", 0))
        for r in rows
        if isinstance(r.get(key), int | float) and math.isfinite(r[key])
    ]
    if not vals:
        return None, None
    return min(vals)


def plot_losses(run_dir: str | Path, rows: list[dict] | None = None) -> Path | None:
    """Write ``loss.png``: training loss and validation NLL (nats/frame, metres) by step."""
    rows = read_metrics(run_dir) if rows is None else rows

    def points(key):
        return [
            (r.get("step", 0), r[key])
            for r in rows
            if isinstance(r.get(key), int | float) and not isinstance(r[key], bool)
        ]

    train, val = points("loss"), points("val_nll")
    if not train and not val:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    if train:
        axes[0].plot(*zip(*train, strict=True), lw=1)
    axes[0].set(xlabel="step", ylabel="training loss", title="training loss")
    if val:
        axes[1].plot(*zip(*val, strict=True), "o-", ms=3)
    axes[1].set(xlabel="step", ylabel="nats / frame (metres)", title="validation NLL")
    for ax in axes:
        ax.grid(alpha=0.3)
    fig.subplots_adjust(left=0.08, right=0.98, bottom=0.15, top=0.9, wspace=0.3)
    path = Path(run_dir) / "loss.png"
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def _fmt_time(seconds: float) -> str:
    if not math.isfinite(seconds):
        return "--:--"
    seconds = int(seconds)
    h, rem = divmod(seconds, 3600)
    m, s = divmod(rem, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m:02d}:{s:02d}"


class Progress:
    """A plain-text progress bar with ETA on stderr (one line per update off a terminal)."""

    def __init__(
        self,
        total: int,
        start: int = 0,
        *,
        enabled: bool = True,
        stream: TextIO | None = None,
        width: int = 24,
    ):
        self.total, self.start, self.enabled = total, start, enabled
        self.stream = stream or sys.stderr
        self.width = width
        self.t0 = time.perf_counter()
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())

    def update(self, step: int, info: str = "") -> None:
        if not self.enabled:
            return
        elapsed = time.perf_counter() - self.t0
        done = step - self.start
        rate = done / elapsed if elapsed > 0 and done > 0 else float("nan")
        eta = (self.total - step) / rate if rate and rate == rate else float("nan")
        frac = step / self.total if self.total else 1.0
        fill = int(round(self.width * frac))
        bar = "#" * fill + "." * (self.width - fill)
        line = (
            f"[{bar}] {step}/{self.total} {100 * frac:3.0f}% {info} "
            f"| {_fmt_time(elapsed)} elapsed, ETA {_fmt_time(eta)}"
        )
        if self.tty:
            self.stream.write("\r\033[K" + line)
        else:
            self.stream.write(line + "\n")
        self.stream.flush()

    def close(self) -> None:
        if self.enabled and self.tty:
            self.stream.write("\n")
            self.stream.flush()


def parse_data(text: str) -> dict[str, Any]:
    """``--data`` value -> DataConfig changes: ``synthetic``, ``bandai``, ``bandai:DIR``,
    ``bvh:DIR`` or a folder of BVH files."""
    if text in ("synthetic", "bandai", "bvh"):
        return {"source": text} if text != "bvh" else _bvh_error(text)
    if ":" in text:
        source, path = text.split(":", 1)
        if source in ("bandai", "bvh") and path:  # synthetic data has no folder
            return {"source": source, "path": path}
    if Path(text).is_dir():
        return {"source": "bvh", "path": text}
    raise RunError(
        f"--data {text!r}: use synthetic, bandai, bandai:DIR, bvh:DIR or an existing folder"
    )


def _bvh_error(text: str):
    raise RunError(f"--data {text}: give the folder as bvh:DIR")


def list_runs(root: str | Path = "runs") -> list[dict]:
    """One dict per run under ``root``: experiment, run, preset, step, best val NLL, dir.

    A run whose ``config.json`` cannot be read gets ``{"dir", "run", "broken": why}``
    instead, so one damaged run never hides the others."""
    from motionflows.config import read_config_json

    out = []
    root = Path(root)
    for cfg in sorted(root.glob("*/*/config.json")):
        run_dir = cfg.parent
        try:
            payload = read_config_json(cfg)
        except RunError as err:
            out.append({"dir": str(run_dir), "run": run_dir.name, "broken": str(err)})
            continue
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", MetricsWarning)
            rows = read_metrics(run_dir)
        damaged = [str(w.message) for w in caught if issubclass(w.category, MetricsWarning)]
        val, val_step = best_val(rows)
        steps = [r["step"] for r in rows if "step" in r]
        status = next((r["status"] for r in reversed(rows) if "status" in r), "running?")
        if damaged:
            status = f"{status} (metrics.jsonl has damaged lines, skipped)"
        out.append(
            {
                "experiment": payload.get("experiment", run_dir.parent.name),
                "run": run_dir.name,
                "preset": payload.get("preset"),
                "step": max(steps) if steps else 0,
                "best_val_nll": val,
                "best_step": val_step,
                "status": status,
                "dir": str(run_dir),
            }
        )
    return out


def format_runs(runs: list[dict]) -> str:
    head = (
        f"{'experiment':<14} {'run':<28} {'preset':<10} {'step':>7} "
        f"{'best val NLL':>13} {'at':>7}  status"
    )
    lines = [head, "-" * len(head)]
    broken = [r for r in runs if "broken" in r]
    for r in runs:
        if "broken" in r:
            continue
        val = f"{r['best_val_nll']:.3f}" if r["best_val_nll"] is not None else "-"
        at = str(r["best_step"]) if r["best_step"] is not None else "-"
        lines.append(
            f"{r['experiment']:<14} {r['run']:<28} {str(r['preset']):<10} "
            f"{r['step']:>7} {val:>13} {at:>7}  {r['status']}"
        )
    lines.append(
        "best val NLL: nats/frame in metres on validation windows ('window' scope, else the "
        "model's first scope, e.g. the VAE-LSTM's ELBO bound)"
    )
    lines += [f"broken run {r['dir']}: {r['broken']}" for r in broken]
    return "\n".join(lines)
