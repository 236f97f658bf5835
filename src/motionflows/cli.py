"""The ``motionflows`` command: train, eval, sample, render, play, runs, data, bench.

    motionflows train moglow --preset quick --data synthetic --steps 2000 --set train.lr=1e-3
    motionflows train moglow --run-name quick-1 --resume
    motionflows eval runs/moglow/quick-1 --split test
    motionflows sample runs/moglow/quick-1 --control walk-turn-run --seconds 8 --num 4
    motionflows render take.bvh --out renders/        (or an .npz with pose / control)
    motionflows play runs/moglow/quick-1 --port 8000   (then open the printed URL)
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
import warnings
import zipfile
from pathlib import Path

import numpy as np

from motionflows.errors import RunError


class _Parser(argparse.ArgumentParser):
    """argparse that reports a bad flag as one line and exit code 2."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


MAX_SAMPLES = 1024
"""Most samples one ``sample`` command draws (memory grows with --num x frames)."""
MAX_SAMPLE_SECONDS = 3600.0
"""Longest ``sample --seconds`` (one hour of motion per sample)."""


def _one_line_warning(message, category, filename, lineno, file=None, line=None):
    """Warnings reach people as one line each, without the source line that raised them."""
    print(f"warning: {message}", file=file or sys.stderr)


def _folder(path: str | Path, flag: str) -> Path:
    """``path`` as an output folder; a path that is an existing file is refused."""
    path = Path(path)
    for p in (path, *path.parents):
        if p.exists() and not p.is_dir():
            raise RunError(
                f"{flag} {path}: {p} is a file, not a folder; give a folder path (it is "
                "created if missing)"
            )
        if p.exists():
            break
    return path


def _output_folder(args, run_dir: Path, local: str, default: Path) -> Path:
    """``--out`` if given; for ``pretrained:NAME``, ``<local>/NAME`` in the working directory
    (never inside the installed package); else ``default`` inside the run."""
    if args.out:
        return _folder(args.out, "--out")
    if str(args.run_dir).startswith("pretrained:"):
        return Path(local) / str(args.run_dir).split(":", 1)[1]
    return default


# ---------------------------------------------------------------------------- commands


def cmd_train(args) -> int:
    from motionflows.cli_train import run_train

    return run_train(args.experiment, args)


def cmd_eval(args) -> int:
    from motionflows import run, runs

    run_dir = runs.resolve_run_dir(args.run_dir)
    if args.batch_size is not None and args.batch_size < 1:
        raise RunError(f"--batch-size must be >= 1, got {args.batch_size}")
    if args.data is None and (args.label or args.skeleton):
        raise RunError("--label and --skeleton go with --data (other takes to score)")
    if args.data is not None and args.split is not None:
        raise RunError(
            "--split picks a split of the run's own data and --data scores other takes: "
            "give one of them"
        )
    out = _output_folder(args, run_dir, "evals", run_dir)
    run.evaluate_run(
        run_dir,
        args.split or "test",
        data=args.data,
        label=args.label,
        skeleton=args.skeleton or "bandai",
        checkpoint=args.checkpoint,
        batch_size=args.batch_size,
        out_dir=out,
    )
    written = sorted(out.glob("eval_*.json"), key=lambda p: p.stat().st_mtime)
    print(f"wrote {written[-1]}", file=sys.stderr)
    return 0


def _sample_controls(
    args, fps: float, root_sigma_s: float, window_s: float | None = None
) -> list[tuple[str, np.ndarray, np.ndarray | None]]:
    """(name, control (T, 3) data units, ground-truth pose (T, 63) metres or None) for
    ``--control``: a preset or .npy (no ground truth), a .bvh take or a folder of takes
    (read with the run's root smoothing ``root_sigma_s``). Without ``--seconds`` a preset
    lasts 8 s and a take or .npy control its own length, or ``window_s`` for a
    fixed-length model."""
    from motionflows.data.controls import load_control

    text = str(args.control)
    path = Path(text)
    if path.suffix.lower() == ".bvh" or path.is_dir():
        from motionflows.data.takes import read_takes

        clips, _ = read_takes(text, fps=fps, skeleton=args.skeleton, root_sigma_s=root_sigma_s)
        out = []
        for clip in clips:
            seconds = args.seconds if args.seconds is not None else window_s
            n = len(clip) if seconds is None else max(1, int(round(seconds * fps)))
            pose, control = clip.pose[:n], clip.control[:n]
            if len(control) < n:  # hold the last frame: the take is shorter than --seconds
                pad = n - len(control)
                control = np.concatenate([control, np.zeros((pad, 3), np.float32)])
                pose = np.concatenate([pose, np.repeat(pose[-1:], pad, 0)])
            out.append((clip.name, control, pose))
        return out
    seconds = args.seconds if args.seconds is not None else window_s
    if seconds is None and path.suffix.lower() != ".npy":
        seconds = 8.0  # a preset has no length of its own
    return [(path.stem, load_control(text, seconds, fps), None)]


