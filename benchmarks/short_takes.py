"""Motion quality on the takes shorter than a window: on Bandai, nearly every run.

The bench scores complete windows only (``motionflows.windows``: a padded window is not
motion), and the Bandai runs of most styles (every one of D2-C's) last 2.0-3.8 s, less than
the bench's 4 s window: so the bench's motion table holds walks and turns, and no running.
This script scores the short takes with the bench's metrics (``motionflows.bench.
motion_metrics``, the calibrated contact rule) on frames ``--skip`` .. ``--frames`` - 1 of
each:

* **short takes**: the split's padded windows with at least ``--frames`` recorded frames;
* **complete windows**: the split's complete windows (the bench's), cut to the same frames,
  so that both rows are scored alike.

Each model samples the whole window: a padded window's control holds the take's last
recorded control over the padded frames (running on, not the zero control the padding
stores), so a model that reads the whole control (the fixed-length Glow, the VAE-LSTM)
sees a run that goes on; a causal MoGlow's first ``--frames`` frames do not depend on it.
The models start from a mean-pose history (the bench's rule) while a Bandai run take
starts at full speed, so ``--skip 10`` leaves out the first half second, the start-up.
The ground truth of the same frames is each row's reference (FDs) and is scored as its
own row. Diversity is left out (one short take per control). Prints one JSON object per
(run, row, temperature) after a line with the machine and its load, and writes
``OUT/short_takes.jsonl`` and ``OUT/SHORT_TAKES.md``::

    python benchmarks/short_takes.py runs/moglow/RUN runs/vae_lstm/RUN --temperatures 0.8 \\
        --skip 10 --out runs/short_takes
    python benchmarks/short_takes.py pretrained:moglow-bandai --temperatures 0.6,0.8

A run is scored on its own data and split (the bench's runs on Bandai: the unseen
performer's test takes; a pretrained model: the test takes of its split by take).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
from pathlib import Path

from motionflows import bench, runs
from motionflows.bench.benchmark import jsonable
from motionflows.bench.short_takes import drawing, score_short_takes, short_windows, take_kinds
from motionflows.errors import RunError
from motionflows.run import restore_run
from motionflows.windows import complete_windows, subset

ROWS = ("short_takes", "complete_windows")
COLUMNS = (
    ("foot_sliding", "foot sliding, m/s"),
    ("contact_rate", "contact rate"),
    ("bone_length_std", "bone-length std, m"),
    ("jerk", "jerk, m/s^3"),
    ("fd_pose", "pose FD, m^2"),
    ("fd_window3", "3-frame FD, m^2"),
    ("diverged", "diverged"),
)


def score_run(
    run: str, temperatures, *, frames: int, limit: int, seed: int, skip: int = 0
) -> list[dict]:
    """Rows ``{run, row, temperature, windows, kinds, step, **metrics}`` of one run: the
    ground truth (temperature None) and its samples at each temperature, on the short
    takes and on the complete windows of its test split."""
    import jax

    exp, config, model, saved = restore_run(runs.resolve_run_dir(run))
    dataset = config.data.load()
    part, fps = dataset.split("test"), float(config.data.fps)
    if part.window < frames:
        raise RunError(f"--frames {frames} is longer than the run's {part.window}-frame window")
    picked = {
        "short_takes": short_windows(part, frames),
        "complete_windows": complete_windows(part),
    }
    key, st = jax.random.key(seed), dataset.standardizer
    samplers = [bench.make_sampler(exp, temp) for temp in temperatures]  # compiled once each
    out = []
    for r, name in enumerate(ROWS):
        idx = picked[name]
        idx = idx[subset(len(idx), limit, seed=2)]
        if len(idx) == 0:
            print(f"{run}: no {name.replace('_', ' ')} of {frames}+ frames in its test split",
                  file=sys.stderr)  # fmt: skip
            continue
        head = {"run": run, "row": name, "windows": len(idx), "kinds": take_kinds(part, idx),
                "step": int(saved["meta"]["step"]), "frames": [skip, frames]}  # fmt: skip
        gt = score_short_takes(part, idx, (skip, frames), fps)
        out.append({**head, "temperature": None, **gt})
        for t, (temp, sampler) in enumerate(zip(temperatures, samplers, strict=True)):
            sample = drawing(sampler, model, st, jax.random.fold_in(key, 10 * r + t))
            metrics = score_short_takes(part, idx, (skip, frames), fps, sample=sample)
            out.append({**head, "temperature": temp, **metrics})
    return out


def markdown(rows: list[dict], command: str) -> str:
    """A table per run: ground truth and samples, short takes beside complete windows."""
    lines = [f"# Motion on the short takes\n\n`{command}`\n"]
    for run in dict.fromkeys(r["run"] for r in rows):
        mine = [r for r in rows if r["run"] == run]
        first, last = mine[0]["frames"]
        lines.append(f"\n## {run} (step {mine[0]['step']}), frames {first}..{last - 1} of each\n")
        lines.append(
            "| rows | windows (takes' motions) | " + " | ".join(c for _, c in COLUMNS) + " |"
        )
        lines.append("|---|---|" + "---:|" * len(COLUMNS))
        for r in mine:
            who = "ground truth" if r["temperature"] is None else f"samples, T {r['temperature']:g}"
            kinds = ", ".join(f"{k} {n}" for k, n in r["kinds"].items())
            cells = " | ".join(
                "n/a" if r.get(k) is None else f"{r[k]:.3f}" if k != "jerk" else f"{r[k]:.1f}"
                for k, _ in COLUMNS
            )
            lines.append(
                f"| {r['row'].replace('_', ' ')}: {who} | {r['windows']} ({kinds}) | {cells} |"
            )
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="+", help="run directories or pretrained:NAME")
    p.add_argument("--temperatures", default="0.8", help="comma-separated")
    p.add_argument("--frames", type=int, default=40, help="frames sampled from each take's start")
    p.add_argument("--skip", type=int, default=0, help="of those, frames left out of the scores")
    p.add_argument("--windows", type=int, default=256, help="at most this many of each row")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="runs/short_takes")
    args = p.parse_args(argv)
    temperatures = [float(t) for t in args.temperatures.split(",") if t.strip()]
    if not 0 <= args.skip <= args.frames - 4:
        print(f"error: --skip {args.skip} must leave at least 4 of the {args.frames} frames "
              "scored (0 <= skip <= frames - 4)", file=sys.stderr)  # fmt: skip
        return 2
    print(json.dumps({"machine": platform.machine(), "cpus": os.cpu_count(),
                      "load_average": os.getloadavg()[0]}))  # fmt: skip
    rows = []
    try:
        for run in args.runs:
            for row in score_run(run, temperatures, frames=args.frames, limit=args.windows,
                                 seed=args.seed, skip=args.skip):  # fmt: skip
                print(json.dumps(jsonable(row)), flush=True)
                rows.append(row)
    except RunError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "short_takes.jsonl", "w") as f:
        f.writelines(json.dumps(jsonable(r)) + "\n" for r in rows)
    command = "python benchmarks/short_takes.py " + " ".join(argv or sys.argv[1:])
    (out / "SHORT_TAKES.md").write_text(markdown(rows, command))
    print(f"wrote {out / 'SHORT_TAKES.md'}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
