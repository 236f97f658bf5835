"""The benchmark end to end at the CI-sized ``smoke`` budget, plus its configuration rules.

One module-scoped run trains every available model (tiny configs, 30 steps; the baselines
fit in closed form) on a small synthetic set and writes the report; the tests then check
the report's structure, the units (nats/frame in metres and bits/frame standardised are
tied by the standardiser's log-Jacobian), finite numbers in plausible ranges, and that a
second bench reuses the finished runs instead of retraining.
"""

from __future__ import annotations

import dataclasses
import json
import math
import shutil
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from motionflows import bench
from motionflows.config import to_dict
from motionflows.data import load_dataset
from motionflows.errors import RunError
from motionflows.evaluation import motion


def _available() -> list[str]:
    names = []
    for name in bench.ALL_MODELS:
        try:
            bench.load_experiment(name)
        except RunError:
            continue
        names.append(name)
    return names


MODELS = _available()

# the smoke bench checks reports and reuse, never speed: compile it cheaply (conftest.py)
pytestmark = pytest.mark.usefixtures("fast_compilation")


@pytest.fixture(scope="module")
def smoke(tmp_path_factory):
    root = tmp_path_factory.mktemp("bench")
    results = bench.run_benchmark(
        data="synthetic",
        models=MODELS,
        budget="smoke",
        out=root / "out",
        runs_dir=root / "runs",
        strict=True,
        progress=None,
    )
    return root, results


def _bench_again(smoke, out, models: str, overrides=(), gifs=False, **options) -> dict:
    """The smoke bench once more on ``models``, against the fixture's runs directory."""
    root, _ = smoke
    return bench.run_benchmark(
        data="synthetic", models=models, budget="smoke", out=out, runs_dir=root / "runs",
        strict=True, gifs=gifs, progress=None, overrides=overrides, **options,
    )  # fmt: skip


def test_all_five_models_are_benchmarked():
    # the baselines always exist; the deep models must be importable once they land
    assert {"gaussian", "linear_ar"} <= set(MODELS)


def test_report_files_and_structure(smoke):
    root, results = smoke
    out = root / "out"
    for f in ("BENCHMARK.md", "results.json", "nll_per_frame.png", "motion_metrics.png"):
        assert (out / f).is_file() and (out / f).stat().st_size > 0, f
    saved = json.loads((out / "results.json").read_text())
    assert saved["models"].keys() == results["models"].keys() == set(MODELS)
    for name in MODELS:
        assert (out / "gifs" / f"{name}.gif").stat().st_size > 0
    md = (out / "BENCHMARK.md").read_text()
    for header in (
        "nats/frame (m)",
        "bits/frame (std)",
        "scored frames",
        "temperature 1",
        "sample frames/s, batch 64",
        "ground truth",
        saved["command"],
        saved["machine"]["cpu"],
        "JAX",
    ):
        assert header in md, header
    for name in MODELS:
        assert f"**{name}**" in md
        assert "error" not in saved["models"][name], saved["models"][name].get("error")


def test_likelihood_units_and_ranges(smoke):
    _, results = smoke
    log_det = None
    for name in MODELS:
        lik = results["models"][name]["likelihood"]
        for scope, entry in lik.items():
            for split in ("test", "train"):
                row = entry[split]
                nats, bits = row["nats_per_frame_metres"], row["bits_per_frame_std"]
                assert math.isfinite(nats) and math.isfinite(bits)
                # standardised NLL of a 63-d pose: far from 0 only by a few hundred bits
                assert -400 < bits < 400, (name, scope, bits)
                lo, hi = row["nats_per_frame_metres_ci95"]
                assert lo <= nats <= hi
                # nats (m) = bits * ln 2 - log_det_per_frame: one offset for every model
                offset = bits * math.log(2) - nats
                if log_det is None:
                    log_det = offset
                assert offset == pytest.approx(log_det, abs=1e-6)
        assert lik["window" if name != "vae_lstm" else "elbo"]["test"]["windows"] >= 2
    # the standardiser's log-Jacobian of 63 values with cm-scale stds: tens of nats/frame
    assert 0 < log_det < 1000
    # identical frames: every model's window scope covers the whole window
    windows = {
        results["models"][n]["likelihood"].get("window", {}).get("frames")
        for n in MODELS
        if n != "vae_lstm"
    }
    assert windows == {results["window"]}


