"""The benchmark's report: ``BENCHMARK.md`` from a results dict, and its plots.

Everything here reads the JSON-able ``results`` dict that :func:`motionflows.bench.run_benchmark`
builds (and writes as ``results.json``), so a report can be regenerated from ``results.json``
alone: ``write_markdown(json.load(open("results.json")), "BENCHMARK.md")``.

Tables keep one unit per column: NLL in nats/frame in metres (standardiser Jacobian included)
and NLL in bits/frame in standardised space are separate columns, and the scored frames are
named in every row. Bounds (ELBO, IWAE-K) are marked; for a bound the NLL column holds the
bound on the NLL (an upper bound: the true NLL is at most this).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

NATS = "nats_per_frame_metres"
BITS = "bits_per_frame_std"


def _fmt(value: Any, digits: int = 2) -> str:
    if value is None:
        return "n/a"
    if isinstance(value, str):
        return value
    try:
        v = float(value)
    except (TypeError, ValueError):
        return str(value)
    if not math.isfinite(v):
        return str(v)
    if abs(v) < 0.5 * 10 ** (-digits):
        return f"{0:.{digits}f}"
    if abs(v) >= 1e7:
        return f"{v:.3g}"
    return f"{v:,.{digits}f}".replace(",", " ")


def _ci(stats: dict | None, unit: str) -> str:
    """'mean [lo, hi]' of one unit of a likelihood stats dict."""
    if not stats or unit not in stats:
        return "n/a"
    lo, hi = stats[unit + "_ci95"]
    return f"{_fmt(stats[unit])} [{_fmt(lo)}, {_fmt(hi)}]"


def _gap(stats_test: dict | None, stats_train: dict | None, unit: str) -> str:
    if not stats_test or not stats_train or unit not in stats_test or unit not in stats_train:
        return "n/a"
    return _fmt(stats_test[unit] - stats_train[unit])


def _ordered(lik: dict) -> list[tuple[str, dict]]:
    """Scopes in table order: ``window`` first, exact scores, then bounds."""
    return sorted(lik.items(), key=lambda kv: (kv[0] != "window", bool(kv[1].get("bound")), kv[0]))


def likelihood_rows(models: dict, order: list[str]) -> list[list[str]]:
    """One row per (model, scope): scope, frames, bound, test/train NLL in both units, gap."""
    rows = []
    for name in order:
        entry = models.get(name, {})
        if "error" in entry and not entry.get("likelihood"):
            rows.append(
                [f"**{name}**", "failed: " + entry["error"].splitlines()[0][:80]] + [""] * 7
            )
            continue
        for scope, lik in _ordered(entry.get("likelihood", {})):
            label = f"{scope} (bound)" if lik.get("bound") else scope
            rows.append([
                f"**{name}**",
                label,
                lik.get("frames_label", str(lik.get("frames", "?"))),
                _ci(lik.get("test"), NATS),
                _ci(lik.get("train"), NATS),
                _gap(lik.get("test"), lik.get("train"), NATS),
                _ci(lik.get("test"), BITS),
                _ci(lik.get("train"), BITS),
                str(lik.get("test", {}).get("windows", "?")),
            ])  # fmt: skip
    return rows


LIKELIHOOD_HEADER = [
    "model",
    "scope",
    "scored frames",
    "test NLL, nats/frame (m) [95% CI]",
    "train NLL, nats/frame (m) [95% CI]",
    "gap test-train, nats/frame (m)",
    "test NLL, bits/frame (std) [95% CI]",
    "train NLL, bits/frame (std) [95% CI]",
    "test windows",
]


def _table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join(["---"] * len(header)) + "|"]
    for row in rows:
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines)


def motion_table(results: dict, order: list[str]) -> str:
    """Rows: ground truth, then each model; columns: the motion metrics with their units."""
    meta = results.get("motion_metrics", {})
    keys = list(meta)
    header = ["model"] + [f"{meta[k]['label']} ({meta[k]['unit']})" for k in keys]
    rows = []
    gt = results.get("ground_truth", {}).get("motion", {})
    rows.append(["*ground truth (test)*"] + [_fmt(gt.get(k), 3) for k in keys])
    for name in order:
        entry = results["models"].get(name, {})
        motion = entry.get("motion")
        if not motion:
            why = entry.get("motion_error") or entry.get("error") or "not run"
            pad = [""] * max(len(keys) - 1, 0)
            rows.append([f"**{name}**", "n/a: " + why.splitlines()[0][:80]] + pad)
            continue
        rows.append([f"**{name}**"] + [_fmt(motion.get(k), 3) for k in keys])
    return _table(header, rows)


def speed_table(results: dict, order: list[str]) -> str:
    header = [
        "model",
        "parameters",
        "train steps",
        "train frames/s",
        "sample frames/s, batch 1",
        "sample frames/s, batch 64",
        "sampler compile s (b1 / b64)",
        "run",
    ]
    rows = []
    for name in order:
        entry = results["models"].get(name, {})
        sp = entry.get("speed", {})
        run = entry.get("run_dir", "")
        reused = " (reused)" if entry.get("reused") else ""
        rows.append([
            f"**{name}**",
            _fmt(entry.get("params"), 0),
            _fmt(entry.get("steps"), 0),
            (_fmt(sp.get("train_frames_per_s"), 0) if sp.get("train_frames_per_s")
             else f"closed-form fit, {_fmt(sp.get('fit_seconds'), 1)} s"
             if sp.get("fit_seconds") is not None else "n/a"),
            _fmt(sp.get("sample_frames_per_s_b1"), 0),
            _fmt(sp.get("sample_frames_per_s_b64"), 0),
            f"{_fmt(sp.get('compile_s_b1'), 1)} / {_fmt(sp.get('compile_s_b64'), 1)}",
            f"`{run}`{reused}",
        ])  # fmt: skip
    return _table(header, rows)


def performer_table(split: dict, order: list[str]) -> str:
    header = [
        "model",
        "scope",
        "test NLL (unseen performers), nats/frame (m) [95% CI]",
        "train NLL, nats/frame (m) [95% CI]",
        "gap, nats/frame (m)",
        "test NLL, bits/frame (std) [95% CI]",
    ]
    rows = []
    for name in order:
        entry = split.get("models", {}).get(name)
        if entry is None:
            continue
        if "error" in entry and not entry.get("likelihood"):
            rows.append(
                [f"**{name}**", "failed: " + entry["error"].splitlines()[0][:80], "", "", "", ""]
            )
            continue
        for scope, lik in _ordered(entry.get("likelihood", {})):
            label = f"{scope} (bound)" if lik.get("bound") else scope
            rows.append([
                f"**{name}**", label,
                _ci(lik.get("test"), NATS), _ci(lik.get("train"), NATS),
                _gap(lik.get("test"), lik.get("train"), NATS), _ci(lik.get("test"), BITS),
            ])  # fmt: skip
    return _table(header, rows)


def _split3(d: Any) -> str:
    if not isinstance(d, dict):
        return "?"
    return " / ".join(str(d.get(k, "?")) for k in ("train", "val", "test"))


def write_markdown(results: dict, path: str | Path) -> str:
    """Write ``BENCHMARK.md`` for ``results``; returns the text."""
    order = [m for m in results.get("model_order", list(results["models"]))]
    data = results["data"]
    m = results["machine"]
    out = []
    out.append(f"# motionflows benchmark: {data['spec']} data, {results['budget']} budget\n")
    out.append(f"Command: `{results['command']}`  ")
    out.append(
        f"Created {results['created']} in {_fmt(results.get('wall_seconds'), 0)} s "
        f"of wall time; budget `{results['budget']}` = {results['budget_note']}.  "
    )
    out.append(
        f"Machine: {m['cpu']} ({m['cores']} cores visible"
        f"{'; ' + ', '.join(m['isa']) if m.get('isa') else ''}), {m['memory']}, "
        f"{m['platform']}; JAX {m['jax']} ({m['backend']}: {m['devices']}), "
        f"Flax {m['flax']}, Python {m['python']}; {m.get('load', 'load unknown')} at "
        "the start (timings on a shared machine are slower than on an idle one).\n"
    )
    info = data.get("info", {})
    out.append("## Data\n")
    out.append(
        f"Source `{data['config']['source']}`"
        + (f" at `{data['config']['path']}`" if data["config"].get("path") else "")
        + f", {data['config']['fps']:g} fps, windows of {data['config']['window']} "
        f"frames ({data['config']['window'] / data['config']['fps']:g} s), hop "
        f"{data['config']['hop']}, split by {data['config']['split_by']}. "
        f"Takes train / val / test: {_split3(info.get('takes'))}; windows "
        f"{_split3(info.get('windows'))} (train with augmentation); complete (unpadded) "
        f"windows scored: test {info.get('complete_windows_test', '?')}. Every model is "
        "trained on this one data configuration and scored on the same test windows "
        "and controls; windows padded past the end of a short take are not scored.\n"
    )
    test = results.get("test_data") or {}
    if test.get("spec"):
        skipped = test.get("skipped") or []
        out.append(
            f"**Test data: `{test['spec']}`** instead of the test split: every table below is "
            f"computed on the {test.get('windows', '?')} complete windows of its "
            f"{len(test.get('takes') or [])} takes (cut at the same fps, window and hop, "
            "standardised with the training standardiser)"
            + (f"; {len(skipped)} take(s) shorter than one window skipped" if skipped else "")
            + ".\n"
        )
    out.append("## Likelihood\n")
    out.append(
        "Negative log-likelihood per frame (lower is better), mean over windows with a "
        f"bootstrap 95% interval ({results['bootstrap']} resamples of windows). "
        "`nats/frame (m)`: the density of the 63 pose values in metres (the standardiser's "
        "log-Jacobian included); `bits/frame (std)`: the same scored frames in the "
        "standardised space of the official MoGlow code. `window` = -log p(x_1:T | c_1:T) / T "
        "over all T frames of the window given its controls (MoGlow: zero, i.e. mean-pose, "
        "history before frame 1). MoGlow `official` = frames tau+1..T given the true first tau "
        "frames. `(bound)` rows are the VAE-LSTM's ELBO / IWAE-K: upper bounds on the NLL, not "
        "the NLL. The train column scores "
        f"{results['train_windows_note']}.\n"
    )
    out.append(_table(LIKELIHOOD_HEADER, likelihood_rows(results["models"], order)) + "\n")
    split = results.get("performer_split")
    if split:
        out.append("### Split by performer\n")
        if split.get("skipped"):
            out.append(f"Not run: {split['skipped']}\n")
        else:
            out.append(
                f"Train on performers {split.get('train', '?')}, test on "
                f"{split.get('test', '?')} (each model retrained on this split).\n"
            )
            out.append(performer_table(split, order) + "\n")
    out.append("## Motion quality of samples\n")
    out.append(
        f"Samples drawn for the controls of {results['motion_windows']} test windows at "
        f"temperature {results['temperature']:g} (every model), converted to metres; diversity "
        f"from {results.get('diversity_samples', 'several')} samples under one control; the "
        "first row scores the ground-truth test motion the same way. "
        + results.get("motion_note", "")
        + "\n"
    )
    out.append(motion_table(results, order) + "\n")
    out.append("## Speed\n")
    out.append(
        "Training frames/s: median of the run's logged frames/s (frames of pose data per "
        "second of training, data loading included). Sampling frames/s: generated frames per "
        f"second of wall time for {results['window']} frames per sequence at batch 1 and 64 "
        "(jitted sampler, compile excluded and listed separately).\n"
    )
    out.append(speed_table(results, order) + "\n")
    plots = results.get("plots", {})
    if plots:
        out.append("## Plots\n")
        if plots.get("per_frame_nll"):
            out.append(f"![NLL per frame position]({plots['per_frame_nll']})\n")
            notes = [f"{k}: {v}" for k, v in results.get("per_frame_notes", {}).items()]
            if notes:
                out.append("Per-frame NLL: " + "; ".join(notes) + ".\n")
        if plots.get("metrics"):
            out.append(f"![motion metrics]({plots['metrics']})\n")
        for name, gif in plots.get("gifs", {}).items():
            out.append(f"- `{name}` beside the ground truth (same test control): [{gif}]({gif})")
        out.append("")
    errors = {k: v["error"] for k, v in results["models"].items() if v.get("error")}
    if errors:
        out.append("## Failures\n")
        for name, err in errors.items():
            out.append(f"- **{name}**: {err.splitlines()[0]}")
        out.append("")
    text = "\n".join(out)
    Path(path).write_text(text)
    return text


# --------------------------------------------------------------------------------------------
# plots
# --------------------------------------------------------------------------------------------


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
    """One bar panel per motion metric: ground truth first, then every model."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    meta = results.get("motion_metrics", {})
    if not meta:
        return False
    names = ["ground truth"] + [
        n for n in results.get("model_order", []) if results["models"].get(n, {}).get("motion")
    ]
    values = {"ground truth": results.get("ground_truth", {}).get("motion", {})}
    for n in names[1:]:
        values[n] = results["models"][n]["motion"]
    keys = list(meta)
    cols = min(4, len(keys))
    rows = math.ceil(len(keys) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 2.8 * rows), squeeze=False)
    colors = ["0.4"] + [f"C{i}" for i in range(len(names) - 1)]
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
