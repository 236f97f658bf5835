"""Scoring, sampling and benchmarking a run on takes it never saw (motionflows.data.takes)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import experiments.moglow as moglow
from motionflows import cli
from motionflows.config import DataConfig, TrainConfig
from motionflows.data import clip_from_bvh, load_control
from motionflows.data.takes import load_takes
from motionflows.errors import MotionDataError
from motionflows.training import evaluate_run, train

pytestmark = pytest.mark.usefixtures("fast_compilation")

DEV = Path(__file__).resolve().parents[2] / "shared" / "data" / "bandai_locomotion_dev"
needs_data = pytest.mark.skipif(not DEV.is_dir(), reason="../shared/data not present")
# 3 takes of each of 3 contents: the take split gives each content 1 train, 1 val, 1 test take
TAKES = [
    f"dataset-1_{content}_{style}_001.bvh"
    for content in ("run", "dash", "walk-back")
    for style in ("active", "childish", "giant")
]


def _folder(path: Path, names) -> Path:
    path.mkdir(parents=True, exist_ok=True)
    for name in names:
        (path / name).symlink_to(DEV / name)
    return path


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """A 2-step MoGlow trained on 9 Bandai takes: (run dir, take folder)."""
    root = tmp_path_factory.mktemp("takes")
    data = _folder(root / "data", TAKES)
    config = moglow.Config(
        data=DataConfig(source="bandai", path=str(data), window=24, hop=8),
        train=TrainConfig(steps=2, batch_size=4, eval_every=2, eval_batches=1, log_every=1),
        K=1,
        hidden=8,
        layers=1,
        tau=3,
    )
    run_dir = root / "run"
    train(moglow, config, run_dir=run_dir, progress=False)
    return run_dir, data


@needs_data
def test_folder_of_the_test_takes_scores_as_the_test_split(tiny_run, tmp_path):
    run_dir, _ = tiny_run
    split = evaluate_run(run_dir, "test", print_table=False)
    test_takes = json.loads((run_dir / "eval_test.json").read_text())
    from motionflows.training import load_run

    _, _, _, ds = load_run(run_dir)
    names = sorted({f"{t}.bvh" for t in np.asarray(ds.test.take).tolist()})
    folder = _folder(tmp_path / "unseen", names)
    rows = evaluate_run(run_dir, data=f"bvh:{folder}", print_table=False)
    assert (run_dir / "eval_unseen.json").is_file()
    assert test_takes and len(rows) == len(split)
    for a, b in zip(split, rows, strict=True):
        assert a["scope"] == b["scope"] and a["windows"] == b["windows"]
        assert b["nats_per_frame_metres"] == pytest.approx(a["nats_per_frame_metres"], abs=1e-5)
        assert b["bits_per_frame_std"] == pytest.approx(a["bits_per_frame_std"], abs=1e-5)
    saved = json.loads((run_dir / "eval_unseen.json").read_text())
    assert saved["data"] == f"bvh:{folder}" and sorted(saved["takes"]) == [n[:-4] for n in names]


@needs_data
def test_a_folder_named_like_a_split_never_overwrites_its_table(tiny_run, tmp_path):
    run_dir, _ = tiny_run
    evaluate_run(run_dir, "test", print_table=False)
    before = (run_dir / "eval_test.json").read_text()
    folder = _folder(tmp_path / "test", TAKES[:3])
    evaluate_run(run_dir, data=f"bvh:{folder}", print_table=False)
    assert (run_dir / "eval_test.json").read_text() == before
    assert json.loads((run_dir / "eval_takes_test.json").read_text())["data"] == f"bvh:{folder}"


@needs_data
def test_short_takes_are_skipped_and_bvh_control_is_the_clip_control(tmp_path):
    take = DEV / "dataset-1_walk_active_001.bvh"
    control = load_control(take, fps=20.0)
    np.testing.assert_array_equal(control, clip_from_bvh(take, fps=20.0).control)
    assert control.shape == (len(clip_from_bvh(take)), 3)
    assert load_control(take, seconds=2.0).shape == (40, 3)
    names = ["dataset-1_walk_active_001.bvh", "dataset-1_dash_old_001.bvh"]
    folder = _folder(tmp_path / "mixed", names)
    takes = load_takes(f"bvh:{folder}", fps=20.0, window=80, hop=10)
    assert takes.label == "mixed"
    assert [s.split(" ")[0] for s in takes.skipped] == ["dataset-1_dash_old_001"]  # 2 s < 4 s
    assert set(takes.windows.take) == {"dataset-1_walk_active_001"}


@needs_data
def test_sample_driven_by_a_take_writes_it_beside_the_ground_truth(tiny_run, tmp_path, capsys):
    run_dir, data = tiny_run
    take = data / TAKES[0]
    code = cli.main(["sample", str(run_dir), "--control", str(take), "--out", str(tmp_path)])
    assert code == 0, capsys.readouterr().err
    (npz,) = tmp_path.glob("*.npz")
    with np.load(npz) as z:
        truth = clip_from_bvh(take, fps=20.0)
        np.testing.assert_array_equal(z["control"], truth.control)
        np.testing.assert_array_equal(z["ground_truth"], truth.pose)
        assert z["pose"].shape == (1, len(truth), 63)
    assert list(tmp_path.glob("*.gif"))
    # a folder gives one sample per take
    out = tmp_path / "folder"
    code = cli.main(["sample", str(run_dir), "--control", str(data), "--out", str(out),
                     "--seconds", "1", "--no-gif"])  # fmt: skip
    assert code == 0 and len(list(out.glob("*.npz"))) == len(TAKES)


@needs_data
def test_bad_takes_give_one_clear_line(tiny_run, tmp_path, capsys):
    run_dir, _ = tiny_run
    empty = tmp_path / "empty"
    empty.mkdir()
    short = _folder(tmp_path / "short", ["dataset-1_dash_old_001.bvh"])
    text = tmp_path / "notes.txt"
    text.write_text("not motion")
    cases = {
        f"bvh:{empty}": "no .bvh files",
        f"bvh:{tmp_path / 'missing'}": "does not exist",
        str(text): "not a .bvh file",
        "bvh:": "give a folder",
    }
    for spec, message in cases.items():
        code = cli.main(["eval", str(run_dir), "--data", spec])
        err = capsys.readouterr().err
        assert code == 2 and message in err and "Traceback" not in err, (spec, err)
    code = cli.main(["eval", str(run_dir), "--data", f"bvh:{short}", "--label", "x"])
    assert code == 0, capsys.readouterr().err  # a 2 s take still holds one 24-frame window
    with pytest.raises(MotionDataError, match="no take has the 200 frames"):
        load_takes(f"bvh:{short}", fps=20.0, window=200, hop=10)
    code = cli.main(["eval", str(run_dir), "--label", "x"])
    assert code == 2 and "go with --data" in capsys.readouterr().err


@needs_data
def test_bench_scores_every_table_on_the_test_data(tmp_path):
    from motionflows.bench import run_benchmark

    folder = _folder(tmp_path / "unseen", TAKES[:4])
    takes = load_takes(f"bvh:{folder}", fps=20.0, window=32, hop=8)
    results = run_benchmark(
        data="synthetic",
        models=("gaussian",),
        budget="smoke",
        out=tmp_path / "bench",
        runs_dir=tmp_path / "runs",
        gifs=False,
        progress=lambda *a: None,
        test_data=f"bvh:{folder}",
    )
    test = results["test_data"]
    assert test["spec"] == f"bvh:{folder}" and test["windows"] == len(takes.windows)
    assert sorted(test["takes"]) == sorted(n[:-4] for n in TAKES[:4])
    info = results["data"]["info"]  # the dataset's counts describe the swapped test split
    assert info["takes"]["test"] == 4 and info["windows"]["test"] == len(takes.windows)
    lik = results["models"]["gaussian"]["likelihood"]["window"]["test"]
    assert lik["windows"] == len(takes.windows)  # scored on the takes, not the split
    saved = json.loads((tmp_path / "bench" / "results.json").read_text())
    assert saved["test_data"]["spec"] == f"bvh:{folder}"
    assert "Test data: `bvh:" in (tmp_path / "bench" / "BENCHMARK.md").read_text()
