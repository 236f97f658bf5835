"""`motionflows export` and `motionflows.pretrained`: shippable runs that work in data units."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

import experiments.moglow as moglow
from motionflows import cli, pretrained
from motionflows.config import DataConfig, TrainConfig
from motionflows.errors import RunError
from motionflows.export import export_run
from motionflows.pretrained import PretrainedModel
from motionflows.training import evaluate_run, train

pytestmark = pytest.mark.usefixtures("fast_compilation")


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """A 3-step MoGlow on a small synthetic set and its export: (run dir, export dir)."""
    root = tmp_path_factory.mktemp("pretrained")
    config = moglow.Config(
        data=DataConfig(window=16, hop=8, synthetic_clips=8, synthetic_seconds=4.0),
        train=TrainConfig(steps=3, batch_size=4, eval_every=3, eval_batches=1, log_every=1),
        K=1,
        hidden=8,
        layers=1,
        tau=3,
        residual=True,
    )
    run_dir = root / "runs" / "moglow" / "tiny"
    train(moglow, config, run_dir=run_dir, progress=False)
    out = export_run(run_dir, root / "models" / "moglow-tiny", temperature=0.7)
    return run_dir, out


def _bytes(folder) -> int:
    return sum(f.stat().st_size for f in folder.rglob("*") if f.is_file())


def test_export_holds_no_optimiser_state_and_loads_like_the_run(exported):
    run_dir, out = exported
    for name in ("config.json", "standardizer.json", "metrics.jsonl", "pretrained.json"):
        assert (out / name).is_file(), name
    assert not (out / "checkpoints" / "latest").exists()
    assert _bytes(out / "checkpoints") < 0.6 * _bytes(run_dir / "checkpoints" / "best")
    info = json.loads((out / "pretrained.json").read_text())
    assert info["temperature"] == 0.7 and info["experiment"] == "moglow"
    a, b = PretrainedModel.from_run(run_dir), PretrainedModel.from_run(out)
    control = np.tile(np.array([0.05, 0.0, 0.01], np.float32), (2, 12, 1))
    np.testing.assert_array_equal(
        a.sample(control, seed=3, temperature=0.7), b.sample(control, seed=3, temperature=0.7)
    )
    assert b.temperature == 0.7 and a.temperature == 1.0  # the run itself has no validated T
    with pytest.raises(RunError, match="not empty"):
        export_run(run_dir, out)


def test_export_overwrite_replaces_only_an_export(exported, tmp_path):
    """``--overwrite`` replaced any non-empty folder: ``--out`` at the runs' folder deleted
    the run being exported and its siblings, ``--out RUN/checkpoints`` its checkpoints."""
    import shutil

    run_dir, out = exported
    runs_copy = tmp_path / "runs"
    shutil.copytree(run_dir, runs_copy / "tiny")
    (runs_copy / "sibling").mkdir()
    (runs_copy / "sibling" / "config.json").write_text("{}")
    for target, needle in [
        (runs_copy, "holds the run"),
        (runs_copy / "tiny" / "checkpoints", "inside the run"),
        (runs_copy / "sibling", "not an export"),
    ]:
        with pytest.raises(RunError, match=needle):
            export_run(runs_copy / "tiny", target, overwrite=True)
    assert (runs_copy / "sibling" / "config.json").is_file()
    assert (runs_copy / "tiny" / "checkpoints" / "best").is_dir()
    export_run(run_dir, out, temperature=0.7, overwrite=True)  # an export: replaced


def test_export_names_its_run_without_the_machines_paths(exported):
    """A shipped export names the run it came from as experiment/run-name: the absolute path
    of the machine that exported it is neither portable nor the user's business."""
    run_dir, out = exported
    (meta_file,) = (out / "checkpoints" / "best").glob("*/meta/metadata")
    meta = json.loads(meta_file.read_text())
    assert meta["exported_from"] == "moglow/tiny"
    assert str(run_dir.parent.parent) not in meta_file.read_text()


