"""Bad input never costs memory, data or trust (issue 18).

From one small valid BVH written here, broken and extreme variants are generated and fed to
the CLI (in-process through ``motionflows.cli.main``; a child process only for the memory
cap and the working-directory check). Every case must exit 2 with one line that names the
problem, print no traceback, and leave an existing run directory byte-for-byte unchanged.
The Python API cases check the models' shared input validation.
"""

from __future__ import annotations

import csv
import errno
import hashlib
import http.server
import json
import logging
import os
import resource
import shutil
import socket
import subprocess
import sys
import threading
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_training_fakes import FakeDataset

from motionflows import cli, runs
from motionflows.checkpoints import Checkpointer, CheckpointWriteError
from motionflows.config import DataConfig
from motionflows.data import MotionDataError, clip_from_bvh, load_dataset
from motionflows.data.download import download_bandai, git_blob_sha1
from motionflows.data.features import MAX_RESAMPLED_FRAMES, resample

ROOT = Path(__file__).resolve().parents[1]
CONSOLE = Path(sys.executable).with_name("motionflows")

# ------------------------------------------------------------------- one valid BVH

# (name, parent, offset cm); every joint but the root has 3 rotation channels
JOINTS = [
    ("Hips", None, (0, 95, 0)),
    ("Spine", "Hips", (0, 10, 0)),
    ("Chest", "Spine", (0, 15, 0)),
    ("Neck", "Chest", (0, 20, 0)),
    ("Head", "Neck", (0, 10, 0)),
    ("UpperArm_L", "Chest", (15, 15, 0)),
    ("LowerArm_L", "UpperArm_L", (25, 0, 0)),
    ("Hand_L", "LowerArm_L", (25, 0, 0)),
    ("UpperArm_R", "Chest", (-15, 15, 0)),
    ("LowerArm_R", "UpperArm_R", (-25, 0, 0)),
    ("Hand_R", "LowerArm_R", (-25, 0, 0)),
    ("UpperLeg_L", "Hips", (10, 0, 0)),
    ("LowerLeg_L", "UpperLeg_L", (0, -45, 0)),
    ("Foot_L", "LowerLeg_L", (0, -42, 0)),
    ("Toes_L", "Foot_L", (0, -5, 12)),
    ("UpperLeg_R", "Hips", (-10, 0, 0)),
    ("LowerLeg_R", "UpperLeg_R", (0, -45, 0)),
    ("Foot_R", "LowerLeg_R", (0, -42, 0)),
    ("Toes_R", "Foot_R", (0, -5, 12)),
]
FRAMES, FRAME_TIME, SPEED_CM_S = 60, 1 / 30, 150.0
ROOT_Z, ROT0 = 2, 6  # motion columns: the root's Zposition, the first rotation after the root


def valid_motion() -> np.ndarray:
    """(FRAMES, 60) channel values: the root walks along +z at 1.5 m/s, legs swing."""
    t = np.arange(FRAMES) * FRAME_TIME
    motion = np.zeros((FRAMES, 6 + 3 * (len(JOINTS) - 1)))
    motion[:, 1] = 95.0
    motion[:, ROOT_Z] = SPEED_CM_S * t
    for k, (name, _, _) in enumerate(JOINTS[1:]):
        if name.startswith("UpperLeg"):
            sign = 1.0 if name.endswith("_L") else -1.0
            motion[:, ROT0 + 3 * k + 1] = sign * 20.0 * np.sin(2 * np.pi * t)  # Xrotation
    return motion


def bvh_text(motion=None, *, frame_time=f"{FRAME_TIME:.6f}", names=None) -> str:
    """The BVH file of ``motion`` (default :func:`valid_motion`); ``names`` renames joints."""
    motion = valid_motion() if motion is None else motion
    names = names or [j[0] for j in JOINTS]
    lines = ["HIERARCHY"]

    def block(index: int, depth: int) -> None:
        pad = "  " * depth
        offset = " ".join(str(v) for v in JOINTS[index][2])
        chans = "6 Xposition Yposition Zposition" if depth == 0 else "3"
        lines.extend(
            [
                f"{pad}{'ROOT' if depth == 0 else 'JOINT'} {names[index]}",
                pad + "{",
                f"{pad}  OFFSET {offset}",
                f"{pad}  CHANNELS {chans} Zrotation Xrotation Yrotation",
            ]
        )
        kids = [i for i, j in enumerate(JOINTS) if j[1] == JOINTS[index][0]]
        for i in kids:
            block(i, depth + 1)
        if not kids:
            lines.extend([f"{pad}  End Site", pad + "  {", f"{pad}    OFFSET 0 5 0", pad + "  }"])
        lines.append(pad + "}")

    block(0, 0)
    lines.extend(["MOTION", f"Frames: {len(motion)}", f"Frame Time: {frame_time}"])
    lines.extend(" ".join(f"{v:.6g}" for v in row) for row in motion)
    return "\n".join(lines) + "\n"