def test_scopes_and_bounds(smoke):
    _, results = smoke
    models = results["models"]
    if "moglow" in models:
        lik = models["moglow"]["likelihood"]
        tau = models["moglow"]["config"]["tau"]
        assert lik["official"]["frames"] == results["window"] - tau
        assert not lik["official"]["bound"]
    if "vae_lstm" in models:
        lik = models["vae_lstm"]["likelihood"]
        assert "window" not in lik  # no exact likelihood: bounds only
        assert {"elbo", "iwae_1", "iwae_10"} <= set(lik)
        assert all(entry["bound"] for entry in lik.values())
    for name in ("gaussian", "linear_ar", "glow_fixed"):
        if name in models:
            assert not models[name]["likelihood"]["window"]["bound"]
    # the fitted AR baseline beats the per-frame Gaussian on held-out windows
    g = models["gaussian"]["likelihood"]["window"]["test"]["nats_per_frame_metres"]
    ar = models["linear_ar"]["likelihood"]["window"]["test"]["nats_per_frame_metres"]
    assert ar < g


def test_per_frame_nll(smoke):
    _, results = smoke
    for name in MODELS:
        pf = results["models"][name]["per_frame_nll"]
        if name in ("gaussian", "linear_ar", "moglow"):
            assert pf["available"], name
            vals = np.asarray(pf["nats_per_frame_metres"], float)
            assert np.all(np.isfinite(vals))
            if pf["method"] == "exact per frame":
                # per-frame values average to the window NLL per frame
                window = results["models"][name]["likelihood"]["window"]["test"]
                assert vals.mean() == pytest.approx(window["nats_per_frame_metres"], abs=1e-3)
        else:
            assert not pf["available"] and "not available" in pf["method"]


def test_motion_quality_and_speed(smoke):
    _, results = smoke
    gt = results["ground_truth"]["motion"]
    assert gt["fd_pose"] == pytest.approx(0.0, abs=1e-6)
    assert gt["pose_error"] == 0.0 and gt["diversity"] > 0  # the data's natural diversity
    assert 0 <= gt["foot_sliding"] < 1.0  # real feet barely slide (m/s)
    assert 0 < gt["contact_rate"] <= 1
    for name in MODELS:
        entry = results["models"][name]
        m = entry["motion"]
        for key in bench.MOTION_METRICS:
            assert m[key] is not None and math.isfinite(m[key]) and m[key] >= 0, (name, key)
        assert m["fd_pose"] > 0 and m["diversity"] > 0  # samples differ from the data and
        assert m["pose_error"] < 2.0  # each other; errors in metres stay body-sized
        sp = entry["speed"]
        for key in ("sample_frames_per_s_b1", "sample_frames_per_s_b64"):
            assert sp[key] > 0
        if entry["config"]["train"]["steps"] > 0:
            assert sp["train_frames_per_s"] > 0
        assert entry["params"] > 0


def test_reference_rows_score_real_training_motion(smoke):
    root, results = smoke
    refs = results["references"]
    own, matched = refs["training_takes"], refs["nearest_training_window"]
    assert own["windows"] == matched["windows"] > 0
    for row in (own, matched):
        for key in ("foot_sliding", "contact_rate", "jerk", "fd_pose", "fd_window3"):
            assert math.isfinite(row[key]) and row[key] >= 0, key
    assert own["diversity"] > 0 and own["pose_error"] is None  # no test control was asked
    assert matched["diversity"] is None and matched["pose_error"] >= 0  # one motion each
    md = (root / "out" / "BENCHMARK.md").read_text()
    assert "*training takes (own controls)*" in md
    assert "*nearest training window (test controls)*" in md and "motion matching" in md


def test_nearest_training_window_returns_the_training_motion_of_the_nearest_control():
    # three training windows that differ in speed; the test asks for the second's control
    # (a little faster): its own poses come back, placed on the test control
    rng = np.random.default_rng(0)
    t = 12
    control = np.zeros((3, t, 3))
    control[:, :, 0] = np.array([0.02, 0.06, 0.12])[:, None]
    pose = rng.normal(size=(3, t, 63)) * 0.1 + np.tile([0.0, 0.9, 0.0], 21)
    train = SimpleNamespace(pose=pose, control=control, valid=None, take=np.array([0, 1, 2]))
    test_control = control[1:2] + [0.002, 0.0, 0.0]
    refs = bench.data_references(train, pose[1:2], test_control, fps=20.0)
    matched, own = refs["nearest_training_window"], refs["training_takes"]
    assert matched["pose_error"] == pytest.approx(0.0, abs=1e-12)  # the same poses
    assert matched["jerk"] == pytest.approx(
        motion.jerk(pose[1:2], fps=20.0, control=test_control)
    )  # ... on the test control
    assert own["jerk"] == pytest.approx(motion.jerk(pose, fps=20.0, control=control))
    assert own["windows"] == 3 and own["diversity"] > 0


