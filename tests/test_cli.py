"""The ``motionflows`` command: the train -> eval -> sample -> runs path and clear errors."""

import os
import subprocess
import sys
import types
from pathlib import Path

import jax
import numpy as np
import pytest
from test_training_fakes import FakeDataset

import experiments.baselines as baselines
from motionflows import cli
from motionflows.config import DataConfig
from motionflows.runs import read_metrics

ROOT = Path(__file__).resolve().parents[1]


def _noisy_loss(model, batch, key):
    loss, metrics = baselines.loss(model, batch, key)
    return loss + 0.01 * jax.random.normal(key, ()), metrics


@pytest.fixture
def fake_data(monkeypatch):
    data = FakeDataset()
    monkeypatch.setattr(DataConfig, "load", lambda self: data)
    # a gradient-trained experiment (the baselines' Gaussian without the closed-form fit)
    fake = types.ModuleType("experiments.cli_fake")
    for name in ("Config", "PRESETS", "SCOPES", "build", "evaluate", "sample"):
        setattr(fake, name, getattr(baselines, name))
    fake.NAME, fake.loss = "cli_fake", _noisy_loss
    monkeypatch.setitem(sys.modules, "experiments.cli_fake", fake)
    return data


def _run(capsys, *argv):
    code = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def test_train_eval_sample_runs(tmp_path, capsys, fake_data):
    runs = tmp_path / "runs"
    common = [
        "--runs-dir",
        runs,
        "--no-progress",
        "--set",
        "model=gaussian",
        "tau=2",
        "train.batch_size=4",
        "eval_batches=1",
        "log_every=1",
        "eval_every=2",
    ]
    code, out, err = _run(capsys, "train", "cli_fake", "--steps", 2, "--run-name", "r", *common)
    assert code == 0, err
    assert "data: fake, 24 training windows" in err  # what it trains on, before it trains
    assert "nats/frame" in out and "window" in out and "official" in out
    run = runs / "cli_fake" / "r"
    assert (run / "eval_test.json").is_file() and (run / "config.json").is_file()
    # resume extends the same run to 4 steps
    code, _, err = _run(
        capsys,
        "train",
        "cli_fake",
        "--resume",
        "--run-name",
        "r",
        "--steps",
        4,
        "--runs-dir",
        runs,
        "--no-progress",
        "--no-eval",
    )
    assert code == 0, err
    assert "resumed" in err
    assert [r["step"] for r in read_metrics(run) if "loss" in r] == [1, 2, 3, 4]
    # --resume continues the saved config: another --preset was silently ignored
    argv = ["train", "cli_fake", "--resume", "--run-name", "r", "--runs-dir", runs]
    code, _, err = _run(capsys, *argv, "--preset", "gaussian", "--no-progress", "--no-eval")
    assert code == 2 and "drop --preset" in err

    code, out, err = _run(capsys, "eval", run, "--split", "val")
    assert code == 0, err
    assert "val split" in out and "bits/frame" in out and (run / "eval_val.json").is_file()

    code, _, err = _run(
        capsys,
        "sample",
        run,
        "--control",
        "walk",
        "--seconds",
        1,
        "--num",
        2,
        "--seed",
        3,
        "--no-gif",
        "--out",
        tmp_path / "s",
    )
    assert code == 0, err
    npz = np.load(tmp_path / "s" / "walk_T1_seed3.npz")
    assert npz["pose"].shape == (2, 20, 63) and npz["control"].shape == (20, 3)
    # poses come back in metres: the (fake) standardiser's mean/std are applied
    assert abs(npz["pose"].mean() - fake_data.standardizer.pose_mean.mean()) < 0.5
    # another draw under the same name does not replace it (it did, silently); the same
    # draw again is written over
    again = ["sample", run, "--control", "walk", "--seed", 3, "--no-gif", "--out", tmp_path / "s"]
    for seconds in (0.5, 0.5, 1):
        assert _run(capsys, *again, "--seconds", seconds, "--num", 2)[0] == 0
    files = sorted(f.name for f in (tmp_path / "s").glob("*.npz"))
    assert files == ["walk_T1_seed3-2.npz", "walk_T1_seed3.npz"], files
    assert np.load(tmp_path / "s" / "walk_T1_seed3.npz")["pose"].shape == (2, 20, 63)
    assert np.load(tmp_path / "s" / "walk_T1_seed3-2.npz")["pose"].shape == (2, 10, 63)
    code, _, err = _run(capsys, *again, "--seed", 2**70)
    assert code == 2 and "--seed must be a 64-bit integer" in err

    code, out, _ = _run(capsys, "runs", "--root", runs)
    assert code == 0 and "cli_fake" in out and " r " in out

    # the closed-form baseline through the same command
    code, out, err = _run(
        capsys,
        "train",
        "baselines",
        "--run-name",
        "ar",
        "--runs-dir",
        runs,
        "--no-progress",
        "--set",
        "tau=2",
        "train.batch_size=8",
    )
    assert code == 0, err
    assert "fitted" in read_metrics(runs / "baselines" / "ar")[-1]["status"]


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["train", "no_such_model"], "unknown experiment"),
        (["train", "baselines", "--preset", "huge"], "unknown preset"),
        (["train", "baselines", "--set", "nonsense=1"], "unknown config key"),
        (["train", "baselines", "--set", "train.steps=lots"], "cannot read"),
        (["train", "baselines", "--data", "mars"], "--data"),
        (["train", "baselines", "--bogus-flag"], "unrecognized arguments"),
        (["eval", "/no/such/run"], "not a run directory"),
        (["sample", "/no/such/run"], "not a run directory"),
        (["render", "/no/such/file.bvh"], "not found"),
        (["data", "download", "nowhere", "--dest", "x"], "unknown dataset"),
        (["frobnicate"], "invalid choice"),
        (["train", "moglow", "--steps", "0"], "train.steps must be >= 1"),
        (["train", "baselines", "--steps", "5", "--set", "train.steps=7"], "disagree"),
        (["train", "baselines", "--set", "ridge=nan"], "ridge must be"),
        (["eval", "pretrained:moglow-bandai", "--data", "bvh:x", "--split", "val"], "give one"),
        (["train", "baselines", "--data", "synthetic:/no/such/dir"], "--data"),
        (["train", "baselines", "--cpu-devices", "100000"], "--cpu-devices must be 1 .. 256"),
    ],
)
def test_user_errors_are_one_clear_line_and_exit_2(capsys, tmp_path, fake_data, argv, needle):
    code, out, err = _run(
        capsys,
        *argv,
        *(["--runs-dir", tmp_path] if argv[0] == "train" and "--bogus-flag" not in argv else []),
    )
    assert code == 2
    assert needle in err
    assert "Traceback" not in err and len(err.strip().splitlines()) <= 2