def _sample_stem(out: Path, stem: str, run_dir: Path, pose: np.ndarray) -> str:
    """The file stem for ``pose`` in ``out``: ``stem``, unless ``out`` holds other samples
    under it, so nothing saved is replaced by something else. Another run's (a shared
    ``--out`` for several models) gives ``<run name>_<stem>``; another draw of this run
    (other ``--seconds``, ``--num``, controls or checkpoint) ``<stem>-2``, ``-3``, ...; the
    same poses again (same run, same draw) are written over."""

    def saved(name: str) -> tuple[str, np.ndarray] | None:  # (run_dir, pose); None: no file
        existing = out / f"{name}.npz"
        if not existing.is_file():
            return None
        try:
            with np.load(existing) as old:
                return str(old["run_dir"]), np.asarray(old["pose"])
        except (OSError, ValueError, KeyError, zipfile.BadZipFile):  # unreadable: keep it
            return "", np.empty(0)

    first = saved(stem)
    base = stem if first is None or first[0] == str(run_dir) else f"{run_dir.name}_{stem}"
    name, k = base, 1
    while (old := saved(name)) is not None and not (
        old[0] == str(run_dir) and np.array_equal(old[1], pose)
    ):
        k += 1
        name = f"{base}-{k}"
    return name


def cmd_sample(args) -> int:
    from motionflows import run, runs
    from motionflows.config import SEED_RANGE
    from motionflows.pretrained.model import INFO_FILE, read_info

    run_dir = runs.resolve_run_dir(args.run_dir)
    if not 1 <= args.num <= MAX_SAMPLES or (
        args.seconds is not None and not 0 < args.seconds <= MAX_SAMPLE_SECONDS
    ):
        raise RunError(
            f"--num must be 1 .. {MAX_SAMPLES} and --seconds in (0, {MAX_SAMPLE_SECONDS:g}] "
            f"(got --num {args.num}, --seconds {args.seconds})"
        )
    low, high = SEED_RANGE
    if not low <= args.seed <= high:
        raise RunError(f"--seed must be a 64-bit integer ({low} .. {high}), got {args.seed}")
    module, config, model, _ = run.load_run(run_dir, checkpoint=args.checkpoint, load_data=False)
    std = run.load_standardizer(run_dir)
    fps = float(config.data.fps)
    temperature = args.temperature
    if temperature is None:  # the temperature the model was validated at, else 1
        temperature = read_info(run_dir / INFO_FILE, module).get("temperature", 1.0)
    temperature = float(temperature)
    if not (np.isfinite(temperature) and temperature >= 0):
        raise RunError(
            f"--temperature must be a finite number >= 0 (1 = the model's own spread, 0 = its "
            f"mode), got {temperature:g}"
        )
    out = _output_folder(args, run_dir, "samples", run_dir / "samples")
    out.mkdir(parents=True, exist_ok=True)
    window_s = config.data.window / fps if runs.fixed_length(module) else None
    for name, control, truth in _sample_controls(args, fps, config.data.root_sigma_s, window_s):
        runs.check_sample_control(
            module, config, model, std, control, "motionflows sample", "--seconds"
        )
        pose = run.draw_samples(
            module, model, std, control, num=args.num, temperature=temperature, seed=args.seed
        )
        extra = {} if truth is None else {"ground_truth": truth}
        lock = "_foot-lock" if args.foot_lock else ""
        if args.foot_lock:  # the samples as drawn stay in the npz beside the locked ones
            extra["pose_drawn"] = pose
            pose = _foot_lock(pose, control)
        stem = _sample_stem(out, f"{name}_T{temperature:g}_seed{args.seed}{lock}", run_dir, pose)
        npz = out / f"{stem}.npz"
        np.savez(
            npz,
            pose=pose,
            control=control,
            fps=fps,
            temperature=temperature,
            seed=args.seed,
            foot_lock=bool(args.foot_lock),
            experiment=module.NAME,
            run_dir=str(run_dir),
            **extra,
        )
        print(f"wrote {npz}: pose {pose.shape} metres, control {control.shape}", file=sys.stderr)
        if args.no_gif:
            continue
        from motionflows import render

        for i in range(args.num):
            title = f"{module.NAME} {name} #{i}" + (", foot lock" if args.foot_lock else "")
            title += "" if truth is None else " | ground truth"
            gif = render.animate(
                pose[i],
                control,
                out / f"{stem}_{i}.gif",
                fps=fps,
                title=title,
                compare=truth,
                still=out / f"{stem}_{i}.png",
            )
            print(f"wrote {gif} and its still {gif.with_suffix('.png').name}", file=sys.stderr)
        render.plot_controls(control, out / f"{stem}_control.png", fps, title=name)
    return 0