def test_reference_rows_use_a_bounded_share_of_a_large_training_split(monkeypatch):
    # the natural diversity compares every pair of windows: a large split is subsampled
    from motionflows.bench import scoring

    monkeypatch.setattr(scoring, "REFERENCE_WINDOWS", 4)
    rng = np.random.default_rng(1)
    control = np.zeros((9, 10, 3))
    control[:, :, 0] = rng.uniform(0.01, 0.1, size=(9, 1))
    pose = rng.normal(size=(9, 10, 63)) * 0.1
    train = SimpleNamespace(pose=pose, control=control, valid=None, take=np.arange(9))
    refs = scoring.data_references(train, pose[:2], control[:2], fps=20.0)
    assert refs["training_takes"]["windows"] == refs["nearest_training_window"]["windows"] == 4


def test_second_bench_reuses_finished_runs(smoke, tmp_path):
    root, first = smoke
    again = _bench_again(smoke, tmp_path / "out", "gaussian,linear_ar")
    for name in ("gaussian", "linear_ar"):
        entry = again["models"][name]
        assert entry["reused"] and entry["run_dir"] == first["models"][name]["run_dir"]
        a = entry["likelihood"]["window"]["test"]["nats_per_frame_metres"]
        b = first["models"][name]["likelihood"]["window"]["test"]["nats_per_frame_metres"]
        assert a == pytest.approx(b, rel=1e-6)
    # a different config is not "the same run"
    data = bench.parse_data_spec("synthetic", "smoke")
    exp = bench.load_experiment("linear_ar")
    config, prov = bench.bench_config("linear_ar", "smoke", data, exp)
    assert bench.find_run(root / "runs", prov["experiment"], config) is not None
    other = config.__class__(**{**config.__dict__, "tau": config.tau + 1})
    assert bench.find_run(root / "runs", prov["experiment"], other) is None


def test_foot_lock_rows_score_the_locked_samples_beside_the_drawn(smoke, tmp_path):
    root, first = smoke
    assert "foot lock" not in (root / "out" / "BENCHMARK.md").read_text()
    again = _bench_again(smoke, tmp_path / "out", "linear_ar", gifs=True, foot_lock=True)
    entry = again["models"]["linear_ar"]
    drawn, locked = entry["motion"], entry["motion_foot_lock"]
    assert drawn["foot_sliding"] == pytest.approx(
        first["models"]["linear_ar"]["motion"]["foot_sliding"]
    )  # the drawn row is still the samples as drawn
    assert locked["foot_sliding"] < 0.5 * drawn["foot_sliding"]
    assert locked["bone_length_std"] == pytest.approx(drawn["bone_length_std"], rel=1e-3)
    text = (tmp_path / "out" / "BENCHMARK.md").read_text()
    assert "| linear_ar + foot lock |" in text and "they are not the models' samples" in text
    assert again["plots"]["gifs"]["linear_ar + foot lock"] == "gifs/linear_ar_foot-lock.gif"
    assert (tmp_path / "out" / "gifs" / "linear_ar_foot-lock.gif").stat().st_size > 0


def test_foot_locked_leaves_diverged_samples_as_drawn():
    from motionflows.bench.scoring import foot_locked

    data = bench.parse_data_spec("synthetic", "smoke").load()
    pose = np.asarray(data.test.pose[:3], np.float32).copy()
    control = np.asarray(data.test.control[:3], np.float32)
    pose[1, 5, 0] = np.nan
    out = foot_locked(pose, control)
    np.testing.assert_array_equal(out[1], pose[1])
    assert np.all(np.isfinite(out[[0, 2]])) and out.shape == pose.shape


def _run_dir(root: Path, entry: dict) -> Path:
    """A report entry's run directory (relative ones are under the fixture's root)."""
    run = Path(entry["run_dir"])
    return run if run.is_absolute() else root / run


def _linear_ar_copy(smoke, tmp_path) -> tuple[Any, dict, Path, Path]:
    """(config, provenance, run, copy): the smoke bench's linear AR run copied into
    ``tmp_path/runs`` under its own name, with the config the bench would train."""
    root, first = smoke
    data = bench.parse_data_spec("synthetic", "smoke")
    exp = bench.load_experiment("linear_ar")
    config, prov = bench.bench_config("linear_ar", "smoke", data, exp)
    run = _run_dir(root, first["models"]["linear_ar"])
    old = tmp_path / "runs" / prov["experiment"] / run.name
    shutil.copytree(run, old)
    return config, prov, run, old


