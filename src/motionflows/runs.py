"""Run directories, experiment lookup, metrics files, progress bar and loss plot.

A run lives in ``runs/<experiment>/<run-name>/`` with ``config.json``,
``standardizer.json``, ``metrics.jsonl``, ``checkpoints/``, ``samples/``, ``loss.png`` and
``eval_<split>.json``.
"""

from __future__ import annotations

import importlib
import json
import math
import sys
import time
from pathlib import Path
from typing import Any, TextIO

from motionflows.errors import RunError

REQUIRED = ("NAME", "Config", "PRESETS", "build", "loss", "evaluate", "SCOPES", "sample")


def experiment_search_paths() -> list[Path]:
    """Where ``experiments/`` is looked for: the repository root (if it holds one) and cwd."""
    import motionflows

    paths = []
    root = Path(motionflows.__file__).resolve().parents[2]
    if (root / "experiments").is_dir():
        paths.append(root)
    paths.append(Path.cwd())
    return paths


def available_experiments() -> list[str]:
    names = set()
    for base in experiment_search_paths():
        for f in (base / "experiments").glob("*.py"):
            if not f.name.startswith("_"):
                names.add(f.stem)
    return sorted(names)


def resolve_experiment(name: str):
    """Import ``experiments.<name>`` (a module object passes through) and check its protocol."""
    if not isinstance(name, str):
        return name
    if not name.isidentifier():
        raise RunError(f"unknown experiment {name!r}; available: {available_experiments()}")
    for base in reversed(experiment_search_paths()):
        if str(base) not in sys.path:
            sys.path.insert(0, str(base))
    try:
        module = importlib.import_module(f"experiments.{name}")
    except ModuleNotFoundError as err:
        if err.name in (f"experiments.{name}", "experiments"):
            raise RunError(
                f"unknown experiment {name!r}; available: {available_experiments()}"
            ) from None
        raise
    missing = [a for a in REQUIRED if not hasattr(module, a)]
    if missing:
        raise RunError(f"experiments.{name} lacks {missing} (see docs/ARCHITECTURE.md)")
    return module


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


def read_metrics(run_dir: str | Path) -> list[dict]:
    path = Path(run_dir) / "metrics.jsonl"
    if not path.is_file():
        return []
    rows = []
    for line in path.read_text().splitlines():
        line = line.strip()
        if line:
            try:
                rows.append(json.loads(line))
            except json.JSONDecodeError:
                continue  # a line cut short by a crash
    return rows


def truncate_metrics(run_dir: str | Path, step: int) -> None:
    """Drop metric rows after ``step`` (written after the checkpoint a resume starts from)."""
    rows = [r for r in read_metrics(run_dir) if r.get("step", 0) <= step and "status" not in r]
    path = Path(run_dir) / "metrics.jsonl"
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))


def append_metrics(run_dir: str | Path, row: dict) -> None:
    with open(Path(run_dir) / "metrics.jsonl", "a") as f:
        f.write(json.dumps(row) + "\n")


def best_val(rows: list[dict], key: str = "val_nll") -> tuple[float | None, int | None]:
    vals = [(r[key], r["step"]) for r in rows if isinstance(r.get(key), int | float)]
    if not vals:
        return None, None
    return min(vals)


def plot_losses(run_dir: str | Path, rows: list[dict] | None = None) -> Path | None:
    """Write ``loss.png``: training loss and validation NLL (nats/frame, metres) by step."""
    rows = read_metrics(run_dir) if rows is None else rows
    train = [(r["step"], r["loss"]) for r in rows if "loss" in r and r["loss"] is not None]
    val = [(r["step"], r["val_nll"]) for r in rows if r.get("val_nll") is not None]
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
        if source in ("bandai", "bvh", "synthetic") and path:
            return {"source": source, "path": path}
    if Path(text).is_dir():
        return {"source": "bvh", "path": text}
    raise RunError(
        f"--data {text!r}: use synthetic, bandai, bandai:DIR, bvh:DIR or an existing folder"
    )


def _bvh_error(text: str):
    raise RunError(f"--data {text}: give the folder as bvh:DIR")


def list_runs(root: str | Path = "runs") -> list[dict]:
    """One dict per run under ``root``: experiment, run, preset, step, best val NLL, dir."""
    out = []
    root = Path(root)
    for cfg in sorted(root.glob("*/*/config.json")):
        run_dir = cfg.parent
        try:
            payload = json.loads(cfg.read_text())
        except (OSError, json.JSONDecodeError):
            continue
        rows = read_metrics(run_dir)
        val, val_step = best_val(rows)
        steps = [r["step"] for r in rows if "step" in r]
        status = next((r["status"] for r in reversed(rows) if "status" in r), "running?")
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
    for r in runs:
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
    return "\n".join(lines)