def test_a_failed_overwrite_keeps_the_old_export_and_the_run_is_read_once(
    exported, tmp_path, monkeypatch
):
    from motionflows import export as export_module
    from motionflows.checkpoints import Checkpointer

    run_dir, out = exported
    again = export_run(run_dir, tmp_path / "copy", temperature=0.5)
    before = {p.relative_to(again): p.read_bytes() for p in again.rglob("*") if p.is_file()}

    def broken(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(export_module, "_write_export", broken)
    with pytest.raises(OSError, match="disk full"):
        export_run(run_dir, again, overwrite=True)
    after = {p.relative_to(again): p.read_bytes() for p in again.rglob("*") if p.is_file()}
    assert after == before  # nothing already saved is lost
    assert [p.name for p in tmp_path.iterdir()] == ["copy"]  # no temporary folder left
    monkeypatch.undo()

    reads = []
    original = Checkpointer.restore
    monkeypatch.setattr(
        Checkpointer, "restore", lambda self, *a, **k: reads.append(1) or original(self, *a, **k)
    )
    export_run(run_dir, again, overwrite=True)
    assert len(reads) == 1
    assert json.loads((again / "pretrained.json").read_text())["step"] == 3
    monkeypatch.undo()

    # an export that could not be loaded is refused before anything is written
    for bad in (float("nan"), -3.0):
        with pytest.raises(ValueError, match="temperature"):
            export_run(run_dir, tmp_path / "hot", temperature=bad)
    no_std = tmp_path / "no_std"
    shutil.copytree(run_dir, no_std)
    (no_std / "standardizer.json").unlink()
    with pytest.raises(RunError, match="standardizer.json is missing"):
        export_run(no_std, tmp_path / "unloadable")
    assert not (tmp_path / "hot").exists() and not (tmp_path / "unloadable").exists()

    # a damaged pretrained.json is one error naming the file, not a raw JSON / KeyError
    damaged = {
        "{bad": "cannot be read",
        '{"temperature": "hot"}': "temperature",
        '{"scope": "elbo"}': "scope 'elbo'",
        "[1]": "JSON object",
    }
    for text, needle in damaged.items():
        (again / "pretrained.json").write_text(text)
        with pytest.raises(RunError, match=f"pretrained.json.*{needle}|{needle}.*pretrained"):
            PretrainedModel.from_run(again)
    # `sample` reads it too (a null temperature was a raw TypeError)
    (again / "pretrained.json").write_text('{"temperature": null}')
    argv = ["sample", str(again), "--seconds", "1", "--no-gif", "--out", str(tmp_path / "s")]
    assert cli.main(argv) == 2


def test_pretrained_model_speaks_data_units(exported):
    run_dir, out = exported
    model = PretrainedModel.from_run(out)
    control = np.tile(np.array([0.05, 0.0, 0.0], np.float32), (3, 16, 1))  # 1 m/s forward
    pose = model.sample(control, seed=0)
    assert pose.shape == (3, 16, 63) and pose.dtype == np.float32
    assert 0.3 < float(np.median(pose[..., 1])) < 1.5  # joint heights in metres, not std units
    assert not np.array_equal(pose, model.sample(control, seed=1))
    np.testing.assert_array_equal(pose, model.sample(control, seed=0))
    # log_prob: nats per frame in metres of the window scope = the eval table's number
    from motionflows.training import load_run

    _, _, _, ds = load_run(run_dir)
    rows = evaluate_run(run_dir, "test", print_table=False)
    window = next(r for r in rows if r["scope"] == "window")
    valid = np.asarray(ds.test.valid).all(axis=1)
    ll = model.log_prob(ds.test.pose[valid], ds.test.control[valid])
    assert ll.shape == (int(valid.sum()),)
    assert -float(np.mean(ll)) == pytest.approx(window["nats_per_frame_metres"], rel=1e-4)
    # the window scope needs no history: windows up to tau frames long score too (the
    # official scope, computed beside it, used to refuse them)
    short = model.log_prob(pose[:, :3], control[:, :3])
    assert short.shape == (3,) and np.isfinite(short).all()
    with pytest.raises(ValueError, match="temperature"):
        model.sample(control, temperature=-1.0)
    for seed in (1.7, "a"):  # 1.7 was silently seed 1
        with pytest.raises(ValueError, match="seed must be an integer"):
            model.sample(control, seed=seed)
    with pytest.raises(ValueError, match="NaN"):
        model.log_prob(np.full((1, 16, 63), np.nan, np.float32), control[:1])


def test_pretrained_names_and_cli(exported, monkeypatch, tmp_path, capsys):
    _, out = exported
    monkeypatch.setattr(pretrained, "MODELS_DIR", out.parent)
    assert pretrained.available() == ["moglow-tiny"]
    assert pretrained.path("moglow-tiny") == out
    assert pretrained.load("moglow-tiny").temperature == 0.7
    with pytest.raises(RunError, match="available: moglow-tiny"):
        pretrained.path("nope")
    code = cli.main(["sample", "pretrained:moglow-tiny", "--control", "walk", "--seconds", "1",
                     "--out", str(tmp_path), "--no-gif"])  # fmt: skip
    assert code == 0, capsys.readouterr().err
    (npz,) = tmp_path.glob("*.npz")
    assert "T0.7" in npz.name  # the validated temperature is the default
    code = cli.main(["eval", "pretrained:nope"])
    assert code == 2 and "no pretrained model 'nope'" in capsys.readouterr().err
    code = cli.main(["export", "pretrained:moglow-tiny", "--out", str(tmp_path / "copy"),
                     "--temperature", "0.6", "--notes", "trained on the tiny set"])  # fmt: skip
    assert code == 0 and (tmp_path / "copy" / "config.json").is_file()
    info = json.loads((tmp_path / "copy" / "pretrained.json").read_text())
    assert info["notes"] == "trained on the tiny set" and info["temperature"] == 0.6


def test_model_quality_labels_its_rows_with_the_step_it_scored(
    exported, benchmark_script, tmp_path, capsys
):
    """``benchmarks/model_quality.py --run`` scores the best checkpoint and says which step
    that is, not the step count the run was configured for (a best checkpoint can be older,
    a run can have stopped early)."""
    import shutil

    _, out = exported
    run = tmp_path / "stopped-early"
    shutil.copytree(out, run)
    config = json.loads((run / "config.json").read_text())
    config["config"]["train"]["steps"] = 500  # configured for 500 steps; its checkpoint: 3
    (run / "config.json").write_text(json.dumps(config))
    script = benchmark_script("model_quality")
    argv = ["moglow", "--run", str(run), "--temperatures", "1.0", "--windows", "4",
            "--sample-windows", "4", "--out", str(tmp_path / "quality")]  # fmt: skip
    assert script.main(argv) == 0
    (row,) = [json.loads(line) for line in capsys.readouterr().out.splitlines()
              if line.startswith("{")]  # fmt: skip
    assert row["steps"] == 3
    report = (tmp_path / "quality" / "QUALITY.md").read_text()
    assert "| 3 | 1 |" in report
    # the bench's two rows of real training motion beside the ground truth, scored alike
    assert "| *training takes (own controls)* | |" in report
    assert "| *nearest training window (test controls)* | |" in report
    assert (tmp_path / "quality" / "quality.jsonl").is_file()  # as the docstring says
    # flags that --run does not use are named, not silently dropped; bad input is one line
    assert script.main([*argv, "--preset", "cpu"]) == 0
    assert "--preset ignored with --run" in capsys.readouterr().err
    for bad in (["moglow", "--run", str(tmp_path / "none"), "--out", "x"],
                ["moglow", "--preset", "huge", "--out", "x"]):  # fmt: skip
        assert script.main(bad) == 2
        err = capsys.readouterr().err
        assert err.startswith("error:") and "Traceback" not in err


def test_model_quality_labels_a_passed_milestone_with_the_step_it_scored(
    benchmark_script, tmp_path, capsys
):
    """A milestone the run has already passed scored its newest checkpoint under the
    milestone's label (a resumed curve then showed step 10's model as step 5's)."""
    script = benchmark_script("model_quality")
    argv = ["moglow", "--preset", "smoke", "--data", "synthetic", "--split", "take",
            "--steps", "10,5", "--temperatures", "1.0", "--windows", "4",
            "--sample-windows", "4", "--out", str(tmp_path / "q")]  # fmt: skip
    assert script.main(argv) == 0
    captured = capsys.readouterr()
    rows = [json.loads(line) for line in captured.out.splitlines() if line.startswith("{")]
    assert [(r["milestone"], r["steps"]) for r in rows] == [(10, 10), (5, 10)]
    assert "milestone 5 scored the checkpoint of step 10" in captured.err


def test_sample_into_a_shared_out_keeps_every_runs_file(exported, tmp_path, capsys):
    run_dir, out = exported  # two run directories of the same tiny model
    args = ["--control", "walk", "--seconds", "1", "--temperature", "0.7", "--out", str(tmp_path),
            "--no-gif"]  # fmt: skip
    assert cli.main(["sample", str(run_dir), *args]) == 0, capsys.readouterr().err
    assert cli.main(["sample", str(out), *args]) == 0, capsys.readouterr().err
    files = sorted(tmp_path.glob("*.npz"))
    assert len(files) == 2  # the second run did not overwrite the first one's sample
    assert {str(np.load(f)["run_dir"]) for f in files} == {str(run_dir), str(out)}
    assert cli.main(["sample", str(out), *args]) == 0  # the same run again: replaced in place
    assert len(list(tmp_path.glob("*.npz"))) == 2


def test_foot_lock_keeps_the_drawn_samples_and_the_demo_shows_both(
    exported, monkeypatch, tmp_path, capsys
):
    """``--foot-lock`` writes the locked samples beside (never over) the drawn ones, which
    its npz keeps as ``pose_drawn``; only the legs move. ``make demo`` writes both."""
    from motionflows import demo

    _, out = exported
    args = ["sample", str(out), "--control", "walk", "--seconds", "1", "--num", "2",
            "--out", str(tmp_path), "--no-gif"]  # fmt: skip
    assert cli.main(args) == 0, capsys.readouterr().err
    assert cli.main([*args, "--foot-lock"]) == 0, capsys.readouterr().err
    drawn, locked = (np.load(f) for f in sorted(tmp_path.glob("*.npz")))  # "_foot-lock" last
    assert not drawn["foot_lock"] and locked["foot_lock"]
    np.testing.assert_array_equal(locked["pose_drawn"], drawn["pose"])
    moved = np.abs(locked["pose"] - drawn["pose"]).reshape(2, -1, 21, 3).max(axis=(0, 1, 3))
    assert set(np.flatnonzero(moved)) <= {2, 3, 4, 6, 7, 8}  # knees, ankles, toes
    take = tmp_path / "take.bvh"
    take.write_text("not read")
    assert cli.main(["render", str(take), "--foot-lock", "--out", str(tmp_path)]) == 2
    assert "--foot-lock holds the feet of sampled motion" in capsys.readouterr().err
    monkeypatch.setattr(pretrained, "MODELS_DIR", out.parent)
    monkeypatch.setattr(demo, "PRETRAINED", out.name)
    assert demo.pretrained_demo("walk", 1.0, tmp_path / "demo", gif=False)
    names = sorted(f.name for f in (tmp_path / "demo").glob("*.npz"))
    assert names == [f"{out.name}_walk.npz", f"{out.name}_walk_foot-lock.npz"]


def test_foot_lock_on_the_command_line_leaves_diverged_samples_as_drawn():
    """A sample that blew up (NaN) is kept as drawn, with a warning, and the others are
    locked: the foot lock would otherwise refuse the whole draw and nothing would be saved."""
    from motionflows.data.synthetic import straight_walk
    from motionflows.foot_lock import foot_lock

    walk = straight_walk(1.2, seconds=2.0)
    pose = np.stack([walk.pose, walk.pose, walk.pose]).astype(np.float32)
    pose[1, 10:] = np.nan
    with pytest.warns(UserWarning, match="1 of 3 samples diverged"):
        locked = cli._foot_lock(pose, walk.control)
    np.testing.assert_array_equal(locked[1], pose[1])
    np.testing.assert_allclose(locked[0], foot_lock(pose[:1], walk.control[None])[0])


def test_play_with_foot_lock_shows_and_records_the_held_feet(exported):
    """``play --foot-lock``: each streamed frame's joints are its (held) pose placed on the
    root path, only the legs differ from the drawn pose, and the recording keeps both."""
    from motionflows.play import load_character
    from motionflows.play.character import place

    _, out = exported
    character = load_character(out, temperature=0.7, foot_lock=True)
    character.target = np.array([1.2, 0.0, 0.3])
    for _ in range(30):
        frame = character.step()
        placed = place(frame["pose"], frame["position"], frame["yaw"])
        np.testing.assert_allclose(frame["joints"], placed, atol=1e-4)
    record = character.recording()
    assert record["pose"].shape == record["pose_drawn"].shape == (30, 63)
    moved = np.abs(record["pose"] - record["pose_drawn"]).reshape(30, 21, 3).max(axis=(0, 2))
    assert set(np.flatnonzero(moved)) <= {2, 3, 4, 6, 7, 8}
    character.reset()
    assert character.recording()["pose"].shape == (0, 63)


@pytest.mark.parametrize("name", pretrained.available())
def test_shipped_model_is_its_experiments_cpu_preset(name):
    """Each shipped model is its experiment's `cpu` preset trained on all Bandai takes (split
    by take): a preset changed without retraining the shipped model fails here."""
    import dataclasses

    from motionflows.config import config_from_json, read_config_json, to_dict
    from motionflows.runs import resolve_experiment

    path = pretrained.path(name) / "config.json"
    saved = read_config_json(path)
    module = resolve_experiment(saved["experiment"])
    assert saved["preset"] == "cpu"
    preset = module.PRESETS["cpu"]
    want = dataclasses.replace(
        preset, data=dataclasses.replace(preset.data, source="bandai", split_by="take")
    )
    assert to_dict(config_from_json(path, module.Config, saved)) == to_dict(want)


@pytest.mark.parametrize("name", pretrained.available())
def test_shipped_model_names_its_run_as_experiment_and_run_name(name):
    """The shipped exports name their runs as `motionflows export` does now
    (experiment/run-name), not by a path on the machine that trained them."""
    (meta_file,) = (pretrained.path(name) / "checkpoints" / "best").glob("*/meta/metadata")
    experiment, run_name = json.loads(meta_file.read_text())["exported_from"].split("/")
    config = json.loads((pretrained.path(name) / "config.json").read_text())
    assert experiment == config["experiment"] and run_name.startswith("ship-")


def test_the_fixed_length_glow_samples_its_window_and_warns_at_other_lengths(tmp_path, capsys):
    """The Glow learnt 80-frame windows: `sample` without --seconds draws one window, and a
    length it never saw (any multiple of 4 runs) warns instead of passing silently."""
    import warnings

    glow = pretrained.load("glow-bandai")
    assert glow.fixed_length and not pretrained.load("vae_lstm-bandai").fixed_length
    control = np.zeros((1, glow.window, 3), np.float32)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert glow.sample(control).shape == (1, glow.window, 63)
    with pytest.warns(UserWarning, match="trained on 80-frame windows"):
        glow.sample(np.zeros((1, glow.window + 4, 3), np.float32))
    # log_prob too: a likelihood at a length it never saw is not the window's
    pose = glow.sample(control)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert glow.log_prob(pose, control).shape == (1,)
    with pytest.warns(UserWarning, match="PretrainedModel.log_prob: .*trained on 80-frame"):
        glow.log_prob(pose[:, :40], control[:, :40])
    args = ["sample", "pretrained:glow-bandai", "--control", "walk", "--out", str(tmp_path),
            "--no-gif"]  # fmt: skip
    assert cli.main(args) == 0, capsys.readouterr().err
    (npz,) = tmp_path.glob("*.npz")
    assert np.load(npz)["pose"].shape == (1, glow.window, 63)
    assert "fixed-length" not in capsys.readouterr().err
    assert cli.main([*args, "--seconds", "4.2"]) == 0
    assert "outside what it learnt" in capsys.readouterr().err


@pytest.mark.parametrize("name, multiple", [("vae_lstm-bandai", 4), ("glow-bandai", 4)])
def test_sample_at_a_length_the_model_cannot_draw_names_the_seconds_that_work(
    name, multiple, tmp_path, capsys
):
    """2.1 s is 42 frames, which neither the VAE-LSTM (pooling by 2 twice) nor the two-level
    Glow can draw: the command says so in frames and seconds and offers the nearest lengths
    that work, instead of a model error that asks for another training window."""
    model = pretrained.load(name)
    assert model.frame_multiple == multiple
    with pytest.raises(ValueError, match="use a control of 40 or 44 frames"):
        model.sample(np.zeros((1, 42, 3), np.float32))  # the API says it in frames
    args = ["sample", f"pretrained:{name}", "--seconds", "2.1", "--no-gif", "--out", str(tmp_path)]
    assert cli.main(args) == 2
    err = capsys.readouterr().err
    assert "42 frames" in err and "--seconds 2 or 2.2" in err, err
    assert "data.window" not in err and "outside what it learnt" not in err, err
    assert not list(tmp_path.glob("*.npz"))
    assert cli.main([*args[:3], "2.2", *args[4:]]) == 0, capsys.readouterr().err
    assert pretrained.load("moglow-bandai").frame_multiple == 1


def test_sample_from_a_control_file_keeps_its_length_unless_seconds_asks(tmp_path, capsys):
    """A (T, 3) .npy control is drawn at its own T frames, as a .bvh take is (it was padded
    to the presets' 8 s, repeating its last frame for 6 s the user never asked for)."""
    control = np.zeros((40, 3), np.float32)
    control[:, 0] = 0.05  # a walk forward, 1 m/s
    np.save(tmp_path / "mine.npy", control)
    args = ["sample", "pretrained:moglow-bandai", "--control", str(tmp_path / "mine.npy"),
            "--no-gif"]  # fmt: skip
    assert cli.main([*args, "--out", str(tmp_path / "own")]) == 0, capsys.readouterr().err
    (npz,) = (tmp_path / "own").glob("*.npz")
    assert np.load(npz)["pose"].shape == (1, 40, 63)
    np.testing.assert_array_equal(np.load(npz)["control"], control)
    assert cli.main([*args, "--seconds", "1", "--out", str(tmp_path / "cut")]) == 0
    (npz,) = (tmp_path / "cut").glob("*.npz")
    assert np.load(npz)["pose"].shape == (1, 20, 63)


def test_a_control_far_outside_the_training_data_warns_and_names_the_units(tmp_path, capsys):
    """A walk given in m/s instead of m/frame (1.1 m/frame = 22 m/s, 37 training standard
    deviations out) used to be drawn without a word: the model extrapolates, the output looks
    like motion and is nonsense. It warns now, naming the channel and the per-frame units; the
    presets at their 8 s (the sidesteps reach 4.5 sd sideways) pass silently."""
    import warnings

    from motionflows.data.controls import PRESETS, load_control

    model = pretrained.load("moglow-bandai")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for name in PRESETS:
            model.sample(load_control(name, 8.0)[None])
    per_second = load_control("walk", 2.0) * model.fps
    with pytest.warns(
        UserWarning, match=r"forward .*m/frame.*divide m/s and rad/s by the fps"
    ) as seen:
        pose = model.sample(per_second[None])
    assert seen[0].filename == __file__  # the warning points at the caller's line
    # scoring poses under such a control is as meaningless as drawing them
    with pytest.warns(UserWarning, match=r"PretrainedModel.log_prob: control .*forward") as seen:
        model.log_prob(pose, per_second[None])
    assert seen[0].filename == __file__
    np.save(tmp_path / "per_second.npy", per_second)
    args = ["sample", "pretrained:moglow-bandai", "--control", str(tmp_path / "per_second.npy"),
            "--no-gif", "--out", str(tmp_path)]  # fmt: skip
    assert cli.main(args) == 0
    err = capsys.readouterr().err
    assert "standard deviations" in err and "Traceback" not in err, err
