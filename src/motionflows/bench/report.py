"""The benchmark's report: ``BENCHMARK.md`` from a results dict.

Everything here reads the JSON-able ``results`` dict that :func:`motionflows.bench.run_benchmark`
builds (and writes as ``results.json``), so a report can be regenerated from ``results.json``
alone: ``write_markdown(json.load(open("results.json")), "BENCHMARK.md")``.

Tables keep one unit per column: NLL in nats/frame in metres (standardiser Jacobian included)
and NLL in bits/frame in standardised space are separate columns, and the scored frames are
named in every row. Bounds (ELBO, IWAE-K) are marked; for a bound the NLL column holds the
bound on the NLL (an upper bound: the true NLL is at most this). Every scope is described by
the experiment that scores it (its ``SCOPES``), so the report names no model.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from motionflows.bench.scoring import DIVERGED_METRES, REFERENCE_WINDOWS
from motionflows.bench.short_takes import SHORT_METRICS

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
    "the window of another take whose control is closest (Euclidean over frames and channels, "
    "each divided by its std); pose / motion error: "
    "Habibie et al.'s errors (root-relative joints / world joints after integrating the "
    "control) between one sample and the test motion, averaged over the report times "
    "(their frames 70, 90, 120, 160, 210 at 60 fps, at this frame rate, those inside the "
    "window). The ground-truth row scores the test motion itself (errors and FD are 0 by "
    "construction). Diverged samples: the fraction holding NaN/inf or a joint more than "
    f"{DIVERGED_METRES:g} m from the root (a flow's inverse can blow up far from its training "
    "data); the other metrics are over the remaining samples."
)
"""The motion section's definitions of its metrics (printed under the table)."""

REFERENCE_ROWS = {
    "training_takes": "training takes (own controls)",
    "nearest_training_window": "nearest training window (test controls)",
}
"""The rows of real training motion under the ground truth (``results["references"]``,
:func:`motionflows.bench.scoring.data_references`), and their labels."""

REFERENCE_NOTE = (
    "Reference rows (real motion, no model): *training takes* scores every complete training "
    f"window (at most {REFERENCE_WINDOWS}, a fixed random subset beyond; mirrored copies "
    "included where the pipeline augments; no model's own augmentation, such as a tempo) on "
    "its own control, as a model that reproduced its training data would score on the "
    "control-independent metrics (its FDs are against the test windows; its diversity is "
    "the training split's natural diversity); *nearest "
    "training window* gives each test control the training window whose control is closest "
    "(Euclidean over frames and channels, each divided by its std) and scores it on the test "
    "control as a sample: motion matching over whole windows."
)
"""How the reference rows were made (printed under the motion table when they are there)."""


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
    refs = results.get("references") or {}
    for ref, label in REFERENCE_ROWS.items():
        if row := refs.get(ref):
            rows.append([f"*{label}*"] + [_fmt(row.get(k), 3) for k in keys])
    return _table(header, rows + _model_rows(results, order, keys, "motion"))


def _model_rows(results: dict, order: list[str], keys: list[str], field: str) -> list[list[str]]:
    """Each model's row of ``entry[field]`` (with its ``field + "_foot_lock"`` row under
    it when scored), or why it is missing (``field + "_error"``, the model's motion or
    training error)."""
    rows = []
    for name in order:
        entry = results["models"].get(name, {})
        motion = entry.get(field)
        if not motion:
            why = entry.get(f"{field}_error") or entry.get("motion_error")
            why = why or entry.get("error") or "not run"
            pad = [""] * max(len(keys) - 1, 0)
            rows.append([f"**{name}**", "n/a: " + why.splitlines()[0][:80]] + pad)
            continue
        rows.append([f"**{name}**"] + [_fmt(motion.get(k), 3) for k in keys])
        if locked := entry.get(f"{field}_foot_lock"):
            rows.append([f"{name} + foot lock"] + [_fmt(locked.get(k), 3) for k in keys])
    return rows


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
    order = list(results.get("model_order", list(results["models"])))
    sections = (
        _header(results),
        _data_section(results),
        _likelihood_section(results, order),
        _motion_section(results, order),
        _speed_section(results, order),
        _plots_section(results),
        _failures_section(results),
    )
    text = "\n".join(line for section in sections for line in section)
    Path(path).write_text(text)
    return text