def test_experiment_module_runs_as_python_dash_m(tmp_path):
    cmd = [
        sys.executable,
        "-m",
        "experiments.baselines",
        "--preset",
        "quick",
        "--data",
        "synthetic",
        "--steps",
        "3",
        "--set",
        "tau=2",
        "fit_windows=32",
        "data.synthetic_clips=12",
        "data.synthetic_seconds=6",
        "--run-name",
        "x",
        "--runs-dir",
        str(tmp_path / "runs"),
        "--no-eval",
    ]
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    run = tmp_path / "runs" / "baselines" / "x"
    assert (run / "config.json").is_file() and (run / "standardizer.json").is_file()
    assert read_metrics(run)[-1]["status"] == "fitted"


def test_experiment_main_errors(capsys):
    from motionflows.training import experiment_main

    assert experiment_main(baselines, ["--preset", "nope"]) == 2
    assert "unknown preset" in capsys.readouterr().err
    assert experiment_main(baselines, ["--steps", "x"]) == 2
    assert "invalid int value" in capsys.readouterr().err


def test_render_npz_and_demo_with_the_baseline(tmp_path, capsys, fake_data):
    # render: an npz of pose (T, 63) metres + control (T, 3) -> GIF and control plot
    pose = np.tile(fake_data.standardizer.pose_mean, (3, 1))
    np.savez(tmp_path / "clip.npz", pose=pose, control=np.full((3, 3), 0.05, np.float32))
    code, _, err = _run(capsys, "render", tmp_path / "clip.npz", "--out", tmp_path / "r")
    assert code == 0, err
    assert (tmp_path / "r" / "clip_0.gif").is_file()
    assert (tmp_path / "r" / "clip_control.png").is_file()

    from motionflows import demo

    code = demo.main(
        [
            "--no-pretrained",
            "--experiment",
            "baselines",
            "--seconds",
            "0.5",
            "--runs-dir",
            str(tmp_path / "runs"),
            "--set",
            "tau=2",
        ]
    )
    out, err = capsys.readouterr()
    assert code == 0, err
    assert "== data: fake, 24 training windows" in err  # as `train` says it
    assert "nats/frame" in out and "window" in out
    (run,) = (tmp_path / "runs" / "baselines").iterdir()
    assert (run / "samples" / "demo_walk-turn-run.gif").is_file()
    assert np.load(run / "samples" / "demo_walk-turn-run.npz")["pose"].shape == (10, 63)
    (tmp_path / "a_file").write_text("")
    assert demo.main(["--no-train", "--runs-dir", str(tmp_path / "a_file")]) == 2
    assert "is a file: give a folder" in capsys.readouterr().err  # was a traceback