def test_a_training_augmentation_set_for_one_model_trains_it_on_its_own_takes(smoke, tmp_path):
    """``--set data.tempo=...``: the model trains on its tempo-augmented takes (its own
    standardiser) and is scored on the bench's frames in its own units."""
    root, first = smoke
    again = _bench_again(smoke, tmp_path / "out", "linear_ar", ["data.tempo=1.25"])
    entry = again["models"]["linear_ar"]
    assert not entry["reused"] and entry["config"]["data"]["tempo"] == 1.25
    run, plain = _run_dir(root, entry), _run_dir(root, first["models"]["linear_ar"])
    own, shared = (json.loads((r / "standardizer.json").read_text()) for r in (run, plain))
    assert not np.allclose(own["pose_std"], shared["pose_std"])  # fitted on other windows
    a = entry["likelihood"]["window"]["test"]["nats_per_frame_metres"]
    b = first["models"]["linear_ar"]["likelihood"]["window"]["test"]["nats_per_frame_metres"]
    assert math.isfinite(a) and abs(a - b) < 0.2 * abs(b)  # the same frames, in metres
    report = (tmp_path / "out" / "BENCHMARK.md").read_text()
    assert "other training augmentation: linear_ar (tempo 1.25)" in report
    assert "other training augmentation" not in (root / "out" / "BENCHMARK.md").read_text()


def test_a_share_of_the_training_takes_set_for_one_model_is_scored_on_the_same_frames(
    smoke, tmp_path
):
    """``--set data.train_fraction=0.5``: the model trains on half its training takes (its
    own standardiser), is validated and scored on the bench's frames, and the report says
    which share it saw."""
    root, first = smoke
    again = _bench_again(smoke, tmp_path / "out", "linear_ar", ["data.train_fraction=0.5"])
    entry = again["models"]["linear_ar"]
    assert not entry["reused"] and entry["config"]["data"]["train_fraction"] == 0.5
    windows = [
        e["likelihood"]["window"]["test"]["windows"] for e in (entry, first["models"]["linear_ar"])
    ]
    assert windows[0] == windows[1]  # the bench's test frames, not a share of them
    run = _run_dir(root, entry)
    meta = json.loads((run / "config.json").read_text())["config"]["data"]
    assert meta["train_fraction"] == 0.5
    report = (tmp_path / "out" / "BENCHMARK.md").read_text()
    assert "style's takes): linear_ar 0.5. It is validated" in report
    assert "training windows, some of which it never saw" in report
    assert "share of the training takes" not in (root / "out" / "BENCHMARK.md").read_text()


def test_a_run_saved_before_a_config_field_existed_is_still_reused(smoke, tmp_path):
    """A field added later (here ``data.tempo``) takes its default for old runs, so the
    bench does not retrain them; a saved value other than the default still differs."""
    config, prov, run, old = _linear_ar_copy(smoke, tmp_path)
    payload = json.loads((old / "config.json").read_text())
    del payload["config"]["data"]["tempo"]
    (old / "config.json").write_text(json.dumps(payload))
    assert bench.find_run(tmp_path / "runs", prov["experiment"], config) == old
    payload["config"]["data"]["tempo"] = 1.25
    (old / "config.json").write_text(json.dumps(payload))
    assert bench.find_run(tmp_path / "runs", prov["experiment"], config) is None


def test_a_run_trained_on_other_devices_is_not_reused(smoke, tmp_path):
    """Data-parallel training on N devices sums the batch in another order, so its run is
    another training, not this one: the bench reuses only a run trained on as many devices
    as it has, in every segment of it (a run resumed on another count is neither; one saved
    before the history was kept counts as its ``"devices"``, before the count as one)."""
    config, prov, run, old = _linear_ar_copy(smoke, tmp_path)
    recorded = json.loads((run / "config.json").read_text())
    assert recorded["devices"] == 1 and recorded["device_counts"] == [1]
    payload = json.loads((old / "config.json").read_text())

    def reused_on(**saved):
        rest = {k: v for k, v in payload.items() if k not in ("devices", "device_counts")}
        (old / "config.json").write_text(json.dumps({**rest, **saved}))
        runs = tmp_path / "runs"
        return {n for n in (1, 4) if bench.find_run(runs, prov["experiment"], config, devices=n)}

    assert reused_on(devices=4, device_counts=[4]) == {4}
    assert reused_on(devices=1, device_counts=[1, 4]) == set()  # resumed on one device
    assert reused_on(devices=1, device_counts=[1]) == {1}
    assert reused_on(devices=4) == {4}
    assert reused_on() == {1}