def _header(results: dict) -> list[str]:
    m = results["machine"]
    return [
        f"# motionflows benchmark: {results['data']['spec']} data, {results['budget']} budget\n",
        f"Command: `{results['command']}`  ",
        f"Created {results['created']} in {_fmt(results.get('wall_seconds'), 0)} s "
        f"of wall time; budget `{results['budget']}` = {results['budget_note']}.  ",
        f"Machine: {m['cpu']} ({m['cores']} cores visible"
        f"{'; ' + ', '.join(m['isa']) if m.get('isa') else ''}), {m['memory']}, "
        f"{m['platform']}; JAX {m['jax']} ({m['backend']}: {m['devices']}), "
        f"Flax {m['flax']}, Python {m['python']}; {m.get('load', 'load unknown')} at "
        "the start (timings on a shared machine are slower than on an idle one).\n",
    ]


def _setting(value) -> str:
    """A config value as a sentence says it: booleans as "on" / "off"."""
    if isinstance(value, bool):
        return "on" if value else "off"
    return str(value)


def _own_training_data(results: dict) -> str:
    """Sentences naming the models trained with other training augmentation than the
    bench's data (their preset's, or ``--set data.tempo=...``) or on a share of its
    training takes (``--set data.train_fraction=...``); "" if none."""
    from motionflows.bench.budgets import AUGMENTATION_FIELDS

    bench = results["data"]["config"]
    own = []
    for name, entry in results.get("models", {}).items():
        data = (entry.get("config") or {}).get("data") or {}
        diff = [
            f"{k} {_setting(data[k])}"
            for k in AUGMENTATION_FIELDS
            if k in data and data[k] != bench.get(k)
        ]
        if diff:
            own.append(f"{name} ({', '.join(diff)})")
    shares = [
        f"{name} {fraction:g}"
        for name, entry in results.get("models", {}).items()
        if (fraction := ((entry.get("config") or {}).get("data") or {}).get("train_fraction", 1.0))
        != 1.0
    ]
    text = ""
    if own:
        text += (
            " Trained with other training augmentation: "
            + "; ".join(own)
            + ". The augmented takes enter that model's training only; it is validated and "
            "scored on the same windows, standardised by its own run."
        )
    if shares:
        text += (
            " Trained on a share of the training takes (`data.train_fraction`, the same "
            "share of each performer's, content's and style's takes): "
            + "; ".join(shares)
            + ". It is validated and scored on the same windows, standardised by its own run;"
            " its train NLL column scores the bench's training windows, some of which it "
            "never saw."
        )
    return text


def _short_takes_note(info: dict, scored: dict | None = None) -> str:
    """The test takes no frame of which the likelihood and motion tables score (each
    shorter than one window, so its one window is padded), and where they are scored
    (``scored``: ``results["short_takes"]``); "" when there are none."""
    short = int(info.get("windows_test", 0)) - int(info.get("complete_windows_test", 0))
    if short <= 0:
        return ""
    where = (
        f"the table *Motion on the short takes* scores the first frames of {scored['windows']} "
        "of them"
        if scored
        else "`python benchmarks/short_takes.py RUN` scores their first frames"
    )
    return (
        f" **{short} test takes are shorter than one window, so the likelihood and the motion "
        "of the complete windows leave out all their frames** (on Bandai mostly runs, which "
        f"last 2-4 s): {where} with the same motion metrics."
    )


