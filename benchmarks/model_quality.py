"""Motion quality and likelihood of one experiment against training steps and temperature.

Trains (or resumes) one run to each milestone of ``--steps`` and, at every milestone,
samples the same test controls at each of ``--temperatures`` and scores the motion metrics
of ``motionflows.evaluation.motion`` (the bench's definitions, ground truth as reference)
and the test likelihood of every scope the experiment defines; beside the ground truth, the
bench's two rows of real training motion (the training takes on their own controls, and the
nearest training window on each scored control). Prints one JSON object per
(milestone, temperature) and writes ``OUT/quality.jsonl``, ``OUT/QUALITY.md`` and
``OUT/quality.png``. Used for the MoGlow jitter diagnosis (docs/readme/moglow_quality.md)::

    python benchmarks/model_quality.py moglow --preset quick --data bandai --split performer \\
        --steps 400,800,1600 --temperatures 1.0,0.8,0.6 --out runs/quality/moglow-quick

``--set key=value`` overrides config fields (the ``motionflows train`` grammar; repeatable); the run
directory is ``OUT/run``; an existing run is resumed (a milestone it has already passed
scores its newest checkpoint: each row's ``steps`` is the step scored, ``milestone`` the
one asked, with a warning when they differ). ``--run RUN`` scores a finished run on its own
data and config (``--preset``, ``--data``, ``--split``, ``--steps`` and ``--set`` are then
ignored, with a warning).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

from motionflows import bench, runs
from motionflows.bench.report import REFERENCE_ROWS
from motionflows.cli_train import add_set_argument
from motionflows.config import apply_overrides
from motionflows.errors import RunError
from motionflows.run import restore_run
from motionflows.training import train
from motionflows.windows import pick, standardized


def _parse_floats(text: str) -> list[float]:
    return [float(t) for t in text.split(",") if t.strip()]


def score(
    run_dir: Path,
    dataset,
    temperatures,
    *,
    windows: int,
    seed: int,
    sample_windows: int,
    split: str = "test",
    checkpoint: str = "latest",
    truth: tuple[dict, dict] | None = None,
):
    """``(rows, nll, gt, refs, step)``: rows of motion metrics (per temperature) and the
    likelihood of a checkpoint, on the windows and controls of ``split``; the ground truth's
    metrics and the bench's two reference rows (:func:`truth_and_references`, or ``truth``
    when given: they depend on the data only, so a run scored at several steps computes them
    once); the training step of the checkpoint scored (a run's best checkpoint can be older
    than its last step). ``dataset=None`` loads the run's own data."""
    import jax

    exp, config, model, saved = restore_run(run_dir, checkpoint=checkpoint)
    if dataset is None:
        dataset = config.data.load()
    key = jax.random.key(seed)
    lik = bench.score_likelihood(
        exp, model, config, dataset, split, limit=windows, key=key, num_bootstrap=200
    )
    part = dataset.split(split)
    idx, gt_m, control_m = _scored_windows(part, sample_windows)
    _, ctrl = standardized(dataset.standardizer, part, idx)
    fps = float(config.data.fps)
    st = dataset.standardizer
    rows = []
    for temp in temperatures:
        sampler = bench.make_sampler(exp, temp)
        samples = bench.sample_in_chunks(sampler, model, ctrl, jax.random.fold_in(key, 20))
        one = np.repeat(ctrl[:1], bench.EVAL_CHUNK, axis=0)
        div = bench.sample_in_chunks(sampler, model, one, jax.random.fold_in(key, 21))[:16]
        metrics = bench.motion_metrics(
            np.asarray(st.denormalize_pose(samples), np.float32),
            control_m,
            gt_m,
            np.asarray(st.denormalize_pose(div), np.float32),
            fps,
        )
        metrics.pop("prediction", None)
        rows.append({"temperature": temp, **metrics})
    nll = {s: r["test"]["nats_per_frame_metres"] if "test" in r else r["nats_per_frame_metres"]
           for s, r in lik.items()}  # fmt: skip
    gt, refs = truth or truth_and_references(dataset, split, sample_windows, fps)
    return rows, nll, gt, refs, int(saved["meta"]["step"])