def _foot_lock(pose: np.ndarray, control: np.ndarray) -> np.ndarray:
    """``--foot-lock``: poses (N, T, 63) with their planted feet held (motionflows.foot_lock)
    on one control (T, 3) or one each (N, T, 3); diverged samples stay as drawn, with a
    warning."""
    from motionflows.bench.scoring import DIVERGED_METRES, diverged, foot_locked

    bad = int(diverged(pose).sum())
    if bad:
        warnings.warn(
            f"{bad} of {len(pose)} samples diverged (NaN/inf or beyond {DIVERGED_METRES:g} m): "
            "--foot-lock leaves them as drawn",
            stacklevel=2,
        )
    return foot_locked(pose, np.broadcast_to(control, pose.shape[:-1] + (3,)))


def _render_run(args) -> int:
    """``render RUN`` / ``render pretrained:NAME``: animate one sample of a preset control."""
    from motionflows import render, runs
    from motionflows.data.controls import load_control
    from motionflows.pretrained import PretrainedModel

    run_dir = runs.resolve_run_dir(args.path)
    model = PretrainedModel.from_run(run_dir)
    seconds = model.window / model.fps if model.fixed_length else 8.0
    control = load_control("walk-turn-run", seconds, model.fps)
    pose = model.sample(control[None], seed=0)
    pose = (_foot_lock(pose, control) if args.foot_lock else pose)[0]
    out = _folder(args.out, "--out")
    stem = f"{run_dir.name}_walk-turn-run" + ("_foot-lock" if args.foot_lock else "")
    gif = render.animate(pose, control, out / f"{stem}.gif", fps=model.fps, title=stem)
    print(f"wrote {gif}", file=sys.stderr)
    return 0


