"""``motionflows train`` and ``python -m experiments.<name>``: train flags -> a run.

Every experiment module gets its command line from :func:`experiment_main`::

    if __name__ == "__main__":
        import sys
        from motionflows.training import experiment_main
        sys.exit(experiment_main(sys.modules[__name__]))

:func:`report_errors` turns user errors of any command into one line on stderr and exit
code 2.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import sys
from pathlib import Path
from typing import Any

import jax

from motionflows import config as cfg
from motionflows import distributed, runs, training
from motionflows.errors import RunError
from motionflows.run import evaluate_run


def add_set_argument(parser: argparse.ArgumentParser, help: str) -> None:
    """``--set KEY=VALUE ...`` into ``args.overrides`` (a flat list, in order): repeatable,
    every ``--set`` adds to the ones before it (``--set a=1 --set b=2`` is both)."""
    parser.add_argument(
        "--set",
        dest="overrides",
        action="extend",
        nargs="+",
        default=[],
        metavar="KEY=VALUE",
        help=f"{help}; repeatable",
    )


def add_train_arguments(parser: argparse.ArgumentParser) -> None:
    """The flags shared by ``python -m experiments.<name>`` and ``motionflows train``."""
    parser.add_argument(
        "--preset", default=None, help="named config (default: quick; --resume: the run's own)"
    )
    parser.add_argument(
        "--data", default=None, help="synthetic | bandai | bandai:DIR | bvh:DIR | DIR"
    )
    parser.add_argument("--steps", type=int, default=None, help="training steps (train.steps)")
    add_set_argument(parser, "config override, e.g. train.lr=1e-3")
    parser.add_argument("--run-name", default=None, help="run directory name")
    parser.add_argument("--runs-dir", default="runs", help="root of run directories")
    parser.add_argument(
        "--resume",
        action="store_true",
        help="continue --run-name (or the latest run) from its checkpoint",
    )
    parser.add_argument("--no-eval", action="store_true", help="skip the final test table")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_cpu_devices_argument(parser)


def add_cpu_devices_argument(parser: argparse.ArgumentParser) -> None:
    """``--cpu-devices N`` (:func:`motionflows.distributed.simulate_cpu_devices`)."""
    parser.add_argument(
        "--cpu-devices",
        type=int,
        default=None,
        metavar="N",
        help="train data-parallel over N simulated CPU devices (the cpu MoGlow on 2 cores: "
        "2-4, 18-29%% faster; docs/readme/running.md)",
    )


def configure(module: Any, args: argparse.Namespace) -> tuple[Any, str | None, Path]:
    """(config, preset, run_dir) from parsed train flags (resume reads config.json)."""
    if args.resume:
        run_dir = (
            Path(args.runs_dir) / module.NAME / args.run_name
            if args.run_name
            else runs.latest_run(args.runs_dir, module.NAME)
        )
        if run_dir is None:
            raise RunError(f"no run of {module.NAME} under {args.runs_dir}/ to resume")
        run_dir = runs.check_run_dir(run_dir)
        _, preset, config = cfg.load_config(run_dir / "config.json", module.Config)
        if args.preset is not None and args.preset != preset:
            raise RunError(
                f"--resume continues {run_dir} with its saved config (preset {preset!r}), "
                f"not --preset {args.preset}: drop --preset, or start a new run"
            )
    else:
        preset = "quick" if args.preset is None else args.preset
        if preset not in module.PRESETS:
            raise RunError(
                f"unknown preset {preset!r} for {module.NAME}; available: {sorted(module.PRESETS)}"
            )
        config = module.PRESETS[preset]
        run_dir = Path(args.runs_dir) / module.NAME / (args.run_name or runs.new_run_name(preset))
    if args.data is not None:
        config = dataclasses.replace(
            config, data=dataclasses.replace(config.data, **runs.parse_data(args.data))
        )
    if args.steps is not None:
        if args.steps < 0:
            raise RunError(f"--steps must be >= 0, got {args.steps}")
        config = dataclasses.replace(
            config, train=dataclasses.replace(config.train, steps=args.steps)
        )
    try:
        config = cfg.apply_overrides(config, args.overrides)
    except ValueError as err:
        raise RunError(str(err)) from None
    training.check_steps(module, config)
    if args.steps is not None and config.train.steps != args.steps:
        raise RunError(
            f"--steps {args.steps} and --set train.steps={config.train.steps} disagree: give "
            "the number of steps once"
        )
    return config, preset, run_dir


def run_train(module: Any, args: argparse.Namespace) -> int:
    """Train from parsed flags, then print the test table; the exit code."""
    # before JAX starts its CPU backend
    distributed.simulate_cpu_devices(args.cpu_devices)
    distributed.configure_cpu_threads()
    if distributed.initialize():  # MOTIONFLOWS_COORDINATOR etc. (see motionflows.distributed)
        print(
            f"process {jax.process_index()} of {jax.process_count()}, "
            f"{jax.device_count()} devices in all",
            file=sys.stderr,
        )
    elif jax.device_count() > 1:
        print(f"data-parallel over {jax.device_count()} devices", file=sys.stderr)
    distributed.check_cpu_devices(args.cpu_devices)
    module = runs.resolve_experiment(module)
    config, preset, run_dir = configure(module, args)
    distributed.check_same_config(module.NAME, config)
    print(f"run directory: {run_dir}", file=sys.stderr)
    dataset = config.data.load()
    print(f"data: {dataset.summary()}", file=sys.stderr)
    result = training.train(
        module,
        config,
        run_dir=run_dir,
        preset=preset,
        resume=args.resume,
        dataset=dataset,
        progress=not args.no_progress,
    )
    if result.status in ("interrupted", "nonfinite"):
        return 130 if result.status == "interrupted" else 1
    if not args.no_eval and jax.process_index() == 0:
        evaluate_run(run_dir, "test", dataset=dataset)
    print(f"done: {run_dir}", file=sys.stderr)
    return 0


def report_errors(fn, *args) -> int:
    """Run ``fn(*args)``; user errors become one line on stderr and exit code 2."""
    from motionflows.checkpoints import CheckpointWriteError
    from motionflows.errors import MotionDataError

    try:
        return fn(*args)
    except (RunError, MotionDataError, FileNotFoundError, CheckpointWriteError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except ValueError as err:  # bad config values and shapes, with the fix in the message
        print(f"error: {err}", file=sys.stderr)
        return 2
    except OSError as err:  # a full disk, a file where a folder should be, no permission
        import errno

        where = f" ({err.filename})" if err.filename else ""
        fix = {
            errno.ENOSPC: "free disk space and run the command again (--resume continues)",
            errno.EEXIST: "a file is in the way: choose another path",
            errno.ENOTDIR: "a file is in the way: choose another path",
            errno.EACCES: "no permission: choose a folder you can write to",
        }.get(err.errno, "check the path")
        print(f"error: {err.strerror or err}{where}; {fix}", file=sys.stderr)
        return 2
    except MemoryError:
        print("error: out of memory; use smaller inputs or a smaller batch", file=sys.stderr)
        return 2


def experiment_main(module: Any, argv: list[str] | None = None) -> int:
    """Command line of ``python -m experiments.<name>``; returns the exit code."""
    name = getattr(module, "NAME", "experiment")
    parser = argparse.ArgumentParser(
        prog=f"python -m experiments.{name}",
        description=(module.__doc__ or "").strip().split("\n")[0],
    )
    add_train_arguments(parser)
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:
        return int(exc.code or 0)
    with contextlib.suppress(KeyboardInterrupt):
        return report_errors(run_train, module, args)
    return 130
