"""The bench's plots: NLL by frame position, and one bar panel per motion metric.

Both read the JSON-able ``results`` dict of :func:`motionflows.bench.run_benchmark`.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from motionflows.bench.report import NATS, REFERENCE_ROWS


def plot_per_frame_nll(results: dict, path: str | Path) -> bool:
    """NLL (nats/frame, metres) against frame position in the window, one line per model."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    values = []
    for name in results.get("model_order", list(results["models"])):
        pf = results["models"].get(name, {}).get("per_frame_nll")
        if not pf or not pf.get("available"):
            continue
        x = [p + 1 for p in pf["positions"]]
        style = "-o" if len(x) < 20 else "-"
        ax.plot(x, pf[NATS], style, label=f"{name} ({pf['method']})", ms=3)
        values += [v for v in pf[NATS] if v is not None and math.isfinite(v)]
    if not values:
        plt.close(fig)
        return False
    title = "Test NLL per frame position"
    lo, hi = min(values), max(values)
    values.sort()
    q90 = values[int(0.9 * (len(values) - 1))]
    if hi - q90 > 2 * max(q90 - lo, 1e-9):  # a few huge values (e.g. a zero-history frame 1)
        pad = 0.15 * max(q90 - lo, 1e-9)
        ax.set_ylim(lo - pad, q90 + 3 * pad)
        title += f" (axis clipped; maximum {hi:.0f})"
    ax.set_xlabel("frame position in the window (1 = first)")
    ax.set_ylabel("NLL, nats/frame (metres)")
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True


def plot_metric_bars(results: dict, path: str | Path) -> bool:
    """One bar panel per motion metric: ground truth and the reference rows of real training
    motion first (greys), then every model."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    meta = results.get("motion_metrics", {})
    if not meta:
        return False
    values = {"ground truth": results.get("ground_truth", {}).get("motion", {})}
    refs = results.get("references") or {}
    short = {ref: label.split(" (")[0] for ref, label in REFERENCE_ROWS.items()}
    values.update({short[ref]: refs[ref] for ref in REFERENCE_ROWS if refs.get(ref)})
    greys = [f"{g:.2f}" for g in np.linspace(0.4, 0.75, len(values))]
    models = [
        n for n in results.get("model_order", []) if results["models"].get(n, {}).get("motion")
    ]
    values.update({n: results["models"][n]["motion"] for n in models})
    names = list(values)
    keys = list(meta)
    cols = min(4, len(keys))
    rows = math.ceil(len(keys) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 2.8 * rows), squeeze=False)
    colors = greys + [f"C{i}" for i in range(len(models))]
    for ax, key in zip(axes.flat, keys, strict=False):
        vals = [values[n].get(key) for n in names]
        vals = [float(v) if v is not None and math.isfinite(float(v)) else 0.0 for v in vals]
        ax.bar(range(len(names)), vals, color=colors)
        ax.set_xticks(range(len(names)))
        ax.set_xticklabels(names, rotation=45, ha="right", fontsize=7)
        ax.set_title(f"{meta[key]['label']}\n({meta[key]['unit']})", fontsize=8)
        ax.tick_params(axis="y", labelsize=7)
    for ax in list(axes.flat)[len(keys) :]:
        ax.axis("off")
    fig.suptitle(f"Motion quality (temperature {results.get('temperature', '?')})", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True