def _scored_windows(part, sample_windows: int):
    """``(idx, pose (N, T, 63) m, control (N, T, 3))`` of the windows whose controls are
    sampled (the same ``pick`` for every checkpoint and for the ground truth)."""
    idx = pick(part, sample_windows, seed=2)
    return idx, np.asarray(part.pose, np.float32)[idx], np.asarray(part.control, np.float32)[idx]


def truth_and_references(dataset, split: str, sample_windows: int, fps: float):
    """``(gt, refs)``: the motion metrics of the ground truth on the ``sample_windows``
    windows of ``split`` that :func:`score` samples the controls of (its diversity the
    split's natural diversity), and the bench's two reference rows of real training motion
    scored alike (:func:`motionflows.bench.data_references`: the training split of
    ``dataset``, with the run's own augmentation)."""
    part = dataset.split(split)
    _, gt_m, control_m = _scored_windows(part, sample_windows)
    gt = bench.motion_metrics(gt_m, control_m, gt_m, None, fps)
    gt["diversity"] = bench.natural_diversity_of(part)
    return gt, bench.data_references(dataset.train, gt_m, control_m, fps)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("experiment")
    p.add_argument("--preset", default="quick")
    p.add_argument("--data", default="bandai")
    p.add_argument("--split", default="performer", choices=["take", "performer"])
    p.add_argument("--steps", default="400,800")
    p.add_argument("--temperatures", default="1.0,0.8,0.6")
    add_set_argument(p, "change the preset (a config field)")
    p.add_argument("--windows", type=int, default=256, help="test windows scored")
    p.add_argument("--sample-windows", type=int, default=64, help="test controls sampled")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--on", default="test", choices=["val", "test"], help="split scored")
    p.add_argument(
        "--run",
        default=None,
        help="score this run (a path or pretrained:NAME) only, at its best checkpoint "
        "(the `steps` column is that checkpoint's step)",
    )
    p.add_argument("--out", required=True)
    return p