def test_a_run_trained_on_other_data_is_not_reused(smoke, tmp_path):
    """Takes added to a folder leave the config as it was but change the split and the
    standardiser: a run is reused only when its standardizer.json is the one the data it
    would train on gives (else the bench scored it in another run's units)."""
    from motionflows.run import load_standardizer

    config, prov, run, old = _linear_ar_copy(smoke, tmp_path)
    std = load_standardizer(run)
    find = dict(runs_dir=tmp_path / "runs", experiment=prov["experiment"], config=config)
    assert bench.find_run(**find, standardizer=lambda: std) == old
    payload = json.loads((old / "standardizer.json").read_text())
    payload["pose_mean"] = [v + 0.02 for v in payload["pose_mean"]]
    (old / "standardizer.json").write_text(json.dumps(payload))
    assert bench.find_run(**find, standardizer=lambda: std) is None
    again = bench.run_benchmark(
        data="synthetic", models="linear_ar", budget="smoke", out=tmp_path / "out",
        runs_dir=tmp_path / "runs", strict=True, gifs=False, progress=None,
    )  # fmt: skip
    entry = again["models"]["linear_ar"]
    assert not entry["reused"] and Path(entry["run_dir"]) != old


def test_set_changes_the_trained_configs_and_is_never_reused(smoke, tmp_path, capsys):
    _, first = smoke
    data = bench.parse_data_spec("synthetic", "smoke")
    config, prov = bench.bench_config("moglow", "smoke", data, None, ["history_noise=0.1"])
    assert config.history_noise == 0.1 and prov["set"] == ["history_noise=0.1"]
    plain, prov = bench.bench_config("linear_ar", "smoke", data, None, ["history_noise=0.1"])
    assert prov["overrides_skipped"] == ["history_noise=0.1"] and "set" not in prov
    again = _bench_again(smoke, tmp_path / "out", "linear_ar", ["train.seed=3"])
    entry = again["models"]["linear_ar"]
    assert not entry["reused"] and entry["config"]["train"]["seed"] == 3
    assert entry["run_dir"] != first["models"]["linear_ar"]["run_dir"]
    with pytest.raises(RunError, match="no config of linear_ar has this key"):
        bench.check_overrides(["linear_ar"], "smoke", data, ["histroy_noise=0.1"])
    with pytest.raises(RunError, match="same data"):
        bench.bench_config("linear_ar", "smoke", data, None, ["data.window=8"])
    # training augmentation may differ per model: the scored frames stay the same
    tempo, prov = bench.bench_config("moglow", "smoke", data, None, ["data.tempo=1.25"])
    assert tempo.data.tempo == 1.25 and prov["set"] == ["data.tempo=1.25"]
    assert dataclasses.replace(tempo.data, tempo=1.0) == data
    args = ["--models", "linear_ar", "--budget", "smoke", "--out", str(tmp_path / "o2")]
    assert bench.main([*args, "--set", "train.seed=x"]) == 2
    assert "train.seed" in capsys.readouterr().err


def test_a_budgets_preset_keeps_its_training_augmentation():
    """The bench gives every model its frames, but a preset's training augmentation
    (mirror, reverse, tempo, its replays, the foot lock) is part of what the budget trains:
    the `cpu` MoGlow trains with its tempo on foot-locked takes, the `paper` MoGlow with
    time reversal, as `motionflows train` would."""
    import experiments.moglow as moglow
    from motionflows.bench.budgets import AUGMENTATION_FIELDS

    data = bench.parse_data_spec("synthetic", "cpu")
    for budget, preset in (("cpu", "cpu"), ("full", "paper")):
        config, _ = bench.bench_config("moglow", budget, data)
        own = moglow.PRESETS[preset].data
        kept = {f: getattr(own, f) for f in AUGMENTATION_FIELDS}
        assert config.data == dataclasses.replace(data, **kept), budget
    cpu = bench.bench_config("moglow", "cpu", data)[0].data
    assert cpu.tempo != data.tempo and cpu.foot_lock and not data.foot_lock
    assert bench.bench_config("moglow", "full", data)[0].data.reverse != data.reverse