def cmd_render(args) -> int:
    from motionflows import render

    if str(args.path).startswith("pretrained:") or (Path(args.path) / "config.json").is_file():
        return _render_run(args)
    path = Path(args.path)
    if path.is_dir():
        raise RunError(
            f"{path} is a folder but not a run (no config.json): give a run directory, "
            "pretrained:NAME, a .bvh file or an .npz with pose and control"
        )
    if not path.is_file():
        raise RunError(f"{path} not found (give a .bvh file or an .npz with pose and control)")
    if args.fps is not None and not (np.isfinite(args.fps) and 1 <= args.fps <= 1000):
        raise RunError(f"--fps must be in [1, 1000] frames per second, got {args.fps:g}")
    out = _folder(args.out, "--out")
    if path.suffix.lower() == ".bvh":
        from motionflows.data import clip_from_bvh

        if args.foot_lock:
            raise RunError(
                "--foot-lock holds the feet of sampled motion (a run, pretrained:NAME or an "
                f".npz); {path.name} is a take: render it without --foot-lock"
            )
        clip = clip_from_bvh(path, fps=args.fps or 20.0, skeleton=args.skeleton)
        files = render.render_clip(clip, out)
        for f in files.values():
            print(f"wrote {f}", file=sys.stderr)
        return 0
    if path.suffix.lower() != ".npz":
        raise RunError(f"{path}: render reads .bvh or .npz files")
    pose, control, fps, resets = _read_motion_npz(path, args.fps)
    poses = pose[None] if pose.ndim == 2 else pose
    if (
        poses.ndim != 3
        or poses.shape[-1] != 63
        or control.shape[-2:] != (poses.shape[1], 3)
        or control.ndim not in (2, 3)
        or (control.ndim == 3 and len(control) != len(poses))
        or 0 in poses.shape
    ):
        raise RunError(
            f"{path}: 'pose' must be (T, 63) or (N, T, 63) metres and 'control' (T, 3) or "
            f"(N, T, 3) with the same T >= 1; got pose {pose.shape}, control {control.shape}"
        )
    for name, arr in (("pose", poses), ("control", control)):
        real = np.issubdtype(arr.dtype, np.integer) or np.issubdtype(arr.dtype, np.floating)
        if not real or not np.all(np.isfinite(arr)):
            raise RunError(
                f"{path}: '{name}' must hold finite real numbers (it has NaN, inf, complex "
                "numbers or text)"
            )
    if resets is not None:
        resets = _frame_indices(resets, poses.shape[1], f"{path}: 'resets'")
    controls = (
        control if control.ndim == 3 else np.broadcast_to(control, (len(poses), *control.shape))
    )
    stem = path.stem
    if args.foot_lock:
        poses, stem = _foot_lock(poses, controls), f"{path.stem}_foot-lock"
    for i, (p, c) in enumerate(zip(poses, controls, strict=True)):
        gif = render.animate(p, c, out / f"{stem}_{i}.gif", fps=fps, title=f"{stem} #{i}")
        print(f"wrote {gif}", file=sys.stderr)
    png = render.plot_controls(controls[0], out / f"{path.stem}_control.png", fps, title=path.stem)
    print(f"wrote {png}", file=sys.stderr)
    if resets is not None and len(resets):
        at = ", ".join(f"{r} ({r / fps:.2f} s)" for r in resets)
        print(
            f"note: the character restarted standing at frame{'s' * (len(resets) > 1)} {at} "
            "after a diverged frame (motionflows play); the motion jumps there",
            file=sys.stderr,
        )
    return 0


def _frame_indices(values: np.ndarray, frames: int, name: str) -> np.ndarray:
    """``values`` as a 1-D integer array of frame indices in [0, ``frames``), else RunError."""
    whole = np.issubdtype(values.dtype, np.integer) or (
        np.issubdtype(values.dtype, np.floating)
        and np.all(np.isfinite(values))
        and np.all(values == np.round(values))
    )
    if values.ndim != 1 or not whole or np.any(values < 0) or np.any(values >= frames):
        raise RunError(
            f"{name} must be frame indices in [0, {frames}) (the frames at which motionflows "
            f"play restarted the character); got {values.tolist()}"
        )
    return values.astype(np.int64)


def _read_motion_npz(
    path: Path, fps_flag: float | None
) -> tuple[np.ndarray, np.ndarray, float, np.ndarray | None]:
    """``pose``, ``control``, the frame rate and ``resets`` (None without one) of an .npz for
    ``render``: the rate is its own 0-d ``fps`` array, else ``--fps`` (default 20); a
    ``--fps`` that disagrees with the file's is refused (the file says at what rate its
    frames were made). ``resets``: a ``motionflows play`` recording's restarts."""
    try:
        data = np.load(path, allow_pickle=False)
    except (OSError, ValueError, zipfile.BadZipFile):
        raise RunError(
            f"{path} is not an .npz archive (np.savez with arrays pose and control)"
        ) from None
    with data:
        if "pose" not in data or "control" not in data:
            raise RunError(
                f"{path} must hold arrays 'pose' (T, 63) or (N, T, 63) metres and 'control' (T, 3)"
            )
        pose, control = np.asarray(data["pose"]), np.asarray(data["control"])
        saved = np.asarray(data["fps"]) if "fps" in data else None
        resets = np.asarray(data["resets"]) if "resets" in data else None
    if saved is None:
        fps = 20.0 if fps_flag is None else float(fps_flag)
    else:
        if saved.shape != () or not np.issubdtype(saved.dtype, np.number):
            raise RunError(f"{path}: 'fps' must be one number, got an array {saved.shape}")
        fps = float(saved)
        if fps_flag is not None and fps_flag != fps:
            raise RunError(
                f"{path} was made at {fps:g} fps (its 'fps' array); --fps {fps_flag:g} "
                "disagrees: drop --fps"
            )
    if not (np.isfinite(fps) and 1 <= fps <= 1000):
        raise RunError(f"{path}: fps must be in [1, 1000], got {fps:g}")
    return pose, control, fps, resets