def with_value(row: int, col: int, value: float) -> str:
    motion = valid_motion()
    motion[row, col] = value
    return bvh_text(motion)


def test_the_generated_bvh_is_valid(tmp_path):
    path = tmp_path / "walk.bvh"
    path.write_text(bvh_text())
    clip = clip_from_bvh(path)
    assert np.all(np.isfinite(clip.pose)) and len(clip) == 39  # 2 s at 20 fps, less one
    # forward speed 1.5 m/s = 0.075 m per 20-fps frame
    np.testing.assert_allclose(np.median(clip.control[:, 0]), 0.075, rtol=0.05)


# ------------------------------------------------------------------------ helpers


def run_cli(capsys, *argv) -> tuple[int, str]:
    code = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out + err


def assert_one_clear_line(code: int, text: str, *needles: str) -> None:
    assert code == 2, text
    assert "Traceback" not in text, text
    errors = [line for line in text.splitlines() if line.startswith("error:")]
    assert len(errors) == 1, text
    for needle in needles:
        assert needle in errors[0], text


def snapshot(folder: Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha1(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


# -------------------------------------------------------------- BVH files (render)

BVH_CASES = {
    "frame time 100000 s": (bvh_text(frame_time="100000"), ["Frame Time", "10 s"]),
    "frame time 0": (bvh_text(frame_time="0"), ["Frame Time"]),
    "frame time 1e-6 s": (bvh_text(frame_time="1e-6"), ["Frame Time", "0.0001"]),
    "root at 1e30 cm": (with_value(5, 0, 1e30), ["Xposition", "Hips", "limit"]),
    "one channel 1e300": (with_value(7, ROOT_Z, 1e300), ["Zposition", "limit"]),
    "root 5 km away": (with_value(3, 0, 5e5), ["1000 m", "frame 3"]),
    "rotation 1e30 degrees": (with_value(2, ROT0 + 4, 1e30), ["rotation", "degrees"]),
    "NaN value": (with_value(4, 1, float("nan")), ["non-finite", "frame 4"]),
    "duplicate joint": (
        bvh_text(names=[j[0] if j[0] != "Neck" else "Spine" for j in JOINTS]),
        ["'Spine'", "more than one joint"],
    ),
    "truncated": (bvh_text()[: len(bvh_text()) // 2], ["truncated"]),
    "empty": ("", ["empty"]),
    "binary junk": (os.urandom(256).decode("latin-1"), ["HIERARCHY"]),
}


@pytest.mark.parametrize("case", list(BVH_CASES))
def test_bad_bvh_files_give_one_clear_line(case, tmp_path, capsys):
    text, needles = BVH_CASES[case]
    path = tmp_path / "bad.bvh"
    path.write_text(text, encoding="utf-8", errors="surrogateescape")
    code, out = run_cli(capsys, "render", path, "--out", tmp_path / "renders")
    assert_one_clear_line(code, out, str(path), *needles)
    assert not (tmp_path / "renders").exists() or not any((tmp_path / "renders").iterdir())


def test_resampler_refuses_before_allocating():
    # 1801 frames at 1 fps -> 200 fps would be 360 001 frames, one beyond the cap
    with pytest.raises(ValueError, match=str(MAX_RESAMPLED_FRAMES)):
        resample(np.zeros((1801, 1)), 1.0, 200.0)
    with pytest.raises(ValueError, match="times longer"):
        resample(np.zeros((3, 1)), 0.1, 1000.0)


def _capped(limit_bytes: int):
    def pre():
        resource.setrlimit(resource.RLIMIT_AS, (limit_bytes, limit_bytes))

    return pre


@pytest.mark.skipif(not CONSOLE.exists(), reason="console script not installed")
def test_header_values_cannot_exhaust_memory(tmp_path):
    """Under a 2 GB address-space cap: Frame Time 100000 (once 21.5 GB) and a 10 s frame
    time resampled to 1000 fps end in one clear line."""
    (tmp_path / "slow.bvh").write_text(bvh_text(frame_time="100000"))
    (tmp_path / "ten.bvh").write_text(bvh_text(frame_time="10"))
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    for name, extra, needle in (
        ("slow.bvh", [], "Frame Time"),
        ("ten.bvh", ["--fps", "1000"], "times longer"),
    ):
        proc = subprocess.run(
            [str(CONSOLE), "render", str(tmp_path / name), "--out", str(tmp_path / "r"), *extra],
            preexec_fn=_capped(2 * 2**30),
            capture_output=True,
            text=True,
            timeout=120,
            env=env,
        )
        assert_one_clear_line(proc.returncode, proc.stdout + proc.stderr, needle)


# ------------------------------------------------------------- folders and --data


def _folder_of_takes(folder: Path, n: int) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        motion = valid_motion()
        motion[:, 0] += 10.0 * i  # distinct takes
        (folder / f"take{i}.bvh").write_text(bvh_text(motion))
    return folder


def test_data_folder_problems(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("MOTIONFLOWS_CACHE", str(tmp_path / "cache"))
    one = _folder_of_takes(tmp_path / "one", 1)
    common = ["--runs-dir", tmp_path / "runs", "--no-progress"]
    code, out = run_cli(capsys, "train", "baselines", "--data", f"bvh:{one / 'take0.bvh'}", *common)
    assert_one_clear_line(code, out, "take0.bvh", "is a file", "bvh:DIR")
    code, out = run_cli(capsys, "train", "baselines", "--data", f"bvh:{one}", *common)
    assert_one_clear_line(code, out, "at least 3 takes")
    bad = _folder_of_takes(tmp_path / "bad", 3)
    (bad / "take1.bvh").write_text(with_value(2, ROT0, 1e30))
    code, out = run_cli(capsys, "train", "baselines", "--data", f"bvh:{bad}", *common)
    assert_one_clear_line(code, out, "take1.bvh", "degrees")
    assert not (tmp_path / "runs").exists()


def test_symlink_loops_are_skipped_with_a_warning(tmp_path):
    folder = _folder_of_takes(tmp_path / "takes", 3)
    (folder / "loop").symlink_to(folder, target_is_directory=True)
    (folder / "a.bvh").symlink_to(folder / "b.bvh")
    (folder / "b.bvh").symlink_to(folder / "a.bvh")
    with pytest.warns(UserWarning, match="symlink loop") as record:
        ds = load_dataset("bvh", path=folder, window=20, hop=10, cache=False)
    assert "a.bvh" in str(record[0].message)
    assert sum(ds.info["takes"].values()) == 3


def test_a_too_short_take_gets_a_warning_with_a_usable_fix(tmp_path):
    folder = _folder_of_takes(tmp_path / "takes", 3)
    (folder / "short.bvh").write_text(bvh_text(valid_motion()[:3]))
    with pytest.warns(UserWarning, match="dropped") as record:
        load_dataset("bvh", path=folder, window=20, hop=10, cache=False)
    message = next(str(w.message) for w in record if "dropped" in str(w.message))
    assert "short (" in message and "min_frames=5" in message
    assert "use short='pad'" not in message  # short='pad' is what is already in use


# ----------------------------------------------------------------- training settings


@pytest.mark.parametrize(
    "setting, needle",
    [
        ("lr=nan", "train.lr"),
        ("lr=-1", "train.lr"),
        ("eval_every=0", "train.eval_every"),
        ("log_every=0", "train.log_every"),
        ("checkpoint_every=0", "train.checkpoint_every"),
        ("batch_size=0", "train.batch_size"),
        ("fps=0", "data.fps"),
        ("fps=inf", "data.fps"),
        ("clip_norm=-1", "train.clip_norm"),
        ("b2=1", "train.b2"),
    ],
)
def test_bad_settings_are_refused_before_training(setting, needle, tmp_path, capsys):
    code, out = run_cli(
        capsys, "train", "baselines", "--runs-dir", tmp_path, "--set", setting, "--no-progress"
    )
    assert_one_clear_line(code, out, needle, setting.split("=")[1])
    assert not any(tmp_path.iterdir())


# ------------------------------------------------------------- damaged run directories


@pytest.fixture(scope="module")
def trained_run(tmp_path_factory):
    """One fitted baselines run (closed form, fake data), copied by the tests that damage it."""
    root = tmp_path_factory.mktemp("runs")
    data = FakeDataset()
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(DataConfig, "load", lambda self: data)
        code = cli.main(
            ["train", "baselines", "--run-name", "good", "--runs-dir", str(root),
             "--no-progress", "--no-eval", "--set", "tau=2", "train.batch_size=8"]
        )  # fmt: skip
    assert code == 0
    return root / "baselines" / "good"


@pytest.fixture
def run_copy(trained_run, tmp_path):
    def copy(name: str = "r") -> Path:
        dest = tmp_path / "runs" / "baselines" / name
        shutil.copytree(trained_run, dest)
        return dest

    return copy


def _edit_config(run: Path, change) -> None:
    payload = json.loads((run / "config.json").read_text())
    change(payload)
    (run / "config.json").write_text(json.dumps(payload))


@pytest.mark.parametrize(
    "damage, needles",
    [
        (lambda p: p["config"].update(tau="abc"), ["config.json", "tau", "'abc'"]),
        (lambda p: p.pop("experiment"), ["config.json", "'experiment'"]),
        (lambda p: p.update(experiment="PIL"), ["unknown experiment 'PIL'"]),
        (lambda p: p["config"]["train"].update(lr=-1.0), ["config.json", "train.lr"]),
    ],
)
def test_damaged_config_json_names_file_and_field(damage, needles, run_copy, capsys):
    run = run_copy()
    _edit_config(run, damage)
    before = snapshot(run)
    for command in ("eval", "sample"):
        code, out = run_cli(capsys, command, run, *(["--no-gif"] if command == "sample" else []))
        assert_one_clear_line(code, out, *needles)
    assert snapshot(run) == before


def test_truncated_config_json(run_copy, capsys):
    run = run_copy()
    text = (run / "config.json").read_text()
    (run / "config.json").write_text(text[: len(text) // 2])
    before = snapshot(run)
    code, out = run_cli(capsys, "eval", run)
    assert_one_clear_line(code, out, str(run / "config.json"), "not valid JSON")
    code, out = run_cli(capsys, "train", "baselines", "--resume", "--run-name", "r",
                        "--runs-dir", run.parents[1], "--no-progress")  # fmt: skip
    assert_one_clear_line(code, out, "config.json", "not valid JSON")
    assert snapshot(run) == before


def test_missing_standardizer_and_bad_flags_leave_the_run_alone(run_copy, tmp_path, capsys):
    run = run_copy()
    (run / "standardizer.json").unlink()
    before = snapshot(run)
    code, out = run_cli(capsys, "sample", run, "--no-gif", "--seconds", 1)
    assert_one_clear_line(code, out, "standardizer.json", "missing")
    assert snapshot(run) == before
    good = run_copy("g")
    before = snapshot(good)
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    for argv, needles in (
        (["sample", good, "--seconds", "1e9"], ["--seconds", "3600"]),
        (["sample", good, "--num", "100000000"], ["--num", "1024"]),
        (["sample", good, "--temperature", "-1"], ["--temperature", "-1"]),
        (["sample", good, "--temperature", "nan"], ["--temperature", "nan"]),
        (["sample", good, "--out", a_file, "--seconds", 1], ["--out", "is a file"]),
        (["render", a_file.with_suffix(".npz"), "--out", a_file], ["not found"]),
        (["data", "download", "bandai", "--dest", a_file], ["--dest", "is a file"]),
        (["train", "baselines", "--resume", "--run-name", "g", "--runs-dir", good.parents[1],
          "--set", "lr=nan"], ["train.lr"]),
    ):  # fmt: skip
        code, out = run_cli(capsys, *argv, *(["--no-gif"] if argv[0] == "sample" else []))
        assert_one_clear_line(code, out, *needles)
    np.savez(tmp_path / "clip.npz", pose=np.zeros((3, 63)), control=np.zeros((3, 3)))
    code, out = run_cli(capsys, "render", tmp_path / "clip.npz", "--out", a_file)
    assert_one_clear_line(code, out, "--out", "is a file")
    code, out = run_cli(capsys, "bench", "--out", a_file)
    assert_one_clear_line(code, out, "--out", "is a file")
    code, out = run_cli(capsys, "eval", good, "--batch-size", 0)
    assert_one_clear_line(code, out, "--batch-size")
    for pose, control, needle in (
        (np.zeros((3, 5)), np.zeros((3, 3)), "(T, 63)"),
        (np.zeros((0, 63)), np.zeros((0, 3)), "T >= 1"),
        (np.full((3, 63), np.nan), np.zeros((3, 3)), "NaN"),
    ):
        np.savez(tmp_path / "bad.npz", pose=pose, control=control)
        code, out = run_cli(capsys, "render", tmp_path / "bad.npz", "--out", tmp_path / "r")
        assert_one_clear_line(code, out, "bad.npz", needle)
    assert snapshot(good) == before and a_file.read_text() == "x"


def test_runs_lists_healthy_runs_beside_broken_ones(run_copy, capsys):
    good, noisy, junk, broken = (run_copy(n) for n in ("good", "noisy", "junk", "broken"))
    rows = (good / "metrics.jsonl").read_bytes()
    (noisy / "metrics.jsonl").write_bytes(b'{"step": 0, "lo\n' + rows + b"\xff\xfe[1,\n")
    (junk / "metrics.jsonl").write_bytes(np.random.default_rng(0).bytes(4000))
    (broken / "config.json").write_text('{"experiment": "baselines", "con')
    every = (good, noisy, junk, broken)
    before = [snapshot(r) for r in every]
    code, out = run_cli(capsys, "runs", "--root", good.parents[1])
    assert code == 0 and "Traceback" not in out
    table = {line.split()[1]: line for line in out.splitlines() if line.startswith("baselines ")}
    assert set(table) == {"good", "noisy", "junk"}
    assert "fitted" in table["good"] and "fitted" in table["noisy"]
    assert "damaged" in table["noisy"] and "damaged" in table["junk"]
    assert sum("broken run" in line and str(broken) in line for line in out.splitlines()) == 1
    with pytest.warns(UserWarning, match="skipped 2 damaged line.*first: line 1"):
        assert runs.read_metrics(noisy) == runs.read_metrics(good)
    assert [snapshot(r) for r in every] == before


# --------------------------------------------------------------------- checkpoints


def _state(x: float) -> dict:
    return {"params": {"w": jnp.full((4,), x)}}


def test_truncated_latest_checkpoint_falls_back_to_the_previous(tmp_path, capsys, caplog):
    ckpt = Checkpointer(tmp_path / "ck", keep=3)
    for step in (1, 2):
        ckpt.save(step, _state(float(step)), {"step": step})
    ckpt.close()
    files = [p for p in (tmp_path / "ck" / "latest" / "2").rglob("*") if p.is_file()]
    for p in files:  # every file of step 2 cut to half
        p.write_bytes(p.read_bytes()[: p.stat().st_size // 2])
    ckpt = Checkpointer(tmp_path / "ck", keep=3)
    state, meta = ckpt.restore({"params": {"w": jnp.zeros(4)}})
    ckpt.close()
    assert meta["step"] == 1 and float(state["params"]["w"][0]) == 1.0
    err = capsys.readouterr().err
    assert "[2]" in err and "using step 1" in err
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR]  # no orbax noise


def test_full_disk_during_a_checkpoint_is_one_line(tmp_path, monkeypatch):
    ckpt = Checkpointer(tmp_path / "ck")

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(ckpt.managers["latest"], "save", full)
    with pytest.raises(CheckpointWriteError, match="No space left on device") as info:
        ckpt.save(1, _state(1.0), {"step": 1})
    ckpt.close()
    assert "\n" not in str(info.value) and "--resume" in str(info.value)

    from motionflows.training import report_errors

    def train_that_fills_the_disk():
        raise info.value

    assert report_errors(train_that_fills_the_disk) == 2


# --------------------------------------------------------------------------- download


def _manifest(path: Path, rows: list[dict]) -> Path:
    with open(path, "w", newline="") as fh:
        writer = csv.DictWriter(fh, ["file", "source_path", "git_blob_sha1", "bytes", "content"])
        writer.writeheader()
        writer.writerows(rows)
    return path


def _row(name: str, data: bytes) -> dict:
    return {"file": name, "source_path": name, "git_blob_sha1": git_blob_sha1(data),
            "bytes": len(data), "content": "walk"}  # fmt: skip


class _Quiet(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args):
        pass


def test_download_stays_in_dest_caps_sizes_and_fails_fast(tmp_path):
    data = b"abc"
    evil = _manifest(tmp_path / "evil.csv", [_row("../escaped.bvh", data)])
    with pytest.raises(MotionDataError, match="outside the destination"):
        download_bandai(tmp_path / "dest", base_url="http://127.0.0.1:9/", manifest=evil)
    assert not (tmp_path / "escaped.bvh").exists()

    # a server sending more than the manifest's size for a file
    mirror = tmp_path / "mirror"
    mirror.mkdir()
    (mirror / "big.bvh").write_bytes(b"x" * 100_000)
    manifest = _manifest(tmp_path / "m.csv", [_row("big.bvh", data)])
    handler = lambda *a, **k: _Quiet(*a, directory=str(mirror), **k)  # noqa: E731
    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=httpd.serve_forever, daemon=True).start()
    try:
        url = f"http://127.0.0.1:{httpd.server_address[1]}/"
        with pytest.raises(MotionDataError, match="100000 bytes, expected 3"):
            download_bandai(tmp_path / "d2", base_url=url, manifest=manifest, retries=0,
                            progress=False)  # fmt: skip
    finally:
        httpd.shutdown()
        httpd.server_close()
    assert not (tmp_path / "d2" / "big.bvh").exists()
    # the folder's manifest is the one the files were checked against, not the packaged one
    assert (tmp_path / "d2" / "manifest.csv").read_bytes() == manifest.read_bytes()

    # an unreachable server: one error after the first file's tries, not one per file
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # closed again: connections are refused
    many = _manifest(tmp_path / "many.csv", [_row(f"f{i}.bvh", data) for i in range(50)])
    events = []
    with pytest.raises(MotionDataError, match="cannot reach") as info:
        download_bandai(tmp_path / "d3", base_url=f"http://127.0.0.1:{port}/", manifest=many,
                        progress=events.append, retries=1, timeout=2.0)  # fmt: skip
    assert events == [] and "\n" not in str(info.value)


# ------------------------------------------------------------ nothing from the cwd


def test_experiments_come_from_entry_points_not_the_working_directory(tmp_path):
    assert {"moglow", "glow_fixed", "vae_lstm", "baselines"} <= set(runs.available_experiments())
    with pytest.raises(Exception, match="unknown experiment 'nope'; available: baselines"):
        runs.resolve_experiment("nope")
    assert runs.resolve_experiment("moglow").__file__ == str(ROOT / "experiments" / "moglow.py")
    if not CONSOLE.exists():
        pytest.skip("console script not installed")
    marker = tmp_path / "ran"
    plant = f"open({str(marker)!r}, 'w').write('imported from the cwd')\n"
    for package in ("experiments", "PIL", "orbax"):
        (tmp_path / package).mkdir()
        (tmp_path / package / "__init__.py").write_text(plant)
        (tmp_path / package / "moglow.py").write_text(plant)
    run = tmp_path / "runs" / "moglow" / "r"
    run.mkdir(parents=True)
    (run / "config.json").write_text(json.dumps({"experiment": "moglow", "config": {}}))
    proc = subprocess.run(
        [str(CONSOLE), "eval", "runs/moglow/r"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONPATH": ""},
    )
    assert_one_clear_line(proc.returncode, proc.stdout + proc.stderr, "no checkpoint")
    assert not marker.exists()


# ------------------------------------------------------------------ the Python API


@pytest.fixture(scope="module")
def models():
    from flax import nnx

    from motionflows.models.moglow import MoGlow
    from motionflows.models.vae_lstm import VAELSTM

    moglow = MoGlow(63, 3, tau=2, K=1, hidden=8, num_layers=1, rngs=jax.random.key(0))
    vae = VAELSTM(kernel=3, latent_dim=8, control_hidden=8, control_features=8, pose_hidden=8,
                  pose_features=16, decoder_hidden=8, rngs=nnx.Rngs(0))  # fmt: skip
    return moglow, vae


def _inputs(b=2, t=8):
    rng = np.random.default_rng(0)
    return rng.normal(size=(b, t, 63)).astype(np.float32), np.zeros((b, t, 3), np.float32)


def _entry_points(moglow, vae):
    key = jax.random.key(0)
    return {
        "MoGlow.log_prob": lambda x, c: moglow.log_prob(x, c),
        "VAELSTM.elbo": lambda x, c: vae.elbo(x, c, key),
    }


@pytest.mark.parametrize(
    "make, needle",
    [
        (lambda x, c: (_nan(x), c), "pose contains non-finite values"),
        (lambda x, c: (_inf_first_frame(x), c), "non-finite"),
        (lambda x, c: (x, _nan(c)), "control contains non-finite"),
        (lambda x, c: (x.astype(np.int32), c), "dtype int32"),
        (lambda x, c: (x > 0, c), "dtype bool"),
        (lambda x, c: (x[:0], c[:0]), "empty"),
    ],
)
def test_models_validate_inputs_with_the_same_message(models, make, needle):
    x, c = _inputs()
    x, c = make(x, c)
    messages = []
    for name, fn in _entry_points(*models).items():
        with pytest.raises(ValueError, match=needle) as info:
            fn(x, c)
        assert str(info.value).startswith(name)
        messages.append(str(info.value).split(": ", 1)[1])
    assert messages[0] == messages[1]


def _nan(a):
    a = np.array(a)
    a[0, 3, 0] = np.nan
    return a


def _inf_first_frame(a):
    a = np.array(a)
    a[1, 0, 2] = np.inf  # a history frame of MoGlow's official scope
    return a


def test_float16_is_computed_in_float32_and_temperature_is_checked(models):
    moglow, vae = models
    x, c = _inputs()
    np.testing.assert_allclose(
        moglow.log_prob(x.astype(np.float16), c.astype(np.float16)),
        moglow.log_prob(x.astype(np.float16).astype(np.float32), c),
        rtol=1e-5,
    )
    assert np.all(np.isfinite(vae.elbo(x.astype(jnp.bfloat16), c, jax.random.key(0))))
    import experiments.moglow as moglow_exp
    import experiments.vae_lstm as vae_exp

    for wrapper, model in ((moglow_exp.sample, moglow), (vae_exp.sample, vae)):
        for bad in (-1.0, float("nan"), float("inf")):
            with pytest.raises(ValueError, match="temperature must be a finite number >= 0"):
                wrapper(model, jax.random.key(0), c, temperature=bad)
        with pytest.raises(ValueError, match="control is empty"):
            wrapper(model, jax.random.key(0), c[:0])
    with pytest.raises(ValueError, match="temperature"):
        moglow.stream_step(moglow.init_stream(2), c[:, 0], jax.random.key(0), temperature=-1)


def test_checks_do_not_break_jit(models):
    moglow, vae = models
    x, c = _inputs()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        jitted = jax.jit(lambda m, x, c: m.log_prob(x, c))(moglow, x, c)
    np.testing.assert_allclose(jitted, moglow.log_prob(x, c), rtol=1e-5, atol=1e-4)


def test_a_damaged_checkpoint_is_one_line_on_the_command_line(tmp_path):
    """The reads orbax still has in flight when a damaged checkpoint fails finish on
    tensorstore's threads after its event loop closed; their echoes ("Event loop is
    closed", asyncio's "Task exception was never retrieved" with a traceback) reached the
    user after the one-line error in about half the runs. Two runs: one line each."""
    import subprocess

    from motionflows import pretrained

    run = tmp_path / "damaged"
    shutil.copytree(pretrained.path("moglow-bandai"), run)
    data = [p for p in (run / "checkpoints").rglob("*") if p.is_file() and p.stat().st_size > 1e5]
    assert data, "the exported model's checkpoint holds no data file to damage"
    for p in data:
        p.write_bytes(p.read_bytes()[:1000])
    command = [sys.executable, "-c", "import sys; from motionflows.cli import main; "
               "sys.exit(main())", "sample", str(run), "--no-gif", "--out",
               str(tmp_path / "out")]  # fmt: skip
    for _ in range(2):
        done = subprocess.run(command, capture_output=True, text=True, timeout=300)
        assert done.returncode == 2
        lines = done.stderr.strip().splitlines()
        assert len(lines) == 1 and "damaged or incomplete" in lines[0], done.stderr
