"""``motionflows bench`` (and ``python -m motionflows.bench``): flags -> the bench library.

motionflows bench --data synthetic --budget quick --out runs/bench
motionflows bench --data bandai --budget cpu --estimate
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path

from motionflows.bench.budgets import BUDGETS
from motionflows.errors import MotionDataError, RunError


def build_parser(parser: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    """The ``motionflows bench`` arguments (added to ``parser`` if given)."""
    p = parser or argparse.ArgumentParser(
        prog="motionflows bench",
        description="Train (or reuse) every model on one split and write a comparison report.",
    )
    p.add_argument("--data", default="synthetic", help="synthetic (default) | bandai | bvh:DIR")
    p.add_argument(
        "--models",
        default=None,
        help="comma-separated model names (default: every model of every experiment "
        "registered in the motionflows.experiments entry points)",
    )
    p.add_argument(
        "--budget",
        default="quick",
        choices=list(BUDGETS),
        help="smoke: CI-sized (each experiment's smoke preset); quick: the quick presets; "
        "cpu: the cpu presets (<= 60 min of training per model on 2 cores); full: the "
        "paper presets",
    )
    p.add_argument("--out", default="runs/bench", help="report folder")
    p.add_argument(
        "--test-data",
        default=None,
        help="score every table on these takes instead of the test split: bvh:DIR, "
        "bandai:DIR or a folder (e.g. a performer the models never saw)",
    )
    p.add_argument("--runs-dir", default="runs", help="where runs are found and trained")
    p.add_argument("--temperature", type=float, default=1.0, help="sampling temperature")
    p.add_argument("--seed", type=int, default=0, help="seed of the scoring and sampling keys")
    from motionflows.cli_train import add_cpu_devices_argument, add_set_argument

    add_set_argument(
        p,
        "config changes for every model whose config has the key (dotted or unique bare "
        "names, as in `motionflows train --set`), e.g. train.seed=1 for a second training "
        "seed; changed runs are trained, not reused, unless only an experiment's "
        "SAMPLING_FIELDS differ (e.g. sampler=prior); data.* keys are refused (use --data)",
    )
    p.add_argument(
        "--performer-split",
        dest="performer_split",
        action="store_true",
        default=None,
        help="also train and score a split by performer (default: on for bandai)",
    )
    p.add_argument("--no-performer-split", dest="performer_split", action="store_false")
    p.add_argument("--retrain", action="store_true", help="train even if a finished run exists")
    p.add_argument("--no-gifs", dest="gifs", action="store_false", help="skip the GIFs")
    p.add_argument(
        "--no-progress",
        dest="training_bars",
        action="store_false",
        help="no training progress bars (the time-stamped bench lines stay): for a log file",
    )
    p.add_argument(
        "--estimate",
        action="store_true",
        help="only time a few training steps per model and print the projected "
        "training time of the budget on this machine (writes OUT/estimate.json)",
    )
    p.add_argument(
        "--foot-lock",
        action="store_true",
        help="also score each model's samples after the foot-lock post-process (extra rows)",
    )
    add_cpu_devices_argument(p)
    return p


def _estimate(args: argparse.Namespace, names: tuple[str, ...]) -> None:
    from motionflows.bench.benchmark import jsonable
    from motionflows.bench.estimate import estimate_training

    est = estimate_training(args.data, names, args.budget, overrides=args.overrides)
    Path(args.out).mkdir(parents=True, exist_ok=True)
    (Path(args.out) / "estimate.json").write_text(json.dumps(jsonable(est), indent=2))
    for name, e in est["models"].items():
        sps = e["seconds_per_step"]
        per = (
            f"{sps:.3f} s/step x {e['steps']} steps + {e['validations']} validation"
            f"{'' if e['validations'] == 1 else 's'} x {e['validation_seconds']:.1f} s"
            if sps
            else e.get("note", "")
        )
        print(f"{name:>10}: {per} = {e['projected_hours']:.2f} h")
    print(
        f"{'total':>10}: {est['total_hours']:.2f} h of training ({args.budget} budget, "
        f"{est['machine']['cpu']}, {est['machine']['cores']} cores)"
    )


def _command(args: argparse.Namespace, names: tuple[str, ...]) -> str:
    from motionflows.bench.benchmark import command_line

    extra = f" --test-data {args.test_data}" if args.test_data else ""
    if args.temperature != 1.0:
        extra += f" --temperature {args.temperature:g}"
    if args.seed:
        extra += f" --seed {args.seed}"
    if args.runs_dir != "runs":  # which runs a bench reuses is part of what it scored
        extra += f" --runs-dir {args.runs_dir}"
    if args.performer_split is not None:
        extra += " --performer-split" if args.performer_split else " --no-performer-split"
    if args.overrides:
        extra += " --set " + " ".join(args.overrides)
    if args.foot_lock:
        extra += " --foot-lock"
    if args.cpu_devices is not None:
        extra += f" --cpu-devices {args.cpu_devices}"
    return command_line(args.data, names, args.budget, args.out, extra)


def main(args: argparse.Namespace | Sequence[str] | None = None) -> int:
    """``motionflows bench``: ``args`` is a parsed Namespace (from the CLI) or an argv list;
    returns the exit code (2 with one line on stderr for a user error)."""
    if args is None or isinstance(args, list | tuple):
        args = build_parser().parse_args(list(args) if args is not None else None)
    from motionflows import distributed
    from motionflows.bench.benchmark import run_benchmark
    from motionflows.bench.budgets import parse_models

    try:
        distributed.simulate_cpu_devices(args.cpu_devices)  # before JAX starts
        distributed.configure_cpu_threads()
        distributed.check_cpu_devices(args.cpu_devices)
        names = parse_models(args.models)
        if args.estimate:
            _estimate(args, names)
            return 0
        run_benchmark(
            data=args.data, models=names, budget=args.budget, out=args.out,
            runs_dir=args.runs_dir, temperature=args.temperature, seed=args.seed,
            performer_split=args.performer_split, retrain=args.retrain, gifs=args.gifs,
            command=_command(args, names), test_data=args.test_data, overrides=args.overrides,
            training_bars=args.training_bars, foot_lock=args.foot_lock,
        )  # fmt: skip
    except (RunError, ValueError, MotionDataError) as err:
        print(f"motionflows bench: error: {err}", file=sys.stderr)
        return 2
    print(f"report: {Path(args.out) / 'BENCHMARK.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