def test_a_sampling_only_field_reuses_the_run_and_samples_as_asked(smoke, tmp_path):
    """``--set sampler=...`` (a VAE-LSTM ``SAMPLING_FIELDS`` entry) changes how the trained
    model samples, not its training: the bench reuses the finished run and loads it with
    the requested sampler (so the motion metrics change); loading a run with any other
    field changed is refused."""
    if "vae_lstm" not in MODELS:
        pytest.skip("no vae_lstm experiment")
    _, first = smoke
    before = first["models"]["vae_lstm"]
    assert before["config"]["sampler"] == "recurrent"
    again = _bench_again(smoke, tmp_path / "out", "vae_lstm", ["sampler=prior"])
    entry = again["models"]["vae_lstm"]
    assert entry["reused"] and entry["run_dir"] == before["run_dir"]
    assert entry["config"]["sampler"] == "prior"
    assert entry["motion"]["diversity"] != pytest.approx(before["motion"]["diversity"], rel=1e-3)
    # the training scopes are the same weights' (the ELBO does not depend on the sampler)
    a = entry["likelihood"]["elbo"]["test"]["nats_per_frame_metres"]
    assert a == pytest.approx(before["likelihood"]["elbo"]["test"]["nats_per_frame_metres"])
    from motionflows import run

    _, config, model, _ = run.restore_run(before["run_dir"], sampling={"sampler": "prior"})
    assert config.sampler == "prior" and model.sampler == "prior"
    with pytest.raises(RunError, match="only the experiment's SAMPLING_FIELDS"):
        run.restore_run(before["run_dir"], sampling={"latent_dim": 3})


def test_configs_share_one_data_config():
    data = bench.parse_data_spec("synthetic", "smoke")
    seen = set()
    for name in MODELS:
        config, prov = bench.bench_config(name, "smoke", data)
        seen.add(json.dumps(to_dict(config.data), sort_keys=True))
        assert prov["preset"] == "smoke" and not prov["overrides_skipped"]
    assert len(seen) == 1
    full, prov = bench.bench_config("linear_ar", "full", bench.parse_data_spec("synthetic"))
    assert prov["preset"] == "paper" and full.data.window == 80


def test_clear_errors(tmp_path, capsys):
    with pytest.raises(RunError, match="unknown model"):
        bench.parse_models("glow_fixed,nope")
    with pytest.raises(ValueError, match="synthetic"):
        bench.parse_data_spec("mocap")
    with pytest.raises(RunError, match="not a folder"):
        bench.parse_data_spec(f"bvh:{tmp_path / 'missing'}")
    with pytest.raises(RunError, match="budget"):
        bench.bench_config("gaussian", "huge", bench.parse_data_spec("synthetic"))
    assert bench.main(["--models", "nope", "--out", str(tmp_path)]) == 2
    assert "unknown model" in capsys.readouterr().err


def test_no_progress_trains_without_bars_and_keeps_the_bench_lines(monkeypatch, tmp_path):
    from motionflows.bench import benchmark, reuse

    seen, run_benchmark = {}, benchmark.run_benchmark
    monkeypatch.setattr(benchmark, "run_benchmark", lambda **kw: seen.update(kw) or {})
    args = ["--models", "linear_ar", "--budget", "smoke", "--out", str(tmp_path)]
    assert bench.main(args) == 0 and seen["training_bars"] is True
    assert bench.main([*args, "--no-progress"]) == 0 and seen["training_bars"] is False

    # run_benchmark hands it to obtain_run (stopped there: nothing is trained)
    class Reached(Exception):
        pass

    def fake_obtain_run(*args, training_bars, **kwargs):
        seen["obtain_run"] = training_bars
        raise Reached

    with monkeypatch.context() as m:
        m.setattr(benchmark, "obtain_run", fake_obtain_run)
        with pytest.raises(Reached):
            run_benchmark(
                models="linear_ar", budget="smoke", out=tmp_path / "o", runs_dir=tmp_path / "r",
                strict=True, progress=None, training_bars=False,
            )  # fmt: skip
    assert seen["obtain_run"] is False
    # down to the training call: no bar, while the bench's own lines still go to progress
    lines, trained = [], {}

    def fake_train_run(exp, config, run_dir, *, preset, progress, dataset=None):
        trained.update(progress=progress, dataset=dataset)

    monkeypatch.setattr(reuse, "train_run", fake_train_run)
    exp = bench.load_experiment("linear_ar")
    data = bench.parse_data_spec("synthetic", "smoke")
    config, prov = bench.bench_config("linear_ar", "smoke", data, exp)
    for bars in (True, False):
        reuse.obtain_run(
            "linear_ar", exp, config, prov, runs_dir=tmp_path / "runs", budget="smoke",
            data_tag="synthetic", retrain=True, progress=lines.append, training_bars=bars,
        )  # fmt: skip
        assert bool(trained["progress"]) is bars
    assert sum("training smoke preset" in line for line in lines) == 2
    # it says what the model trains on, as `motionflows train` does, and loads it once
    summary = trained["dataset"].summary()
    assert summary.startswith("synthetic, split by ")
    assert sum(line.endswith(f"] linear_ar: data: {summary}") for line in lines) == 2