def cmd_export(args) -> int:
    from motionflows import runs
    from motionflows.export import export_run

    run_dir = runs.resolve_run_dir(args.run_dir)
    out = export_run(
        run_dir,
        _folder(args.out, "--out"),
        checkpoint=args.checkpoint,
        temperature=args.temperature,
        overwrite=args.overwrite,
        notes=args.notes,
    )
    size = sum(f.stat().st_size for f in out.rglob("*") if f.is_file())
    print(f"wrote {out} ({size / 1e6:.1f} MB, no optimiser state)", file=sys.stderr)
    return 0


def cmd_play(args) -> int:
    try:
        from motionflows.play import play
        from motionflows.play.server import check_installed

        check_installed()
    except ImportError as err:
        raise RunError(str(err)) from None
    play(
        args.run_dir,
        host=args.host,
        port=args.port,
        temperature=args.temperature,
        foot_lock=args.foot_lock,
    )
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
    download_bandai(_folder(args.dest, "--dest"), base_url=base_url)
    return 0


def cmd_bench(args) -> int:
    from motionflows import cli_bench

    _folder(args.out, "--out")
    return cli_bench.main(args)


# ----------------------------------------------------------------------------- parser


def _add_train(sub) -> None:
    """The ``train`` command's flags."""
    from motionflows.cli_train import add_train_arguments

    p = sub.add_parser("train", help="train an experiment (experiments/<name>.py)")
    p.add_argument("experiment", help="experiment name, e.g. moglow, glow_fixed, baselines")
    add_train_arguments(p)
    p.set_defaults(func=cmd_train)


def _add_eval(sub) -> None:
    """The ``eval`` command's flags."""
    p = sub.add_parser("eval", help="likelihood table of a run (writes eval_<split>.json)")
    p.add_argument("run_dir")
    p.add_argument(
        "--split",
        default=None,
        choices=["train", "val", "test"],
        help="the split of the run's own data to score (default test)",
    )
    p.add_argument(
        "--data",
        default=None,
        help="score other takes instead of a split: bvh:DIR, bandai:DIR, a folder or a .bvh "
        "(the run's standardiser, window and fps; writes eval_<label>.json)",
    )
    p.add_argument("--label", default=None, help="name of the --data output (default: folder)")
    p.add_argument("--out", default=None, help="folder of eval_*.json (default: the run)")
    p.add_argument("--skeleton", default=None, help="skeleton mapping of --data BVH files")
    p.add_argument("--checkpoint", default="best", choices=["best", "latest"])
    p.add_argument("--batch-size", type=int, default=None)
    p.set_defaults(func=cmd_eval)


def _add_sample(sub) -> None:
    """The ``sample`` command's flags."""
    p = sub.add_parser("sample", help="sample motion for a control (npz + GIF)")
    p.add_argument("run_dir")
    p.add_argument(
        "--control",
        default="walk-turn-run",
        help="a control preset (stand, walk, run, walk-turn-left, walk-then-run, "
        "walk-turn-run, figure-eight, ...), a (T, 3) .npy file, or a .bvh take or folder of "
        "takes (its own control; the GIF shows the take beside the sample)",
    )
    p.add_argument(
        "--seconds",
        type=float,
        default=None,
        help="length (default: a preset 8 s, a take or .npy control its own; a fixed-length "
        "model's window)",
    )
    p.add_argument("--skeleton", default="bandai", help="skeleton mapping of --control BVH")
    p.add_argument("--num", type=int, default=1, help="number of samples")
    p.add_argument(
        "--temperature",
        type=float,
        default=None,
        help="sampling temperature (default: the validated one of a pretrained model, else 1)",
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=None, help="output folder (default: <run>/samples)")
    p.add_argument("--checkpoint", default="best", choices=["best", "latest"])
    p.add_argument("--no-gif", action="store_true", help="only write the npz")
    _add_foot_lock(p)
    p.set_defaults(func=cmd_sample)


