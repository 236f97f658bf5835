"""Datasets: splits, windows, standardiser (log-Jacobian vs autodiff), cache, batches."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from motionflows.config import DataConfig
from motionflows.data import MotionDataError, Standardizer, load_dataset
from motionflows.data.controls import PRESETS, load_control, preset
from motionflows.data.features import ROOT_SIGMA_S, Clip
from motionflows.data.pipeline import make_windows


@pytest.fixture(scope="module")
def ds(tmp_path_factory):
    cache = tmp_path_factory.mktemp("cache")
    return load_dataset(
        "synthetic", n_clips=12, seconds=6.0, seed=1, window=40, hop=10, cache_dir=cache
    )


def test_shapes_info_and_disjoint_splits(ds):
    for split in ("train", "val", "test"):
        ws = ds.split(split)
        assert ws.pose.shape[1:] == (40, 63) and ws.control.shape[1:] == (40, 3)
        assert ws.pose.dtype == np.float32 and len(ws) == ws.take.shape[0] > 0
    takes = [set(ds.split(s).take) for s in ("train", "val", "test")]
    assert not (takes[0] & takes[1]) and not (takes[0] & takes[2]) and not (takes[1] & takes[2])
    assert ds.info["takes"] == {"train": 10, "val": 1, "test": 1}
    assert ds.info["frames_used"]["val"] == ds.info["frames_total"]["val"]
    # mirror augmentation doubles the training windows
    assert len(ds.train) == 2 * len(
        load_dataset(
            "synthetic",
            n_clips=12,
            seconds=6.0,
            seed=1,
            window=40,
            hop=10,
            mirror=False,
            cache=False,
        ).train
    )
    with pytest.raises(ValueError, match="valid: train, val, test"):
        ds.split("nope")


def test_standardizer_log_jacobian_matches_autodiff(ds):
    st = ds.standardizer
    assert st.pose_std.shape == (63,) and (st.pose_std >= 1e-3).all()
    x = jnp.asarray(ds.train.pose[0, 0])
    jac = jax.jacfwd(lambda v: st.normalize_pose(v))(x)
    _, logdet = jnp.linalg.slogdet(jac)
    assert float(logdet) == pytest.approx(st.log_det_per_frame, rel=1e-5)
    assert st.log_jacobian(3) == pytest.approx(3 * float(logdet), rel=1e-5)
    np.testing.assert_allclose(
        st.denormalize_pose(st.normalize_pose(ds.val.pose)), ds.val.pose, atol=1e-5
    )
    back = Standardizer.from_dict(st.to_dict())
    np.testing.assert_array_equal(back.pose_std, st.pose_std)
    # fitted on the (augmented) training windows: standardised training data are N(0, 1)
    z = st.normalize_pose(ds.train.pose).reshape(-1, 63)
    np.testing.assert_allclose(z.mean(0), 0, atol=1e-3)
    assert np.allclose(z.std(0)[ds.train.pose.reshape(-1, 63).std(0) > 1e-3], 1, atol=1e-3)


def test_standardizer_floor_on_constant_channel():
    pose = np.random.default_rng(0).normal(size=(4, 10, 63)).astype(np.float32)
    pose[..., 5] = 0.3
    st = Standardizer.fit(pose, np.zeros((4, 10, 3)))
    assert st.pose_std[5] == pytest.approx(1e-3) and np.isfinite(st.log_det_per_frame)


def test_batches_deterministic_and_resumable(ds):
    b1 = ds.batch("train", 8, seed=3, index=5)
    b2 = ds.batch("train", 8, seed=3, index=5)
    np.testing.assert_array_equal(b1["pose"], b2["pose"])
    assert b1["pose"].shape == (8, 40, 63) and b1["control"].shape == (8, 40, 3)
    assert b1["pose"].dtype == np.float32
    assert b1["valid"].shape == (8, 40) and b1["valid"].dtype == bool  # rows of the windows':
    ordered = ds.batch("train", 8, seed=3, index=0, shuffle=False)["valid"]
    np.testing.assert_array_equal(ordered, ds.split("train").valid[:8])
    assert not np.array_equal(b1["pose"], ds.batch("train", 8, seed=4, index=5)["pose"])
    stream = list(ds.batches("train", 8, seed=3, epochs=2))
    per_epoch = len(ds.train) // 8
    assert len(stream) == 2 * per_epoch
    resumed = list(ds.batches("train", 8, seed=3, start=per_epoch + 1, epochs=2))
    np.testing.assert_array_equal(resumed[0]["pose"], stream[per_epoch + 1]["pose"])
    # one epoch visits distinct windows; the next epoch is a different order
    first = np.concatenate([b["pose"] for b in stream[:per_epoch]])
    assert len({raw_i.tobytes() for raw_i in first}) == per_epoch * 8
    assert not np.array_equal(stream[0]["pose"], stream[per_epoch]["pose"])
    unstd = ds.batch("val", 4, seed=0, index=0, standardized=False)
    assert np.abs(unstd["pose"]).max() < 3.0  # metres


def test_windows_pad_short_clips_and_report():
    rng = np.random.default_rng(0)
    clips = [
        Clip(rng.normal(size=(n, 63)), rng.normal(size=(n, 3)), 20.0, f"c{n}", {})
        for n in (25, 50, 5)
    ]
    ws, stats = make_windows(clips, 40, 10)
    assert stats["padded_windows"] == 1 and stats["dropped_clips"] == ["c5 (5 frames)"]
    assert stats["frames_used"] == 75 and stats["frames_total"] == 80
    padded = ws.take == "c25"
    assert ws.valid[padded].sum() == 25
    # windows of the 50-frame clip cover the tail: starts 0 and 10
    assert sorted(ws.start[ws.take == "c50"]) == [0, 10]


def test_cache_hit_is_identical(tmp_path):
    a = load_dataset("synthetic", n_clips=3, seconds=4.0, seed=2, window=20, cache_dir=tmp_path)
    assert a.info["cache_file"] and list(tmp_path.glob("*.npz"))
    b = load_dataset("synthetic", n_clips=3, seconds=4.0, seed=2, window=20, cache_dir=tmp_path)
    np.testing.assert_array_equal(a.train.pose, b.train.pose)


def test_root_smoothing_is_an_option_and_part_of_the_cache_key(tmp_path):
    """The same clips with Holden's 0.05 s root smoothing are other features: a cached copy
    of one must never answer for the other, and the dataset says which it holds."""
    opts = dict(n_clips=3, seconds=6.0, seed=2, window=20, cache_dir=tmp_path)
    ours = load_dataset("synthetic", **opts)
    holden = load_dataset("synthetic", root_sigma_s=0.05, **opts)
    assert len(list(tmp_path.glob("*.npz"))) == 2
    assert (ours.info["root_sigma_s"], holden.info["root_sigma_s"]) == (ROOT_SIGMA_S, 0.05)
    assert not np.allclose(ours.train.control, holden.train.control, atol=1e-4)
    # the root travels alike; the gait cycle moves from the control into the pose
    within = [d.train.control[..., 0].std(axis=1).mean() for d in (ours, holden)]
    assert within[0] < within[1]
    again = load_dataset("synthetic", root_sigma_s=0.05, **opts)
    np.testing.assert_array_equal(again.train.control, holden.train.control)


def test_errors_for_people(tmp_path, monkeypatch):
    with pytest.raises(ValueError, match="synthetic, bandai, bvh"):
        load_dataset("cmu-mocap")
    monkeypatch.setenv("MOTIONFLOWS_BANDAI_DIR", str(tmp_path / "missing"))
    with pytest.raises(MotionDataError, match="motionflows data download bandai"):
        load_dataset("bandai", path=str(tmp_path / "missing"))
    with pytest.raises(MotionDataError, match="no .bvh files"):
        load_dataset("bvh", path=str(tmp_path))


def test_bvh_source_and_performer_split(tmp_path):
    tiny = (
        "HIERARCHY\nROOT Hips\n{\n OFFSET 0 0 0\n CHANNELS 3 Xposition Yposition "
        "Zposition\n End Site\n {\n  OFFSET 0 1 0\n }\n}\nMOTION\nFrames: 2\n"
        "Frame Time: 0.05\n0 0 0\n1 0 0\n"
    )
    (tmp_path / "a.bvh").write_text(tiny)
    with pytest.raises(MotionDataError, match="skeleton mapping"):
        load_dataset("bvh", path=str(tmp_path), cache=False)
    syn = load_dataset(
        "synthetic", n_clips=8, seconds=4.0, window=20, split_by="performer", cache=False
    )
    assert syn.info["performers"]["test"] == ["S3"]
    assert "S3" not in syn.info["performers"]["train"]
    kw = dict(n_clips=8, seconds=4.0, window=20, split_by="performer", cache=False)
    # validating on the test performer would select the model on its test takes
    with pytest.raises(ValueError, match=r"\['S3'\] both for validation and for test"):
        load_dataset("synthetic", val_performers=["S3"], **kw)
    # one name as a string is that performer, not its characters
    one = load_dataset("synthetic", test_performers="S2", val_performers="S1", **kw)
    assert one.info["performers"]["test"] == ["S2"]
    assert one.info["performers"]["val"] == ["S1"]


def test_styles_keep_only_those_takes_in_every_split():
    """``styles``: only the takes of the named styles (Bandai's ``style`` metadata) are
    loaded; an unknown style, or a source without style names, is an error naming them."""
    from motionflows.data.datasets import _with_styles

    base = load_dataset("synthetic", n_clips=6, seconds=3.0, window=20, cache=False)
    clips = [c for s in ("train", "val", "test") for c in base.clips[s]]
    named = [
        Clip(c.pose, c.control, c.fps, c.name, dict(c.meta, style=("old", "new")[i % 2]))
        for i, c in enumerate(clips)
    ]
    kept = _with_styles(named, ("new",))
    assert [c.name for c in kept] == [c.name for c in named[1::2]]
    assert _with_styles(named, None) == named
    assert _with_styles(named, "new") == kept  # one style by name, not its letters
    with pytest.raises(MotionDataError, match=r"no take has style \['odd'\].*\['new', 'old'\]"):
        _with_styles(named, ("odd", "new"))
    with pytest.raises(MotionDataError, match="data.styles.*name none"):
        load_dataset("synthetic", n_clips=6, seconds=3.0, window=20, cache=False, styles=["x"])


def test_train_fraction_keeps_a_nested_share_of_each_groups_training_takes():
    """``train_fraction``: the training split keeps round(fraction * n) (at least one) of
    each (performer, content, style) group's n training takes, the first in hash order, so
    a smaller fraction's takes are a subset of a larger one's; validation and test keep
    every take, and the standardiser is fitted on the kept takes."""
    kw = dict(n_clips=24, seconds=3.0, window=20, split_by="performer", cache=False)
    full = load_dataset("synthetic", **kw)
    half = load_dataset("synthetic", train_fraction=0.5, **kw)
    quarter = load_dataset("synthetic", train_fraction=0.25, **kw)

    def names(d, split):
        return [c.name for c in d.clips[split]]

    assert set(names(quarter, "train")) < set(names(half, "train")) < set(names(full, "train"))
    for split in ("val", "test"):
        assert names(half, split) == names(full, split)

    def groups(d):
        out = {}
        for c in d.clips["train"]:
            style = c.meta.get("style")
            key = (c.meta["performer"], c.meta["content"], style if isinstance(style, str) else "")
            out[key] = out.get(key, 0) + 1
        return out

    for key, n in groups(full).items():
        assert groups(half)[key] == max(1, round(0.5 * n))
        assert groups(quarter)[key] == max(1, round(0.25 * n))
    assert half.info["train_fraction"] == 0.5 and full.info["train_fraction"] == 1.0
    assert half.info["takes"]["train"] == len(half.clips["train"])
    assert half.split("train").take.size < full.split("train").take.size
    assert not np.allclose(half.standardizer.pose_mean, full.standardizer.pose_mean)
    with pytest.raises(ValueError, match=r"data.train_fraction must be .*> 0 and <= 1"):
        DataConfig(train_fraction=0.0)
    with pytest.raises(ValueError, match=r"train_fraction must be in \(0, 1\]"):
        load_dataset("synthetic", train_fraction=1.5, **kw)


def test_summary_counts_each_splits_takes_and_windows_and_the_share_kept():
    """``MotionDataset.summary()``, the line ``motionflows train`` prints: the takes and
    windows of each split, the augmentation, and with a ``train_fraction`` how many of the
    available training takes the share kept."""
    kw = dict(n_clips=24, seconds=3.0, window=20, split_by="performer", cache=False)
    half = load_dataset("synthetic", train_fraction=0.5, **kw)
    full = load_dataset("synthetic", **kw)
    n_half, n_full = len(half.clips["train"]), len(full.clips["train"])
    assert n_half < n_full
    line = half.summary()
    assert line.startswith("synthetic, split by performer: ")
    share = f"train {n_half} of {n_full} takes (train_fraction 0.5)"
    assert f"{share} -> {len(half.train)} windows (mirrored)" in line
    for split in ("val", "test"):
        assert f"{split} {len(half.clips[split])} takes ({len(half.split(split))} windows)" in line
    assert f"train {n_full} takes -> {len(full.train)} windows (mirrored)" in full.summary()
    faster = load_dataset("synthetic", tempo=1.25, tempo_replay="faster", mirror=False, **kw)
    assert f"-> {len(faster.train)} windows (tempo 1.25 faster)" in faster.summary()


def test_with_test_describes_the_new_test_split():
    """``with_test`` (the bench's ``--test-data``) swaps the test windows: the info and the
    summary count the new split's takes and windows, and nothing keeps the old split's
    counts or clips."""
    kw = dict(n_clips=24, seconds=3.0, window=20, split_by="performer", cache=False)
    data = load_dataset("synthetic", **kw)
    other = load_dataset("synthetic", seed=5, **kw).train
    valid = other.valid.copy()
    valid[:3, -4:] = False  # three windows padded past their take's end
    other = dataclasses.replace(other, valid=valid)
    swapped = data.with_test(other, test_data="elsewhere")
    n_takes = len(set(other.take.tolist()))
    assert n_takes != data.info["takes"]["test"]
    assert swapped.info["takes"]["test"] == n_takes
    assert swapped.info["windows"]["test"] == len(other)
    assert swapped.info["padded_windows"]["test"] == 3 != data.info["padded_windows"]["test"]
    assert "test" not in swapped.info["frames_total"] and "test" not in swapped.clips
    assert f"test {n_takes} takes ({len(other)} windows)" in swapped.summary()
    assert swapped.info["test_data"] == "elsewhere"
    assert data.info["takes"]["test"] == len(data.clips["test"])  # the original is untouched


def test_control_presets():
    for name in PRESETS:
        c = preset(name, 6.0)
        assert c.shape == (120, 3) and c.dtype == np.float32
    assert np.degrees(preset("walk-turn-left", 8.0)[:, 2].sum()) == pytest.approx(90, abs=1)
    assert np.degrees(preset("walk-turn-right", 8.0)[:, 2].sum()) == pytest.approx(-90, abs=1)
    assert preset("walk", 4.0)[:, 0].mean() * 20 == pytest.approx(1.1, abs=0.01)
    assert preset("walk-back", 4.0)[:, 0].mean() < 0
    assert preset("sidestep-left", 4.0)[:, 1].mean() > 0
    with pytest.raises(ValueError, match="walk-turn-left"):
        preset("moonwalk", 3.0)
    # spelling-tolerant names: underscores, case, figure8
    for alias in ("figure_eight", "figure8", "Figure-Eight"):
        np.testing.assert_array_equal(load_control(alias, 6.0), preset("figure-eight", 6.0))
    np.testing.assert_array_equal(preset("walk_then_run", 4.0), preset("walk-then-run", 4.0))


def test_load_control_file(tmp_path):
    np.save(tmp_path / "c.npy", np.ones((10, 3)))
    assert load_control(tmp_path / "c.npy", 1.0).shape == (20, 3)
    np.save(tmp_path / "bad.npy", np.ones((10, 4)))
    with pytest.raises(ValueError, match=r"\(T, 3\)"):
        load_control(tmp_path / "bad.npy")
    np.save(tmp_path / "nan.npy", np.full((10, 3), np.nan))
    with pytest.raises(ValueError, match="non-finite"):
        load_control(tmp_path / "nan.npy")
    # the message says where the first bad value is and what to do about it
    holes = np.ones((10, 3))
    holes[6, 2], holes[8, 0] = np.inf, np.nan
    np.save(tmp_path / "holes.npy", holes)
    with pytest.raises(ValueError, match=r"2 of 10 frames.*first at frame 6.*np.nan_to_num"):
        load_control(tmp_path / "holes.npy")
    assert load_control("run", 2.0).shape == (40, 3)
    # a complex control used to lose its imaginary part without a word
    np.save(tmp_path / "complex.npy", np.ones((10, 3)) * (1 + 1j))
    with pytest.raises(ValueError, match="real numbers, got dtype complex128"):
        load_control(tmp_path / "complex.npy")
    # a file that is not a .npy array says how to write one, not numpy's reader's words
    (tmp_path / "text.npy").write_text("1 2 3\n")
    with pytest.raises(ValueError, match=r"text.npy as a numeric NumPy array.*numpy.save"):
        load_control(tmp_path / "text.npy")


def test_foot_lock_changes_the_training_takes_only():
    kw = dict(n_clips=12, seconds=6.0, window=40, hop=20, cache=False)
    plain = load_dataset("synthetic", **kw)
    locked = load_dataset("synthetic", foot_lock=True, **kw)
    for split in ("val", "test"):  # validated and scored on the takes as recorded
        np.testing.assert_array_equal(locked.split(split).pose, plain.split(split).pose)
    assert np.abs(locked.train.pose - plain.train.pose).max() > 1e-3
    np.testing.assert_array_equal(locked.train.control, plain.train.control)
    assert locked.info["augment"]["foot_lock"] and not plain.info["augment"]["foot_lock"]
    assert "feet locked" in locked.summary() and "feet locked" not in plain.summary()
    # a config field, as the other augmentations, that the bench's --set takes
    config = DataConfig(synthetic_clips=12, synthetic_seconds=6.0, window=40, hop=20)
    from_config = dataclasses.replace(config, foot_lock=True).load()
    np.testing.assert_array_equal(from_config.train.pose, locked.train.pose)
    from motionflows.bench.budgets import TRAINING_DATA_SETTABLE

    assert "data.foot_lock" in TRAINING_DATA_SETTABLE


def test_short_repeat_repeats_the_padded_training_windows_only():
    """``short_repeat`` = k: each window of a take shorter than the window is in the training
    split k times, every complete window once; validation and test are as cut."""
    from motionflows.data.datasets import repeat_padded
    from motionflows.data.synthetic import straight_walk

    long, short = straight_walk(1.2, seconds=4.0), straight_walk(2.4, seconds=1.5, seed=1)
    short = dataclasses.replace(short, name="short")
    windows, _ = make_windows([long, short], 40, 10, short="pad", min_frames=10)
    padded = ~windows.valid.all(axis=1)
    assert padded.sum() == 1 and len(windows) > 2
    assert repeat_padded(windows, 1) is windows
    tripled = repeat_padded(windows, 3)
    assert len(tripled) == len(windows) + 2
    np.testing.assert_array_equal(tripled.pose[: len(windows)], windows.pose)
    for field in ("pose", "control", "valid", "start"):
        extra = getattr(tripled, field)[len(windows) :]
        np.testing.assert_array_equal(extra, np.repeat(getattr(windows, field)[padded], 2, 0))
    assert list(tripled.take[len(windows) :]) == ["short", "short"]
    with pytest.raises(ValueError, match="short_repeat"):
        repeat_padded(windows, 0)
    # through the config: 3 s takes in 4 s windows are all padded
    config = DataConfig(synthetic_clips=12, synthetic_seconds=3.0, window=80, hop=10)
    plain, twice = config.load(), dataclasses.replace(config, short_repeat=2).load()
    assert len(twice.train) == 2 * len(plain.train)
    for split in ("val", "test"):
        np.testing.assert_array_equal(twice.split(split).pose, plain.split(split).pose)
    assert twice.info["augment"]["short_repeat"] == 2 and "short takes x2" in twice.summary()
    with pytest.raises(ValueError, match="short_repeat"):
        DataConfig(short_repeat=0)
    from motionflows.bench.budgets import TRAINING_DATA_SETTABLE

    assert "data.short_repeat" in TRAINING_DATA_SETTABLE