def test_the_speed_section_says_when_sampling_ran_on_simulated_cpu_devices():
    from motionflows.bench.report import simulated_devices_note

    assert simulated_devices_note({"backend": "cpu", "devices": "1 x cpu"}) == ""
    assert simulated_devices_note({"backend": "gpu", "devices": "2 x NVIDIA H200"}) == ""
    assert "4 simulated CPU devices" in simulated_devices_note(
        {"backend": "cpu", "devices": "4 x cpu"}
    )


def test_bench_cpu_devices_flag_is_in_the_report_command_and_checked(capsys):
    from motionflows import cli_bench

    args = cli_bench.build_parser().parse_args(["--budget", "smoke", "--cpu-devices", "4"])
    assert cli_bench._command(args, ("moglow",)).endswith("--cpu-devices 4")
    # the report's command names every option that changes what was scored
    args = cli_bench.build_parser().parse_args(
        ["--data", "bandai", "--runs-dir", "elsewhere", "--no-performer-split"]
    )
    assert "--runs-dir elsewhere --no-performer-split" in cli_bench._command(args, ("moglow",))
    args = cli_bench.build_parser().parse_args(["--data", "bandai"])
    assert "--runs-dir" not in cli_bench._command(args, ("moglow",))
    assert "performer-split" not in cli_bench._command(args, ("moglow",))
    assert cli_bench.main(["--budget", "smoke", "--cpu-devices", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert (
        len(err) == 1
        and err[0].startswith("motionflows bench: error: --cpu-devices must be 1 .. 256")
        and err[0].endswith("got 0")
    )


def test_motion_metrics_count_and_drop_diverged_samples():
    rng = np.random.default_rng(0)
    ds = load_dataset("synthetic", n_clips=4, seconds=4.0, window=40, hop=40, cache=False)
    gt = np.asarray(ds.train.pose[:4], np.float64)
    ctrl = np.asarray(ds.train.control[:4], np.float64)
    samples = gt + 0.01 * rng.normal(size=gt.shape)
    clean = bench.motion_metrics(samples[1:], ctrl[1:], gt[1:], samples[1:], 20.0)
    blown = samples.copy()
    blown[0, 30:] = 1e20  # a flow inverse that blew up late in the window
    out = bench.motion_metrics(blown, ctrl, gt, blown, 20.0)
    assert out["diverged"] == pytest.approx(0.25) and clean["diverged"] == 0.0
    for key in ("foot_sliding", "jerk", "fd_pose", "diversity", "pose_error"):
        assert out[key] == pytest.approx(clean[key]), key
    blown[1:, 5, 0] = np.nan
    with pytest.raises(ValueError, match="all 4 samples diverged"):
        bench.motion_metrics(blown, ctrl, gt, None, 20.0)


def test_models_and_presets_come_from_the_experiments(monkeypatch):
    models = bench.bench_models()
    assert models["gaussian"] == ("baselines", {"model": "gaussian"})  # BENCH_MODELS
    assert models["linear_ar"].experiment == "baselines"
    data = bench.parse_data_spec("synthetic", "smoke")
    config, prov = bench.bench_config("gaussian", "smoke", data)
    assert config.model == "gaussian" and config.data == data
    assert prov["experiment"] == "baselines" and prov["overrides"]["model"] == "gaussian"
    # a budget whose preset an experiment lacks is refused, naming the preset
    monkeypatch.delitem(bench.load_experiment("linear_ar").PRESETS, "smoke")
    with pytest.raises(RunError, match="no preset 'smoke'"):
        bench.bench_config("linear_ar", "smoke", data)


def test_report_names_a_models_own_augmentation_in_words():
    from motionflows.bench.report import _own_training_data

    bench = {"mirror": True, "tempo": 1.0, "foot_lock": False}
    own = {"mirror": False, "tempo": 1.25, "foot_lock": True}
    results = {"data": {"config": bench}, "models": {"moglow": {"config": {"data": own}}}}
    text = _own_training_data(results)
    assert "moglow (mirror off, tempo 1.25, foot_lock on)" in text
    results["models"]["moglow"]["config"]["data"] = bench
    assert _own_training_data(results) == ""


def test_estimate_counts_the_validation_passes_of_the_training(capsys):
    # a budget's projection is steps x s/step plus each validation pass the run will make
    from motionflows.bench.estimate import estimate_training

    est = estimate_training(
        "synthetic", "moglow", "smoke", progress=None, overrides=["train.eval_every=10"]
    )
    e = est["models"]["moglow"]
    assert e["steps"] == 30 and e["validations"] == 3  # at steps 10, 20 and 30
    assert e["seconds_per_step"] > 0 and e["validation_seconds"] > 0
    total = e["seconds_per_step"] * 30 + 3 * e["validation_seconds"]
    assert e["projected_hours"] == pytest.approx(total / 3600)
    assert est["total_hours"] == pytest.approx(e["projected_hours"])
    with pytest.raises(RunError, match="train.lrr=5"):  # a typo changed nothing, silently
        estimate_training("synthetic", "moglow", "smoke", progress=None, overrides=["train.lrr=5"])


def test_test_data_sharing_training_takes_is_flagged(monkeypatch):
    """``--test-data`` holding takes the models trained on (the same folder as --data, say)
    is scored, but warned about and marked in results.json and the report."""
    from motionflows.bench import benchmark, report
    from motionflows.data import takes as takes_module

    data = bench.parse_data_spec("synthetic", "smoke")
    ds = data.load()
    train = ds.split("train")
    monkeypatch.setattr(
        takes_module,
        "load_takes",
        lambda *a, **k: SimpleNamespace(windows=train, label="same", skipped=[]),
    )
    with pytest.warns(UserWarning, match="not held out|are training or validation takes"):
        _, info = benchmark._test_data(ds, data, "bvh:/same", None)
    assert info["shared_with_training"] == sorted(set(np.asarray(train.take).tolist()))
    config = {"source": "synthetic", "fps": 20.0, "window": 40, "hop": 10, "split_by": "take"}
    lines = report._data_section({"test_data": info, "data": {"config": config}})
    assert any("Not held out" in line for line in lines)


def test_short_test_takes_get_their_own_motion_table(smoke, tmp_path, monkeypatch):
    """Test takes shorter than a window (padded) are left out of the likelihood and the
    motion of complete windows, and every model samples them for a table of their own,
    beside their recorded frames; the report's data note points to it."""
    from motionflows.bench import benchmark, report
    from motionflows.data.pipeline import make_windows
    from motionflows.data.synthetic import straight_walk

    clips = [dataclasses.replace(straight_walk(1.2, seconds=4.0), name="d_walk_x_001")]
    clips += [dataclasses.replace(straight_walk(2.4, seconds=s, seed=i), name=f"d_run_x_00{i}")
              for i, s in enumerate((1.2, 1.4, 0.5))]  # fmt: skip
    windows, _ = make_windows(clips, 32, 8, short="pad", min_frames=8)
    real = benchmark._test_data

    def short_test(dataset, data_cfg, test_data, progress):
        return dataset.with_test(windows), real(dataset, data_cfg, None, progress)[1]

    monkeypatch.setattr(benchmark, "_test_data", short_test)
    results = _bench_again(smoke, tmp_path / "out", ",".join(MODELS), foot_lock=True)
    # 3 short takes, 2 with the 16 frames sampled from a smoke take's start (0.5 s: 10)
    assert results["short_takes"] == {"windows": 2, "frames": [4, 16], "kinds": {"run": 2}}
    truth = results["ground_truth"]["motion_short_takes"]
    assert truth["fd_pose"] < 1e-6 and truth["jerk"] > 0
    for name in MODELS:
        motion = results["models"][name]["motion_short_takes"]
        assert set(short_takes_metrics()) <= set(motion) and motion["fd_pose"] > 0, name
    text = (tmp_path / "out" / "BENCHMARK.md").read_text()
    assert "### Motion on the short takes" in text and "(run 2)" in text
    assert "3 test takes are shorter than one window" in text
    assert "*Motion on the short takes* scores the first frames of 2" in text
    table = report.short_takes_table(results, MODELS)
    assert len(table.splitlines()) == 3 + 2 * len(MODELS)  # each model + its foot-locked draws
    drawn = results["models"]["linear_ar"]["motion_short_takes"]
    locked = results["models"]["linear_ar"]["motion_short_takes_foot_lock"]
    assert locked["foot_sliding"] < 0.5 * drawn["foot_sliding"]
    assert "| linear_ar + foot lock |" in text and "the same samples after the foot lock" in text


def short_takes_metrics():
    from motionflows.bench.short_takes import SHORT_METRICS

    return SHORT_METRICS


def test_report_says_how_many_test_takes_no_frame_of_is_scored():
    """A test take shorter than one window gives one padded window, which the bench does not
    score: the report counts them and names the script that does; no note without them."""
    from motionflows.bench import report

    config = {"source": "bandai", "fps": 20.0, "window": 80, "hop": 10, "split_by": "performer"}
    info = {"windows_test": 1153, "complete_windows_test": 1051}
    text = "".join(report._data_section({"data": {"config": config, "info": info}}))
    assert "102 test takes are shorter than one window" in text
    assert "benchmarks/short_takes.py" in text
    info = {"windows_test": 298, "complete_windows_test": 298}
    text = "".join(report._data_section({"data": {"config": config, "info": info}}))
    assert "shorter than one window" not in text
