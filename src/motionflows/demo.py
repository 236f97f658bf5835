"""``make demo``: the shipped MoGlow walks, turns and runs; then a model trains from scratch.

1. Samples the ``walk-turn-run`` control (8 s) from the pretrained ``moglow-bandai`` model
   (:mod:`motionflows.pretrained`: seconds, no training) and writes the sample (npz,
   metres), its GIF and a PNG still under ``<runs-dir>/demo/``, then the same sample with
   its planted feet held (:mod:`motionflows.foot_lock`, files ``*_foot-lock.*``).
2. Trains an experiment's ``quick`` preset (MoGlow by default) on the embedded synthetic
   data (progress bar with ETA on stderr), prints the test-split likelihood table
   (nats/frame in metres and bits/frame standardised), and samples and animates the same
   control under ``<run>/samples/``.

    python -m motionflows.demo [--experiment NAME] [--steps N] [--seconds S] [--runs-dir DIR]
                               [--no-pretrained] [--no-train] [--set key=value ...]
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

PRETRAINED = "moglow-bandai"


def _write(pose, control, fps: float, out: Path, stem: str, title: str, gif: bool) -> None:
    """npz (metres) + GIF + PNG still of one sample."""
    out.mkdir(parents=True, exist_ok=True)
    np.savez(out / f"{stem}.npz", pose=pose, control=control, fps=fps)
    print(f"== sample: {out / f'{stem}.npz'} (pose {pose.shape} metres)", file=sys.stderr)
    if gif:
        from motionflows import render

        path = render.animate(pose, control, out / f"{stem}.gif", fps=fps, title=title)
        print(f"== GIF: {path}", file=sys.stderr)


def pretrained_demo(control_name: str, seconds: float, out: Path, *, gif: bool = True) -> bool:
    """Sample and animate the shipped MoGlow; False (with a note) when it is not installed."""
    from motionflows import pretrained
    from motionflows.data.controls import load_control

    if PRETRAINED not in pretrained.available():
        print(f"demo: no pretrained {PRETRAINED} in this install; skipping", file=sys.stderr)
        return False
    t0 = time.perf_counter()
    model = pretrained.load(PRETRAINED)
    control = load_control(control_name, seconds, model.fps)
    pose = model.sample(control[None], seed=0)[0]
    print(
        f"== pretrained {PRETRAINED} ({model!r}): {control_name}, {seconds:g} s sampled in "
        f"{time.perf_counter() - t0:.1f} s",
        file=sys.stderr,
    )
    title = f"pretrained {PRETRAINED}: {control_name} (T={model.temperature:g})"
    _write(pose, control, model.fps, out, f"{PRETRAINED}_{control_name}", title, gif)
    from motionflows.foot_lock import foot_lock

    locked = foot_lock(pose, control)
    stem = f"{PRETRAINED}_{control_name}_foot-lock"
    _write(locked, control, model.fps, out, stem, f"{title}, foot lock", gif)
    return True


def train_demo(args) -> int:
    """Train the quick preset on synthetic data, score it, sample and animate the control."""
    from motionflows import run, training
    from motionflows.config import apply_overrides
    from motionflows.data.controls import load_control
    from motionflows.runs import resolve_experiment

    module = resolve_experiment(args.experiment)
    config = module.PRESETS["quick"]
    config = dataclasses.replace(config, data=dataclasses.replace(config.data, source="synthetic"))
    if args.steps is not None:
        config = dataclasses.replace(
            config, train=dataclasses.replace(config.train, steps=args.steps)
        )
    config = apply_overrides(config, args.overrides)
    run_dir = Path(args.runs_dir) / module.NAME / f"demo-{time.strftime('%Y%m%d-%H%M%S')}"
    print(
        f"\n== training {module.NAME} (preset quick, {config.train.steps} steps) on synthetic "
        f"data -> {run_dir}",
        file=sys.stderr,
    )
    dataset = config.data.load()
    print(f"== data: {dataset.summary()}", file=sys.stderr)
    result = training.train(module, config, run_dir=run_dir, preset="quick", dataset=dataset)
    if result.status not in ("finished", "fitted"):
        print(f"demo: training stopped ({result.status}); see {run_dir}", file=sys.stderr)
        return 1
    print("\n== test-split likelihood", file=sys.stderr)
    run.evaluate_run(run_dir, "test", dataset=dataset)
    _, _, model, _ = run.load_run(run_dir, dataset=dataset)
    fps = float(config.data.fps)
    control = load_control(args.control, args.seconds, fps)
    pose = run.draw_samples(module, model, dataset.standardizer, control, seed=0)
    title = f"{module.NAME} quick: {args.control}"
    _write(pose[0], control, fps, run_dir / "samples", f"demo_{args.control}", title, args.gif)
    print(
        f"\n== next:\n   motionflows sample {run_dir} --control figure-eight --seconds 10 --num 3\n"
        f"   motionflows sample pretrained:{PRETRAINED} --control ../shared/data/"
        "bandai_locomotion_dev/dataset-2_walk-turn-left_normal_001.bvh\n"
        f"   motionflows eval {run_dir} --split test\n   motionflows runs",
        file=sys.stderr,
    )
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The demo's flags (``python -m motionflows.demo --help``)."""
    from motionflows.cli_train import add_set_argument

    parser = argparse.ArgumentParser(prog="python -m motionflows.demo", description=__doc__)
    parser.add_argument("--experiment", default="moglow", help="the experiment to train")
    parser.add_argument("--steps", type=int, default=None, help="override the quick steps")
    parser.add_argument("--seconds", type=float, default=8.0, help="length of the samples")
    parser.add_argument("--control", default="walk-turn-run")
    parser.add_argument("--runs-dir", default="runs")
    parser.add_argument("--no-pretrained", dest="pretrained", action="store_false")
    parser.add_argument("--no-train", dest="train", action="store_false")
    parser.add_argument("--no-gif", dest="gif", action="store_false")
    add_set_argument(parser, "config overrides of the trained model, as for `motionflows train`")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from motionflows.errors import MotionflowsError

    t0 = time.perf_counter()
    if Path(args.runs_dir).exists() and not Path(args.runs_dir).is_dir():
        print(f"demo: --runs-dir {args.runs_dir} is a file: give a folder", file=sys.stderr)
        return 2
    try:
        if args.pretrained:
            out = Path(args.runs_dir) / "demo"
            pretrained_demo(args.control, args.seconds, out, gif=args.gif)
        code = train_demo(args) if args.train else 0
    except (MotionflowsError, ValueError, OSError) as err:  # OSError: a folder not writable
        print(f"demo: {err}", file=sys.stderr)
        return 2
    print(f"\n== done in {(time.perf_counter() - t0) / 60:.1f} min", file=sys.stderr)
    return code


if __name__ == "__main__":
    sys.exit(main())
