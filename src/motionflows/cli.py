"""The ``motionflows`` command: train, eval, sample, render, runs, data, bench.

    motionflows train moglow --preset quick --data synthetic --steps 2000 --set train.lr=1e-3
    motionflows train moglow --run-name quick-1 --resume
    motionflows eval runs/moglow/quick-1 --split test
    motionflows sample runs/moglow/quick-1 --control walk-turn-run --seconds 8 --num 4
    motionflows render take.bvh --out renders/        (or an .npz with pose / control)
    motionflows runs
    motionflows data download bandai --dest data/bandai
    motionflows bench --data synthetic --budget quick --out runs/bench

User errors (unknown experiment, missing run directory, bad flags or values) print one
line on stderr and exit with code 2.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

from motionflows.errors import RunError


class _Parser(argparse.ArgumentParser):
    """argparse that reports a bad flag as one line and exit code 2."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


# ---------------------------------------------------------------------------- commands


def cmd_train(args) -> int:
    from motionflows import training

    return training.run_train(args.experiment, args)


def cmd_eval(args) -> int:
    from motionflows import runs, training

    runs.check_run_dir(args.run_dir)
    training.evaluate_run(
        args.run_dir, args.split, checkpoint=args.checkpoint, batch_size=args.batch_size
    )
    print(f"wrote {Path(args.run_dir) / f'eval_{args.split}.json'}", file=sys.stderr)
    return 0


def cmd_sample(args) -> int:
    from motionflows import runs, training
    from motionflows.data.controls import load_control

    run_dir = runs.check_run_dir(args.run_dir)
    if args.num < 1 or args.seconds <= 0:
        raise RunError("--num must be >= 1 and --seconds > 0")
    module, config, model, _ = training.load_run(
        run_dir, checkpoint=args.checkpoint, load_data=False
    )
    std = training.load_standardizer(run_dir)
    fps = float(config.data.fps)
    control = load_control(args.control, args.seconds, fps)  # (T, 3) m/frame, rad/frame
    temperature = float(args.temperature)
    pose = training.draw_samples(
        module, model, std, control, num=args.num, temperature=temperature, seed=args.seed
    )
    out = Path(args.out) if args.out else run_dir / "samples"
    out.mkdir(parents=True, exist_ok=True)
    stem = f"{Path(str(args.control)).stem}_T{temperature:g}_seed{args.seed}"
    npz = out / f"{stem}.npz"
    np.savez(
        npz,
        pose=pose,
        control=control,
        fps=fps,
        temperature=temperature,
        seed=args.seed,
        experiment=module.NAME,
        run_dir=str(run_dir),
    )
    print(f"wrote {npz}: pose {pose.shape} metres, control {control.shape}", file=sys.stderr)
    if not args.no_gif:
        from motionflows import render

        for i in range(args.num):
            gif = render.animate(
                pose[i],
                control,
                out / f"{stem}_{i}.gif",
                fps=fps,
                title=f"{module.NAME} {args.control} #{i}",
            )
            print(f"wrote {gif}", file=sys.stderr)
        render.plot_controls(control, out / f"{stem}_control.png", fps, title=str(args.control))
    return 0


def cmd_render(args) -> int:
    from motionflows import render

    path = Path(args.path)
    if not path.is_file():
        raise RunError(f"{path} not found (give a .bvh file or an .npz with pose and control)")
    out = Path(args.out)
    if path.suffix.lower() == ".bvh":
        from motionflows.data import clip_from_bvh

        clip = clip_from_bvh(path, fps=args.fps, skeleton=args.skeleton)
        files = render.render_clip(clip, out)
        for f in files.values():
            print(f"wrote {f}", file=sys.stderr)
        return 0
    if path.suffix.lower() != ".npz":
        raise RunError(f"{path}: render reads .bvh or .npz files")
    with np.load(path, allow_pickle=False) as data:
        if "pose" not in data or "control" not in data:
            raise RunError(
                f"{path} must hold arrays 'pose' (T, 63) or (N, T, 63) metres and 'control' (T, 3)"
            )
        pose, control = np.asarray(data["pose"]), np.asarray(data["control"])
        fps = float(data["fps"]) if "fps" in data else args.fps
    poses = pose[None] if pose.ndim == 2 else pose
    controls = (
        control if control.ndim == 3 else np.broadcast_to(control, (len(poses), *control.shape))
    )
    for i, (p, c) in enumerate(zip(poses, controls, strict=True)):
        gif = render.animate(p, c, out / f"{path.stem}_{i}.gif", fps=fps, title=f"{path.stem} #{i}")
        print(f"wrote {gif}", file=sys.stderr)
    png = render.plot_controls(controls[0], out / f"{path.stem}_control.png", fps, title=path.stem)
    print(f"wrote {png}", file=sys.stderr)
    return 0