def _add_foot_lock(p) -> None:
    p.add_argument(
        "--foot-lock",
        action="store_true",
        help="hold each planted foot in place (a post-process of the samples: "
        "motionflows.foot_lock; files get a _foot-lock suffix, an npz keeps the drawn "
        "samples as pose_drawn)",
    )


def _add_render(sub) -> None:
    """The ``render`` command's flags."""
    p = sub.add_parser(
        "render",
        help="GIF + control plot of a .bvh or .npz (pose, control), or a sample of a run "
        "directory / pretrained:NAME",
    )
    p.add_argument("path")
    p.add_argument("--out", default="renders", help="output folder")
    p.add_argument(
        "--fps",
        type=float,
        default=None,
        help="frame rate: a BVH file is resampled to it, an .npz without an 'fps' array is "
        "drawn at it (default 20; an .npz's own 'fps' is used, and a different --fps refused)",
    )
    p.add_argument("--skeleton", default="bandai", help="skeleton mapping of a BVH file")
    _add_foot_lock(p)
    p.set_defaults(func=cmd_render)


def _add_export(sub) -> None:
    """The ``export`` command's flags."""
    p = sub.add_parser("export", help="a shippable copy of a run (parameters, no optimiser)")
    p.add_argument("run_dir")
    p.add_argument("--out", required=True, help="folder to write (must be new or empty)")
    p.add_argument("--checkpoint", default="best", choices=["best", "latest"])
    p.add_argument(
        "--temperature", type=float, default=None, help="validated sampling temperature to store"
    )
    p.add_argument("--overwrite", action="store_true", help="replace an existing export")
    p.add_argument("--notes", default=None, help="text stored as pretrained.json's notes")
    p.set_defaults(func=cmd_export)


def _add_play(sub) -> None:
    """The ``play`` command's flags."""
    p = sub.add_parser("play", help="steer a MoGlow character in real time from a web page")
    p.add_argument("run_dir", help="a run directory of a causal model, or pretrained:NAME")
    p.add_argument("--port", type=int, default=0, help="port to listen on (default: a free one)")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on")
    p.add_argument(
        "--temperature",
        type=float,
        default=None,
        help="initial sampling temperature (default: the validated one of a pretrained "
        "model, else 1; the page has a slider)",
    )
    p.add_argument(
        "--foot-lock",
        action="store_true",
        help="hold planted feet, frame by frame (motionflows.foot_lock.StreamingFootLock: a "
        "post-process; the recording keeps the drawn poses as pose_drawn)",
    )
    p.set_defaults(func=cmd_play)


def _add_runs(sub) -> None:
    """The ``runs`` command's flags."""
    p = sub.add_parser("runs", help="table of runs with their best validation NLL")
    p.add_argument("--root", default="runs")
    p.set_defaults(func=cmd_runs)


def _add_data(sub) -> None:
    """The ``data`` command's flags."""
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


def _add_bench(sub) -> None:
    """The ``bench`` command's flags."""
    from motionflows import cli_bench

    p = sub.add_parser("bench", help="compare every model on one split (BENCHMARK.md)")
    cli_bench.build_parser(p)
    p.set_defaults(func=cmd_bench)


def build_parser() -> argparse.ArgumentParser:
    """The ``motionflows`` parser: one sub-command per ``_add_<command>``."""
    parser = _Parser(
        prog="motionflows", description="Probabilistic, controllable motion models in JAX."
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True
    for add in (
        _add_train,
        _add_eval,
        _add_sample,
        _add_render,
        _add_export,
        _add_play,
        _add_runs,
        _add_data,
        _add_bench,
    ):
        add(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``motionflows`` console script; returns the exit code."""
    from motionflows.cli_train import report_errors
    from motionflows.compile_cache import use_persistent_cache

    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:
        return int(exc.code or 0)
    use_persistent_cache()
    shown, warnings.showwarning = warnings.showwarning, _one_line_warning
    try:
        return report_errors(args.func, args)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    finally:
        warnings.showwarning = shown


if __name__ == "__main__":
    sys.exit(main())