def test_render_refuses_what_it_cannot_draw_right(tmp_path, capsys, fake_data):
    """Bad .npz files, frame rates and folders: one line and exit 2, never a traceback and
    never a GIF at the wrong speed (a --fps the file's own rate overrode silently)."""
    pose = np.tile(fake_data.standardizer.pose_mean, (3, 1))
    control = np.full((3, 3), 0.05, np.float32)
    np.savez(tmp_path / "at30.npz", pose=pose, control=control, fps=30.0)
    np.savez(tmp_path / "fps2.npz", pose=pose, control=control, fps=np.array([20.0, 30.0]))
    np.savez(tmp_path / "complex.npz", pose=pose.astype(np.complex64), control=control)
    np.savez(tmp_path / "nofps.npz", pose=pose, control=control)
    (tmp_path / "text.npz").write_text("not an archive")
    (tmp_path / "folder").mkdir()
    out = ["--out", tmp_path / "r"]
    cases = [
        (["at30.npz", "--fps", "10"], "made at 30 fps"),
        (["fps2.npz"], "'fps' must be one number"),
        (["complex.npz"], "finite real numbers"),
        (["text.npz"], "not an .npz archive"),
        (["nofps.npz", "--fps", "1e-9"], "--fps must be in [1, 1000]"),
        (["folder"], "is a folder but not a run"),
    ]
    for argv, needle in cases:
        code, _, err = _run(capsys, "render", tmp_path / argv[0], *argv[1:], *out)
        assert code == 2 and needle in err and "Traceback" not in err, (argv, err)
    assert _run(capsys, "render", tmp_path / "at30.npz", "--fps", "30", *out)[0] == 0


def test_render_says_where_a_play_recording_restarts(tmp_path, capsys, fake_data):
    """A `motionflows play` recording keeps the motion across a restart after a diverged
    frame (its ``resets``); the GIF jumps there to a standing pose. `render` named nothing,
    so the jump looked like the model's; it now says at which frames and seconds the
    character restarted, and refuses a ``resets`` that is not frame indices of the take."""
    pose = np.tile(fake_data.standardizer.pose_mean, (4, 1))
    control = np.full((4, 3), 0.05, np.float32)
    np.savez(tmp_path / "rec.npz", pose=pose, control=control, fps=20.0, resets=[2])
    np.savez(tmp_path / "calm.npz", pose=pose, control=control, fps=20.0, resets=[])
    np.savez(tmp_path / "bad.npz", pose=pose, control=control, resets=[7])
    np.savez(tmp_path / "frac.npz", pose=pose, control=control, resets=[1.5])
    out = ["--out", tmp_path / "r"]
    code, _, err = _run(capsys, "render", tmp_path / "rec.npz", *out)
    assert code == 0, err
    assert "restarted standing at frame 2 (0.10 s)" in err, err
    code, _, err = _run(capsys, "render", tmp_path / "calm.npz", *out)
    assert code == 0 and "restarted" not in err, err
    for name in ("bad.npz", "frac.npz"):
        code, _, err = _run(capsys, "render", tmp_path / name, *out)
        assert code == 2 and "'resets' must be" in err and "Traceback" not in err, err