def cmd_runs(args) -> int:
    from motionflows import runs

    found = runs.list_runs(args.root)
    if not found:
        print(f"no runs under {args.root}/ (train one with `motionflows train <experiment>`)")
        return 0
    print(runs.format_runs(found))
    return 0


def cmd_data(args) -> int:
    if args.data_command != "download":
        raise RunError("usage: motionflows data download bandai --dest DIR")
    if args.dataset != "bandai":
        raise RunError(f"unknown dataset {args.dataset!r}; downloadable: bandai")
    from motionflows.data.download import BASE_URL, download_bandai

    base_url = args.url or os.environ.get("MOTIONFLOWS_BANDAI_URL") or BASE_URL
    download_bandai(args.dest, base_url=base_url)
    return 0


def cmd_bench(args) -> int:
    try:
        from motionflows import bench
    except ImportError:
        raise RunError("the benchmark (motionflows.bench) is not available yet") from None
    return int(bench.main(args) or 0)


# ----------------------------------------------------------------------------- parser


def build_parser() -> argparse.ArgumentParser:
    from motionflows.training import add_train_arguments

    parser = _Parser(
        prog="motionflows", description="Probabilistic, controllable motion models in JAX."
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True

    p = sub.add_parser("train", help="train an experiment (experiments/<name>.py)")
    p.add_argument("experiment", help="experiment name, e.g. moglow, glow_fixed, baselines")
    add_train_arguments(p)
    p.set_defaults(func=cmd_train)

    p = sub.add_parser("eval", help="likelihood table of a run (writes eval_<split>.json)")
    p.add_argument("run_dir")
    p.add_argument("--split", default="test", choices=["train", "val", "test"])
    p.add_argument("--checkpoint", default="best", choices=["best", "latest"])
    p.add_argument("--batch-size", type=int, default=None)
    p.set_defaults(func=cmd_eval)

    p = sub.add_parser("sample", help="sample motion for a control (npz + GIF)")
    p.add_argument("run_dir")
    p.add_argument(
        "--control",
        default="walk-turn-run",
        help="a control preset (stand, walk, run, walk-turn-left, walk-then-run, "
        "walk-turn-run, figure-eight, ...) or a (T, 3) .npy file",
    )
    p.add_argument("--seconds", type=float, default=8.0)
    p.add_argument("--num", type=int, default=1, help="number of samples")
    p.add_argument("--temperature", type=float, default=1.0)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=None, help="output folder (default: <run>/samples)")
    p.add_argument("--checkpoint", default="best", choices=["best", "latest"])
    p.add_argument("--no-gif", action="store_true", help="only write the npz")
    p.set_defaults(func=cmd_sample)

    p = sub.add_parser("render", help="GIF + control plot of a .bvh or .npz (pose, control)")
    p.add_argument("path")
    p.add_argument("--out", default="renders", help="output folder")
    p.add_argument("--fps", type=float, default=20.0)
    p.add_argument("--skeleton", default="bandai", help="skeleton mapping of a BVH file")
    p.set_defaults(func=cmd_render)

    p = sub.add_parser("runs", help="table of runs with their best validation NLL")
    p.add_argument("--root", default="runs")
    p.set_defaults(func=cmd_runs)

    p = sub.add_parser("data", help="data utilities: download bandai --dest DIR")
    dsub = p.add_subparsers(dest="data_command", metavar="ACTION", parser_class=_Parser)
    dsub.required = True
    d = dsub.add_parser("download", help="download a dataset")
    d.add_argument("dataset", help="bandai")
    d.add_argument("--dest", required=True, help="folder to download into")
    d.add_argument(
        "--url",
        default=None,
        help="base URL of the dataset repository's files (default: $MOTIONFLOWS_BANDAI_URL, "
        "else GitHub raw at the pinned commit), e.g. a local mirror",
    )
    p.set_defaults(func=cmd_data)

    p = sub.add_parser("bench", help="compare every model on one split (BENCHMARK.md)")
    try:
        from motionflows import bench

        bench.build_parser(p)
    except (ImportError, AttributeError):
        p.add_argument("--data", default="synthetic", help="synthetic | bandai | bvh:DIR")
        p.add_argument("--models", default="glow_fixed,moglow,vae_lstm,gaussian,linear_ar")
        p.add_argument("--budget", default="quick", choices=["smoke", "quick", "full"])
        p.add_argument("--out", default="runs/bench")
    p.set_defaults(func=cmd_bench)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``motionflows`` console script; returns the exit code."""
    from motionflows.training import report_errors

    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:
        return int(exc.code or 0)
    try:
        return report_errors(args.func, args)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