def _data_section(results: dict) -> list[str]:
    data = results["data"]
    cfg, info = data["config"], data.get("info", {})
    out = [
        "## Data\n",
        f"Source `{cfg['source']}`"
        + (f" at `{cfg['path']}`" if cfg.get("path") else "")
        + f", {cfg['fps']:g} fps, windows of {cfg['window']} frames "
        f"({cfg['window'] / cfg['fps']:g} s), hop {cfg['hop']}, split by {cfg['split_by']}. "
        f"Takes train / val / test: {_split3(info.get('takes'))}; windows "
        f"{_split3(info.get('windows'))} (train with augmentation); complete (unpadded) "
        f"windows scored: test {info.get('complete_windows_test', '?')}. Every model is "
        "trained on these takes and scored on the same test windows and controls; windows "
        "padded past the end of a short take are not scored."
        + _short_takes_note(info, results.get("short_takes"))
        + _own_training_data(results)
        + "\n",
    ]
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
        shared = test.get("shared_with_training") or []
        if shared:
            out.append(
                f"**Not held out:** {len(shared)} of these takes are also training or validation "
                f"takes of the models (e.g. {', '.join(map(str, shared[:3]))}).\n"
            )
    return out


def scope_notes(results: dict, order: list[str]) -> list[str]:
    """One line per (scope, description) across the models: which models score it, and
    what it is (the experiments' own ``SCOPES`` descriptions)."""
    seen: dict[tuple[str, str, bool], list[str]] = {}
    for name in order:
        for scope, lik in _ordered(results["models"].get(name, {}).get("likelihood", {})):
            key = (scope, lik.get("description", ""), bool(lik.get("bound")))
            seen.setdefault(key, []).append(name)
    return [
        f"- `{scope}`{' (bound)' if bound else ''}, {', '.join(names)}: {text or 'no description'}"
        for (scope, text, bound), names in seen.items()
    ]


def _likelihood_section(results: dict, order: list[str]) -> list[str]:
    out = [
        "## Likelihood\n",
        "Negative log-likelihood per frame (lower is better), mean over windows with a "
        f"bootstrap 95% interval ({results['bootstrap']} resamples of windows). "
        "`nats/frame (m)`: the density of the 63 pose values in metres (the standardiser's "
        "log-Jacobian included); `bits/frame (std)`: the same scored frames in the "
        "standardised space of the official MoGlow code. `window` = -log p(x_1:T | c_1:T) / T "
        "over all T frames of the window given its controls. `(bound)` rows are bounds on "
        "the likelihood (an upper bound on the NLL, not the NLL). The train column scores "
        f"{results['train_windows_note']}. The scopes, as each experiment defines them:\n",
        *scope_notes(results, order),
        "",
        _table(LIKELIHOOD_HEADER, likelihood_rows(results["models"], order)) + "\n",
    ]
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
    return out


def _motion_section(results: dict, order: list[str]) -> list[str]:
    return [
        "## Motion quality of samples\n",
        f"Samples drawn for the controls of {results['motion_windows']} test windows at "
        f"temperature {results['temperature']:g} (every model), converted to metres; diversity "
        f"from {results.get('diversity_samples', 'several')} samples under one control; the "
        "first row scores the ground-truth test motion the same way. "
        + results.get("motion_note", "")
        + foot_lock_note(results)
        + (" " + REFERENCE_NOTE if results.get("references") else "")
        + "\n",
        motion_table(results, order) + "\n",
        *_short_takes_section(results, order),
    ]


def short_takes_table(results: dict, order: list[str]) -> str:
    """Rows: the recorded short takes, then each model's samples for them; columns: the
    motion metrics of :data:`~motionflows.bench.short_takes.SHORT_METRICS`."""
    meta = results.get("motion_metrics", {})
    keys = [k for k in SHORT_METRICS if k in meta]
    header = ["model"] + [f"{meta[k]['label']} ({meta[k]['unit']})" for k in keys]
    gt = results.get("ground_truth", {}).get("motion_short_takes") or {}
    rows = [["*ground truth (short test takes)*"] + [_fmt(gt.get(k), 3) for k in keys]]
    return _table(header, rows + _model_rows(results, order, keys, "motion_short_takes"))