def test_the_ablation_script_passes_each_runs_settings(tmp_path):
    """benchmarks/moglow_ablations.sh gave the unchanged preset (`all`, no settings) a bare
    `--set` that argparse refused, stopping the script at its first run."""
    fake = tmp_path / "bin" / "python"
    fake.parent.mkdir()
    fake.write_text('#!/bin/sh\necho "$@" >> "$CALLS"\n')
    fake.chmod(0o755)
    env = {**os.environ, "PATH": f"{fake.parent}:{os.environ['PATH']}",
           "CALLS": str(tmp_path / "calls")}  # fmt: skip
    script = ROOT / "benchmarks" / "moglow_ablations.sh"
    out = tmp_path / "q"
    out.mkdir()
    subprocess.run(["bash", script, out, "all", "res-K8"], env=env, cwd=ROOT, check=True)
    calls = (tmp_path / "calls").read_text().splitlines()
    assert len(calls) == 2 and "--set" not in calls[0].split()
    assert "--set residual=true K=8 --out" in calls[1]


@pytest.mark.parametrize(
    "script, required",
    [("model_quality", ["vae_lstm", "--out", "q"]), ("contact_oracle", ["--out", "q"])],
)
def test_benchmark_scripts_count_every_repeated_set_flag(benchmark_script, script, required):
    # the scripts that train a preset take --set as the CLI does: `--set a --set b` is both
    # (they kept only the last --set, scoring a config other than the one asked)
    sets = ["--set", "train.steps=54000", "tau=3", "--set", "train.seed=1"]
    args = benchmark_script(script).build_parser().parse_args([*required, *sets])
    assert args.overrides == ["train.steps=54000", "tau=3", "train.seed=1"]


@pytest.mark.parametrize("command", ["train", "bench", "demo"])
def test_every_set_flag_counts_when_set_is_repeated(command):
    # `--set a --set b` is how most people write two changes: each --set adds, none replaces
    # (the bench and the demo used to keep only the last one, silently training another run)
    from motionflows import cli_bench, demo

    sets = ["--set", "train.steps=54000", "tau=3", "--set", "train.seed=1"]
    parsers = {
        "train": lambda: cli.build_parser().parse_args(["train", "moglow", *sets]),
        "bench": lambda: cli_bench.build_parser().parse_args(sets),
        "demo": lambda: demo.build_parser().parse_args(sets),
    }
    args = parsers[command]()
    assert args.overrides == ["train.steps=54000", "tau=3", "train.seed=1"]
    if command == "bench":
        assert cli_bench._command(args, ("moglow",)).endswith(
            "--set train.steps=54000 tau=3 train.seed=1"
        )


def test_runs_table_best_is_the_lowest_finite_validation():
    """A NaN validation row (the trainer logs one when a validation blew up) is not the
    run's best: min() over floats with a NaN first returned the NaN."""
    from motionflows.runs import best_val

    rows = [{"step": 10, "val_nll": float("nan")}, {"step": 20, "val_nll": -5.0},
            {"step": 30, "val_nll": -4.0}, {"step": 40, "loss": 1.0}]  # fmt: skip
    assert best_val(rows) == (-5.0, 20)
    assert best_val([{"step": 10, "val_nll": float("inf")}]) == (None, None)


@pytest.mark.parametrize(
    "script, argv",
    [
        ("play_latency", ["--presses", "0"]),  # was a median of nothing
        ("play_latency", ["pretrained:moglow-bandai", "--quick"]),  # --quick was ignored
        ("long_run_drift", ["pretrained:moglow-bandai", "--block", "0"]),
        ("control_phase_sliding", ["--every", "0"]),  # was "slice step cannot be zero"
        ("control_phase_sliding", ["--shifts", "-2"]),
    ],
)
def test_measurement_scripts_refuse_settings_that_measure_nothing(
    benchmark_script, script, argv, capsys
):
    with pytest.raises(SystemExit) as exit_info:
        benchmark_script(script).main(argv)
    assert exit_info.value.code == 2 and "Traceback" not in capsys.readouterr().err


def test_measurement_scripts_name_a_missing_run_in_one_line(benchmark_script, tmp_path, capsys):
    for script, argv in [
        ("play_latency", [str(tmp_path / "none")]),
        ("long_run_drift", ["pretrained:moglow-bandai", "--control", "moonwalk"]),
        ("contact_oracle", ["--out", str(tmp_path / "o"), "--baseline", str(tmp_path / "no")]),
    ]:
        assert benchmark_script(script).main(argv) == 2, script
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