def main(argv=None) -> int:
    """The script; bad input (an unknown experiment or preset, a missing run, a bad
    ``--set``) is one ``error:`` line and exit code 2."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return _main(args, parser)
    except (RunError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2


def _main(args, parser) -> int:
    exp = runs.resolve_experiment(args.experiment)
    if args.preset not in exp.PRESETS:
        raise RunError(f"unknown preset {args.preset!r}; available: {sorted(exp.PRESETS)}")
    config = exp.PRESETS[args.preset]
    data = bench.parse_data_spec(args.data)
    config = dataclasses.replace(
        config,
        data=dataclasses.replace(
            config.data,
            source=data.source,
            path=data.path,
            split_by=args.split,
        ),
    )
    config = apply_overrides(config, args.overrides)
    out = Path(args.out)
    run_dir = out / "run"
    temps = _parse_floats(args.temperatures)
    results = []
    if args.run:  # score an existing run (its own data config) at its best checkpoint
        flags = {"preset": "--preset", "data": "--data", "split": "--split",
                 "steps": "--steps", "overrides": "--set"}  # fmt: skip
        ignored = [flag for k, flag in flags.items() if getattr(args, k) != parser.get_default(k)]
        if ignored:
            print(f"warning: {', '.join(ignored)} ignored with --run: the run is scored on "
                  "its own data and config", file=sys.stderr)  # fmt: skip
        run_path = runs.resolve_run_dir(args.run)  # a path or pretrained:NAME
        rows, nll, gt, refs, step = score(run_path, None, temps, windows=args.windows,
                                    seed=args.seed, sample_windows=args.sample_windows,
                                    split=args.on, checkpoint="best")  # fmt: skip
        results = [{"steps": step, "train_s": None, "nll": nll, **row} for row in rows]
        for rec in results:
            print(json.dumps(rec), flush=True)
        _write(out, results, gt, refs)
        return 0
    dataset = config.data.load()
    truth = truth_and_references(dataset, args.on, args.sample_windows, float(config.data.fps))
    for steps in [int(s) for s in args.steps.split(",")]:
        t0 = time.perf_counter()
        cfg = dataclasses.replace(config, train=dataclasses.replace(config.train, steps=steps))
        resume = (run_dir / "config.json").is_file()
        train(exp, cfg, run_dir=run_dir, preset=args.preset, resume=resume, dataset=dataset,
              progress=False)  # fmt: skip
        train_s = time.perf_counter() - t0
        rows, nll, gt, refs, scored = score(
            run_dir,
            dataset,
            temps,
            windows=args.windows,
            seed=args.seed,
            sample_windows=args.sample_windows,
            split=args.on,
            truth=truth,
        )
        if scored != steps:  # a run already past the milestone, or stopped early
            print(f"warning: milestone {steps} scored the checkpoint of step {scored}",
                  file=sys.stderr)  # fmt: skip
        for row in rows:
            rec = {"steps": scored, "milestone": steps, "train_s": train_s, "nll": nll, **row}
            results.append(rec)
            print(json.dumps(rec), flush=True)
    _write(out, results, gt, refs)
    return 0


def _write(out: Path, results: list[dict], gt: dict, refs: dict | None) -> None:
    """``OUT/quality.jsonl`` and the report (:func:`write_report`)."""
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "quality.jsonl", "w") as fh:
        for rec in results:
            fh.write(json.dumps(rec) + "\n")
    write_report(out, results, gt, " ".join(sys.argv), refs)


COLUMNS = ("foot_sliding", "skate_ratio", "contact_rate", "bone_length_std", "jerk",
           "fd_pose", "fd_window3", "diversity", "diverged")  # fmt: skip


def write_report(
    out: Path, results: list[dict], gt: dict, command: str, refs: dict | None = None
) -> None:
    """QUALITY.md (a table) and quality.png (jerk and FD against steps per temperature).
    ``refs``: the reference rows of real training motion (:func:`score`), under the ground
    truth's."""
    scopes = sorted(results[0]["nll"]) if results else []

    def metric_cells(row: dict) -> list[str]:
        return [f"{row[c]:.3f}" if row.get(c) is not None else "n/a" for c in COLUMNS]

    head = ["steps", "T", *COLUMNS, *(f"NLL {s}" for s in scopes)]
    lines = [f"`{command}`", "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines.append(
        "| ground truth | | "
        + " | ".join(f"{gt.get(c, float('nan')) or 0:.3f}" for c in COLUMNS)
        + " |" * (len(scopes) + 1)
    )
    for ref, label in REFERENCE_ROWS.items():
        row = (refs or {}).get(ref)
        if row:
            cells = metric_cells(row)
            lines.append(f"| *{label}* | | " + " | ".join(cells) + " |" * (len(scopes) + 1))
    for r in results:
        cells = [str(r["steps"]), f"{r['temperature']:g}", *metric_cells(r)]
        cells += [f"{r['nll'][s]:.1f}" for s in scopes]
        lines.append("| " + " | ".join(cells) + " |")
    if refs:
        note = (
            "Reference rows in italics: real motion of the training split, with the run's own"
            " augmentation (mirrored, tempo or foot-locked takes where its data config asks),"
            " scored like the samples (motionflows.bench.data_references)."
        )
        lines += ["", note]
    (out / "QUALITY.md").write_text("\n".join(lines) + "\n")
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.5))
    for ax, metric in zip(axes, ("jerk", "fd_pose", "foot_sliding"), strict=True):
        for temp in sorted({r["temperature"] for r in results}, reverse=True):
            rs = [r for r in results if r["temperature"] == temp]
            ax.plot([r["steps"] for r in rs], [r[metric] for r in rs], "o-", label=f"T={temp:g}")
        ax.axhline(gt.get(metric) or 0.0, color="k", ls="--", lw=1, label="ground truth")
        ax.set_xlabel("training steps")
        ax.set_title(metric)
        ax.set_xscale("log")
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "quality.png", dpi=90)
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())