def _short_takes_section(results: dict, order: list[str]) -> list[str]:
    """The motion on the test takes shorter than a window, when there are any."""
    short = results.get("short_takes")
    if not short:
        return []
    skip, frames = short["frames"]
    locked = any(e.get("motion_short_takes_foot_lock") for e in results["models"].values())
    kinds = ", ".join(f"{kind} {n}" for kind, n in short.get("kinds", {}).items())
    return [
        "### Motion on the short takes\n",
        f"Samples drawn at temperature {results['temperature']:g} for the controls of "
        f"{short['windows']} test takes shorter than one window ({kinds}), scored on their "
        f"frames {skip}..{frames - 1} (the first {skip}, the start from a mean-pose history "
        "while a recorded run starts at full speed, left out): each take's own control, held "
        "at its last value over the padded frames (a run going on, not the stop the padding "
        "stores). The first row scores the recorded frames; the Frechet distances are "
        "against them. Diversity and the errors at the report times are not scored "
        "(`motionflows.bench.short_takes`)."
        + (" Rows '+ foot lock': the same samples after the foot lock." if locked else "")
        + "\n",
        short_takes_table(results, order) + "\n",
    ]


def foot_lock_note(results: dict) -> str:
    """A sentence for a bench run with ``--foot-lock``, else ''."""
    if not any(e.get("motion_foot_lock") for e in results.get("models", {}).values()):
        return ""
    return (
        " Rows '+ foot lock' (`--foot-lock`) score the same samples after a post-process "
        "that holds each planted foot where it stands (`motionflows.foot_lock.foot_lock`: "
        "the calibrated contact rule's stances, a 3-frame fade, a two-bone IK that keeps the "
        "bone lengths); they are not the models' samples, and the row above each is."
    )


def simulated_devices_note(machine: dict) -> str:
    """A sentence for a bench run on several simulated CPU devices, else ''."""
    count = str(machine.get("devices", "")).split(" x ")[0]
    if machine.get("backend") != "cpu" or not count.isdigit() or int(count) < 2:
        return ""
    return (
        f" Run on {count} simulated CPU devices (`--cpu-devices {count}`): training, scoring "
        "and batch-64 sampling are data-parallel over them, batch-1 sampling runs on one of "
        "them, and all of them share this machine's cores and threads "
        "(docs/readme/speed.md), so compare these speed columns only with runs on as many "
        "devices."
    )


def _speed_section(results: dict, order: list[str]) -> list[str]:
    return [
        "## Speed\n",
        "Training frames/s: median of the run's logged frames/s (frames of pose data per "
        "second of training, data loading included). Sampling frames/s: generated frames per "
        f"second of wall time for {results['window']} frames per sequence at batch 1 and 64 "
        "(jitted sampler, compile excluded and listed separately)."
        + simulated_devices_note(results.get("machine", {}))
        + "\n",
        speed_table(results, order) + "\n",
    ]


def _plots_section(results: dict) -> list[str]:
    plots = results.get("plots", {})
    if not plots:
        return []
    out = ["## Plots\n"]
    if plots.get("per_frame_nll"):
        out.append(f"![NLL per frame position]({plots['per_frame_nll']})\n")
        notes = [f"{k}: {v}" for k, v in results.get("per_frame_notes", {}).items()]
        if notes:
            out.append("Per-frame NLL: " + "; ".join(notes) + ".\n")
    if plots.get("metrics"):
        out.append(f"![motion metrics]({plots['metrics']})\n")
    for name, gif in plots.get("gifs", {}).items():
        out.append(f"- `{name}` beside the ground truth (same test control): [{gif}]({gif})")
    return out + [""]


def _failures_section(results: dict) -> list[str]:
    errors = {k: v["error"] for k, v in results["models"].items() if v.get("error")}
    if not errors:
        return []
    return ["## Failures\n", *(f"- **{n}**: {e.splitlines()[0]}" for n, e in errors.items()), ""]
