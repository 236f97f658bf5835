"""``make demo``: train the best available model at ``quick`` on synthetic data, then show it.

Picks the first experiment that imports: ``moglow``, then ``glow_fixed``, then the
closed-form ``baselines`` (linear-Gaussian AR). Trains its ``quick`` preset on the
embedded synthetic data (progress bar with ETA on stderr), prints the test-split
likelihood table (nats/frame in metres and bits/frame standardised), samples the
``walk-turn-run`` control and writes the sample (npz, metres) and its GIF under
``<run>/samples/``.

    python -m motionflows.demo [--experiment NAME] [--steps N] [--seconds S] [--runs-dir DIR]
                               [--set key=value ...]
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

CANDIDATES = ("moglow", "glow_fixed", "baselines")


def choose_experiment(names=CANDIDATES, *, verbose: bool = True):
    """The first experiment module in ``names`` that imports and has a ``quick`` preset."""
    from motionflows.runs import resolve_experiment

    for name in names:
        try:
            module = resolve_experiment(name)
        except Exception as err:  # a model still being written must not break the demo
            if verbose:
                print(f"demo: skipping {name} ({type(err).__name__}: {err})", file=sys.stderr)
            continue
        if "quick" in module.PRESETS:
            return module
    raise RuntimeError(f"none of the experiments {names} is available")


def _sample_length(config, seconds: float) -> int:
    return max(1, int(round(seconds * float(config.data.fps))))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m motionflows.demo", description=__doc__)
    parser.add_argument("--experiment", default=None, help=f"one of {', '.join(CANDIDATES)}")
    parser.add_argument("--steps", type=int, default=None, help="override the quick steps")
    parser.add_argument("--seconds", type=float, default=8.0, help="length of the sample")
    parser.add_argument("--control", default="walk-turn-run")
    parser.add_argument("--runs-dir", default="runs")
    parser.add_argument(
        "--set",
        dest="overrides",
        nargs="+",
        default=[],
        metavar="KEY=VALUE",
        help="config overrides, as for `motionflows train`",
    )
    parser.add_argument("--no-gif", action="store_true")
    args = parser.parse_args(argv)

    from motionflows import training
    from motionflows.config import apply_overrides
    from motionflows.data.controls import load_control
    from motionflows.errors import RunError

    t0 = time.perf_counter()
    try:
        module = choose_experiment((args.experiment,) if args.experiment else CANDIDATES)
    except RuntimeError as err:
        print(f"demo: {err}", file=sys.stderr)
        return 2
    config = module.PRESETS["quick"]
    config = dataclasses.replace(config, data=dataclasses.replace(config.data, source="synthetic"))
    if args.steps is not None:
        config = dataclasses.replace(
            config, train=dataclasses.replace(config.train, steps=args.steps)
        )
    try:
        config = apply_overrides(config, args.overrides)
    except ValueError as err:
        print(f"demo: {err}", file=sys.stderr)
        return 2
    run_dir = Path(args.runs_dir) / module.NAME / f"demo-{time.strftime('%Y%m%d-%H%M%S')}"
    print(
        f"== motionflows demo: {module.NAME} (preset quick, {config.train.steps} steps) on "
        f"synthetic data -> {run_dir}",
        file=sys.stderr,
    )
    print("== loading the synthetic data (generated once, then cached)", file=sys.stderr)
    dataset = config.data.load()
    result = training.train(module, config, run_dir=run_dir, preset="quick", dataset=dataset)
    if result.status not in ("finished", "fitted"):
        print(f"demo: training stopped ({result.status}); see {run_dir}", file=sys.stderr)
        return 1

    print("\n== test-split likelihood", file=sys.stderr)
    training.evaluate_run(run_dir, "test", dataset=dataset)

    _, _, model, _ = training.load_run(run_dir, dataset=dataset)
    fps = float(config.data.fps)
    control = load_control(args.control, args.seconds, fps)
    try:
        pose = training.draw_samples(module, model, dataset.standardizer, control, seed=0)
    except (ValueError, TypeError) as err:  # e.g. a fixed-length model: one window only
        n = int(config.data.window)
        print(
            f"demo: sampling {len(control)} frames failed ({err}); sampling one "
            f"{n}-frame window instead",
            file=sys.stderr,
        )
        control = load_control(args.control, n / fps, fps)
        pose = training.draw_samples(module, model, dataset.standardizer, control, seed=0)
    except RunError as err:
        print(f"demo: {err}", file=sys.stderr)
        return 1
    out = run_dir / "samples"
    out.mkdir(parents=True, exist_ok=True)
    npz = out / f"demo_{args.control}.npz"
    np.savez(npz, pose=pose, control=control, fps=fps)
    print(f"\n== sample: {npz} (pose {pose.shape[1:]} metres)", file=sys.stderr)
    if not args.no_gif:
        from motionflows import render

        print("== rendering the GIF", file=sys.stderr)
        gif = render.animate(
            pose[0],
            control,
            out / f"demo_{args.control}.gif",
            fps=fps,
            title=f"{module.NAME}: {args.control}",
        )
        render.plot_controls(
            control, out / f"demo_{args.control}_control.png", fps, title=args.control
        )
        print(f"== GIF: {gif}", file=sys.stderr)
    minutes = (time.perf_counter() - t0) / 60
    print(
        f"\n== done in {minutes:.1f} min. Next:\n"
        f"   motionflows sample {run_dir} --control figure-eight --seconds 10 --num 3\n"
        f"   motionflows eval {run_dir} --split test\n"
        f"   motionflows runs",
        file=sys.stderr,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
