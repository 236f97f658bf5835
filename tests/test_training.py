"""The training loop: exact resume, Ctrl-C checkpoint, non-finite guard, run reload, eval."""

import dataclasses
import json
import os
import signal
import sys
import types

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from flax import nnx
from test_training_fakes import FakeDataset, MinimalDataset

import experiments.baselines as baselines
from motionflows.checkpoints import Checkpointer
from motionflows.config import TrainConfig
from motionflows.errors import RunError
from motionflows.evaluation import likelihood
from motionflows.optim import averaged_parameters, parameter_average
from motionflows.run import run_keys
from motionflows.runs import read_metrics
from motionflows.training import (
    evaluate_run,
    gradient_clipping,
    learning_rate_schedule,
    load_run,
    make_optimizer,
    train,
)


def _noisy_loss(model, batch, key):
    # the key matters: a resume that replays different random draws changes the curve
    loss, metrics = baselines.loss(model, batch, key)
    return loss + 0.1 * jax.random.normal(key, ()), metrics


fake = types.ModuleType("experiments.fake_gaussian")
for name in ("Config", "PRESETS", "SCOPES", "build", "evaluate", "sample"):
    setattr(fake, name, getattr(baselines, name))
fake.NAME = "fake_gaussian"
fake.loss = _noisy_loss
sys.modules["experiments.fake_gaussian"] = fake

CONFIG = baselines.Config(
    model="gaussian",
    tau=2,
    train=TrainConfig(
        steps=6,
        batch_size=4,
        lr=0.05,
        log_every=1,
        eval_every=3,
        eval_batches=1,
        checkpoint_every=100,
        keep_checkpoints=2,
    ),
)


def _losses(run_dir):
    return [(r["step"], r["loss"]) for r in read_metrics(run_dir) if "loss" in r]


def _params(model):
    return [np.asarray(x) for x in jax.tree_util.tree_leaves(nnx.state(model, nnx.Param))]


def test_resume_after_ctrl_c_gives_identical_loss_sequence(tmp_path):
    data = FakeDataset()
    full = train(fake, CONFIG, run_dir=tmp_path / "a", dataset=data, progress=False)
    assert full.status == "finished" and full.step == 6

    def interrupt(step, out):
        if step == 2:
            os.kill(os.getpid(), signal.SIGINT)

    part = train(
        fake, CONFIG, run_dir=tmp_path / "b", dataset=data, progress=False, on_step=interrupt
    )
    assert part.status == "interrupted" and part.step == 3
    assert (tmp_path / "b" / "checkpoints" / "latest" / "3").is_dir()
    with pytest.raises(ValueError, match="--resume"):
        train(fake, CONFIG, run_dir=tmp_path / "b", dataset=data, progress=False)
    resumed = train(fake, CONFIG, run_dir=tmp_path / "b", dataset=data, progress=False, resume=True)
    assert resumed.status == "finished" and resumed.step == 6
    a, b = _losses(tmp_path / "a"), _losses(tmp_path / "b")
    assert [s for s, _ in a] == list(range(1, 7))
    assert a == b
    for x, y in zip(_params(full.model), _params(resumed.model), strict=True):
        np.testing.assert_array_equal(x, y)

    # a KeyboardInterrupt raised by code inside the loop also leaves a checkpoint
    def raise_interrupt(step, out):
        if step == 3:
            raise KeyboardInterrupt

    part = train(
        fake, CONFIG, run_dir=tmp_path / "c", dataset=data, progress=False, on_step=raise_interrupt
    )
    assert part.status == "interrupted" and part.step == 4
    train(fake, CONFIG, run_dir=tmp_path / "c", dataset=data, progress=False, resume=True)
    assert _losses(tmp_path / "c") == a
    # the loss went down and the plot exists
    assert a[-1][1] < a[0][1]
    assert (tmp_path / "a" / "loss.png").is_file()
    row = next(r for r in read_metrics(tmp_path / "a") if "loss" in r)
    for key in ("grad_norm", "lr", "steps_per_s", "frames_per_s", "skipped"):
        assert key in row


def test_guard_skips_nan_steps_and_stops_after_max_nonfinite(tmp_path):
    cfg = dataclasses.replace(
        CONFIG, train=dataclasses.replace(CONFIG.train, max_nonfinite=2, steps=8)
    )
    # one bad batch: skipped and counted, the run finishes
    minimal = MinimalDataset(FakeDataset(nan_at={2}))  # only .batch and .standardizer
    one = train(fake, cfg, run_dir=tmp_path / "one", dataset=minimal, progress=False)
    assert one.status == "finished"
    rows = [r for r in read_metrics(tmp_path / "one") if "skipped" in r]
    assert rows[-1]["skipped"] == 1 and rows[2]["loss"] is None  # step 3 had no finite loss
    # a skipped step does not advance the schedule (its optimiser state is the step's
    # before), and the logged lr is the one the last applied update used
    warm = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, warmup_steps=8))
    train(fake, warm, run_dir=tmp_path / "warm", dataset=minimal, progress=False)
    lrs = [r["lr"] for r in read_metrics(tmp_path / "warm") if "lr" in r]
    sched = learning_rate_schedule(warm.train)
    assert lrs == pytest.approx([float(sched(i)) for i in (0, 1, 1, 2, 3, 4, 5, 6)])
    assert all(np.all(np.isfinite(p)) for p in _params(one.model))
    rows = evaluate_run(tmp_path / "one", "test", dataset=minimal, print_table=False)
    assert rows[0]["scope"] == "window" and rows[0]["windows"] == 4  # eval_batches x B

    # bad from batch 3 on: steps 4 and 5 skipped, the run stops at 5 with the step-3 state
    bad = train(
        fake,
        cfg,
        run_dir=tmp_path / "bad",
        dataset=FakeDataset(nan_at=range(3, 99)),
        progress=False,
    )
    assert bad.status == "nonfinite" and bad.step == 5
    good = train(
        fake,
        dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, steps=3)),
        run_dir=tmp_path / "good",
        dataset=FakeDataset(),
        progress=False,
    )
    _, _, restored, _ = load_run(tmp_path / "bad", checkpoint="latest", dataset=FakeDataset())
    for x, y in zip(_params(good.model), _params(restored), strict=True):
        np.testing.assert_array_equal(x, y)
    assert read_metrics(tmp_path / "bad")[-1]["status"] == "nonfinite"


def test_fit_load_run_and_eval_table(tmp_path):
    data = FakeDataset(n=128)
    cfg = dataclasses.replace(
        CONFIG,
        model="linear_ar",
        covariance="diag",
        train=dataclasses.replace(CONFIG.train, batch_size=16),
    )
    res = train(baselines, cfg, run_dir=tmp_path / "ar", dataset=data, progress=False)
    assert res.status == "fitted"
    module, config, model, _ = load_run(tmp_path / "ar", dataset=data)
    assert module is baselines and config == cfg
    batch = data.batch("test", 5, seed=0, index=0)
    np.testing.assert_allclose(
        model.log_prob(batch["pose"], batch["control"]),
        res.model.log_prob(batch["pose"], batch["control"]),
        rtol=1e-6,
    )

    rows = evaluate_run(tmp_path / "ar", "test", dataset=data, batch_size=5, print_table=False)
    saved = json.loads((tmp_path / "ar" / "eval_test.json").read_text())
    assert saved["rows"] == rows
    by = {r["scope"]: r for r in rows}
    assert by["window"]["scored_frames_per_window"] == 8
    assert by["official"]["scored_frames_per_window"] == 6  # tau = 2 frames conditioned on
    pose = data.standardizer.normalize_pose(data.test.pose).astype(np.float32)
    control = data.standardizer.normalize_control(data.test.control).astype(np.float32)
    ll = np.asarray(model.log_prob(pose, control), np.float64)
    ldpf = data.standardizer.log_det_per_frame
    assert by["window"]["windows"] == len(pose)
    np.testing.assert_allclose(
        by["window"]["nats_per_frame_metres"], np.mean(-(ll + 8 * ldpf) / 8), rtol=1e-5
    )
    np.testing.assert_allclose(
        by["window"]["bits_per_frame_std"], np.mean(-ll / 8 / np.log(2)), rtol=1e-5
    )
    lo, hi = by["window"]["nats_per_frame_metres_ci95"]
    assert lo < by["window"]["nats_per_frame_metres"] < hi
    # the fitted AR beats a gradient-free untrained model by far
    untrained = baselines.build(cfg, key=jax.random.key(0))
    assert float(jnp.mean(untrained.log_prob(pose, control))) < ll.mean()


def test_bootstrap_and_units():
    ll = np.array([-10.0, -12.0, -14.0])
    np.testing.assert_allclose(likelihood.nats_per_frame_metres(ll, 2, 1.5), [3.5, 4.5, 5.5])
    np.testing.assert_allclose(likelihood.bits_per_frame_standardized(ll, 2), -ll / 2 / np.log(2))
    mean, lo, hi = likelihood.bootstrap_ci(np.arange(100.0), seed=1)
    assert mean == 49.5 and 43 < lo < 49.5 < hi < 56
    with pytest.raises(ValueError, match="not finite"):
        likelihood.likelihood_rows({"window": [np.nan, 1.0]}, 4, 0.0)


def test_noam_schedule_matches_the_official_rule():
    # paper_version: lr0 = minimum = 1e-4 is a linear warm-up, then constant 1e-4
    paper = learning_rate_schedule(
        TrainConfig(lr=1e-4, schedule="noam", warmup_steps=1000, min_lr_ratio=1.0)
    )
    assert float(paper(0)) == pytest.approx(1e-7, rel=1e-4)
    assert float(paper(499)) == pytest.approx(5e-5, rel=1e-4)
    assert float(paper(999)) == pytest.approx(1e-4, rel=1e-4)
    assert float(paper(50_000)) == pytest.approx(1e-4, rel=1e-4)
    # preferred: lr0 = 1e-3 peaks at g = 999 and decays as sqrt(W / (g + 1)) to ~1.1e-4
    pref = learning_rate_schedule(
        TrainConfig(lr=1e-3, schedule="noam", warmup_steps=1000, min_lr_ratio=0.1)
    )
    assert float(pref(999)) == pytest.approx(1e-3, rel=1e-4)
    assert float(pref(3999)) == pytest.approx(1e-3 * 0.5, rel=1e-4)
    assert float(pref(79_999)) == pytest.approx(1e-3 * np.sqrt(1000 / 80_000), rel=1e-4)
    assert float(pref(10**7)) == pytest.approx(1e-4, rel=1e-4)  # the floor
    with pytest.raises(ValueError, match="schedule"):
        TrainConfig(schedule="linear")


def test_a_final_learning_rate_ratio_the_schedule_does_not_use_warns(tmp_path):
    """``train.min_lr_ratio`` sets where the cosine decay ends or the noam floor; the
    ``constant`` schedule does not read it, and a ratio given there was silently not
    applied. It now warns (a preset switched to constant by ``--set`` keeps its ratio, so
    not an error) and the rate stays constant; a schedule that reads it does not warn."""
    import warnings

    with pytest.warns(UserWarning, match="min_lr_ratio=0.1 is not used"):
        sched = learning_rate_schedule(TrainConfig(lr=0.5, steps=100, min_lr_ratio=0.1))
    assert float(sched(99)) == 0.5
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        learning_rate_schedule(TrainConfig(lr=0.5, steps=100))
        learning_rate_schedule(TrainConfig(lr=0.5, steps=100, schedule="cosine", min_lr_ratio=0.1))
    # a training run builds its schedule once: one warning, not one per place that reads it
    config = dataclasses.replace(
        CONFIG, train=dataclasses.replace(CONFIG.train, schedule="constant", min_lr_ratio=0.1)
    )
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        train(fake, config, run_dir=tmp_path / "run", dataset=FakeDataset(), progress=False)
    assert sum("min_lr_ratio" in str(w.message) for w in caught) == 1


@pytest.mark.standard_dtypes  # optax transforms called directly
def test_optimizer_clips_values_then_norm_and_warms_up():
    tc = TrainConfig(lr=1.0, clip_value=1.0, clip_norm=1.0, warmup_steps=4, optimizer="adam")
    sched = learning_rate_schedule(tc)
    assert float(sched(0)) == 0.0 and float(sched(2)) == pytest.approx(0.5)
    assert float(sched(10)) == pytest.approx(1.0)
    opt = gradient_clipping(tc)
    g = {"a": jnp.array([3.0, 0.0]), "b": jnp.array([0.0, 0.5])}
    out, _ = opt.update(g, opt.init(g))
    want = np.array([1.0, 0.0, 0.0, 0.5]) / np.sqrt(1.25)
    np.testing.assert_allclose(np.concatenate([out["a"], out["b"]]), want, rtol=1e-6)
    full = make_optimizer(tc)
    out, _ = full.update(g, full.init(g), g)
    assert float(out["a"][0]) == 0.0  # warm-up: the first step has lr 0
    with pytest.raises(ValueError, match="optimizer"):
        make_optimizer(dataclasses.replace(tc, optimizer="sgdd"))


@pytest.mark.standard_dtypes  # optax transforms called directly
def test_weight_decay_is_l2_with_adam_and_decoupled_with_adamw():
    # "adam": torch.optim.Adam's weight_decay, w * p added to the (clipped) gradient before
    # Adam's moments; "adamw": decoupled, p -= lr * w * p beside Adam's step. Before, "adam"
    # ignored weight_decay without a word.
    p = {"a": jnp.array([2.0, -1.0]), "b": jnp.array([0.5])}
    g = {"a": jnp.array([10.0, 0.2]), "b": jnp.array([-0.3])}
    tc = TrainConfig(lr=0.1, clip_value=1.0, weight_decay=0.5, optimizer="adam")

    def first_update(config, grads):
        opt = make_optimizer(config)
        out, _ = opt.update(grads, opt.init(p), p)
        return np.concatenate([np.asarray(out["a"]), np.asarray(out["b"])])

    clipped = jax.tree.map(lambda x: jnp.clip(x, -1.0, 1.0), g)
    l2 = jax.tree.map(lambda x, q: x + 0.5 * q, clipped, p)
    plain = dataclasses.replace(tc, weight_decay=0.0, clip_value=None)
    np.testing.assert_allclose(first_update(tc, g), first_update(plain, l2), rtol=1e-6)
    assert not np.allclose(first_update(tc, g), first_update(plain, clipped))
    decoupled = dataclasses.replace(tc, optimizer="adamw")
    flat_p = np.array([2.0, -1.0, 0.5])
    np.testing.assert_allclose(
        first_update(decoupled, g), first_update(plain, clipped) - 0.1 * 0.5 * flat_p, rtol=1e-6
    )


def test_a_resume_keeps_the_device_counts_of_the_earlier_segments(tmp_path):
    """A run trained partly on 4 devices and resumed on one is not a one-device training:
    its config.json keeps every count (the bench's reuse reads them), the latest as
    ``devices``."""

    def interrupt(step, out):
        if step == 2:
            os.kill(os.getpid(), signal.SIGINT)

    run_dir, data = tmp_path / "run", FakeDataset()
    train(fake, CONFIG, run_dir=run_dir, dataset=data, progress=False, on_step=interrupt)
    saved = json.loads((run_dir / "config.json").read_text())
    assert (saved["devices"], saved["device_counts"]) == (1, [1])
    saved["devices"], saved["device_counts"] = 4, [4]  # as if its first segment ran on 4
    (run_dir / "config.json").write_text(json.dumps(saved))
    train(fake, CONFIG, run_dir=run_dir, dataset=data, progress=False, resume=True)
    saved = json.loads((run_dir / "config.json").read_text())
    assert (saved["devices"], saved["device_counts"]) == (1, [1, 4])


def test_parameter_average_is_what_validation_checkpoints_and_resume_use(tmp_path):
    # train.ema_decay changes no training step, and the model a run gives (the returned
    # model, load_run, export) is the debiased exponential average of the iterates p_1..p_6
    # (weights (1 - d) d^(n - k) / (1 - d^n)); they come from a run without it that
    # checkpoints every step
    data, d = FakeDataset(), 0.6
    every = dataclasses.replace(CONFIG.train, checkpoint_every=1, keep_checkpoints=6)
    plain = train(
        fake, dataclasses.replace(CONFIG, train=every), run_dir=tmp_path / "plain",
        dataset=data, progress=False,
    )  # fmt: skip
    built = fake.build(CONFIG, key=run_keys(CONFIG.train.seed)["build"])
    _, params, rest = nnx.split(built, nnx.Param, ...)
    ckpt = Checkpointer(tmp_path / "plain" / "checkpoints", keep=6)
    iterates = [_params(built)]
    for step in range(1, 7):
        state, _ = ckpt.restore({"params": params, "rest": rest}, step=step)
        iterates.append([np.asarray(x) for x in jax.tree_util.tree_leaves(state["params"])])
    ckpt.close()
    np.testing.assert_array_equal(iterates[-1][0], _params(plain.model)[0])
    want = iterates[0]
    for k, p in enumerate(iterates[1:], start=1):  # the debiased average (no p_0 weight)
        rate = (1 - d) / (1 - d**k)
        want = [a + rate * (x - a) for a, x in zip(want, p, strict=True)]

    cfg = dataclasses.replace(CONFIG, train=dataclasses.replace(CONFIG.train, ema_decay=d))
    avg = train(fake, cfg, run_dir=tmp_path / "avg", dataset=data, progress=False)
    assert _losses(tmp_path / "avg") == _losses(tmp_path / "plain")
    for got, w, last in zip(_params(avg.model), want, iterates[-1], strict=True):
        np.testing.assert_allclose(got, w, rtol=1e-6, atol=1e-7)
        assert not np.allclose(got, last)  # the average, not the last iterate
    loaded = load_run(tmp_path / "avg", checkpoint="latest", load_data=False)[2]
    for x, y in zip(_params(loaded), _params(avg.model), strict=True):
        np.testing.assert_array_equal(x, y)
    # validation scored the average: the step-6 row is the average's NLL
    val = [r for r in read_metrics(tmp_path / "avg") if "val_nll" in r]
    plain_val = [r for r in read_metrics(tmp_path / "plain") if "val_nll" in r]
    assert val[-1]["val_nll"] != plain_val[-1]["val_nll"]

    # --resume continues the iterate (not the average) and the average alike
    def interrupt(step, out):
        if step == 2:
            os.kill(os.getpid(), signal.SIGINT)

    part = train(fake, cfg, run_dir=tmp_path / "b", dataset=data, progress=False, on_step=interrupt)
    assert part.status == "interrupted" and part.step == 3
    resumed = train(fake, cfg, run_dir=tmp_path / "b", dataset=data, progress=False, resume=True)
    assert _losses(tmp_path / "b") == _losses(tmp_path / "avg")
    for x, y in zip(_params(resumed.model), _params(avg.model), strict=True):
        np.testing.assert_array_equal(x, y)
    # turning the average off (or on) on resume is refused, and config.json is kept
    saved = (tmp_path / "b" / "config.json").read_text()
    with pytest.raises(RunError, match="ema_decay=0.6 and cannot resume with None"):
        train(fake, CONFIG, run_dir=tmp_path / "b", dataset=data, progress=False, resume=True)
    with pytest.raises(RunError, match="ema_decay=None and cannot resume with 0.6"):
        train(fake, cfg, run_dir=tmp_path / "plain", dataset=data, progress=False, resume=True)
    assert (tmp_path / "b" / "config.json").read_text() == saved
    with pytest.raises(ValueError, match="ema_decay"):
        TrainConfig(ema_decay=1.0)


@pytest.mark.standard_dtypes  # optax transforms called directly
def test_parameter_average_passes_updates_through_and_averages():
    opt = optax.chain(optax.sgd(0.5), parameter_average(0.75))
    p = {"w": jnp.array([1.0, -2.0])}
    state = opt.init(p)
    np.testing.assert_array_equal(averaged_parameters(state)["w"], p["w"])
    g = {"w": jnp.array([2.0, 2.0])}
    updates, state = opt.update(g, state, p)
    np.testing.assert_allclose(updates["w"], [-1.0, -1.0])  # sgd's, unchanged
    np.testing.assert_allclose(averaged_parameters(state)["w"], [0.0, -3.0])  # p_1 alone
    p2 = optax.apply_updates(p, updates)
    updates, state = opt.update(g, state, p2)  # p_2 = [-1, -4]; weights 0.25, 0.1875
    want = [(0.75 * 0.0 + -1.0) / 1.75, (0.75 * -3.0 + -4.0) / 1.75]
    np.testing.assert_allclose(averaged_parameters(state)["w"], want, rtol=1e-6)
    # far fewer steps than 1 / (1 - d): the average is of the iterates, not the initial
    # parameters (it kept d^n of them: 98 % after 20 steps of d = 0.999)
    slow = optax.chain(optax.sgd(1.0), parameter_average(0.999))
    w, state = {"w": jnp.zeros(())}, slow.init({"w": jnp.zeros(())})
    for _ in range(20):  # the iterates 1, 2, ..., 20
        updates, state = slow.update({"w": -jnp.ones(())}, state, w)
        w = optax.apply_updates(w, updates)
    assert abs(float(averaged_parameters(state)["w"]) - 10.5) < 0.1
    assert averaged_parameters(optax.adam(1.0).init(p)) is None
    with pytest.raises(ValueError, match="decay"):
        parameter_average(1.0)


@pytest.mark.standard_dtypes  # optax transforms called directly
def test_parameter_average_after_one_update_is_that_update_exactly():
    # the first rate (1 - d) / (1 - d^1) is 1: the average is p_1 itself, not p_1 plus a
    # share of (p_1 - p_0) (it was 1.0000129 with 1 - d in float64 over 1 - d^n in float32)
    for d in (0.999, 0.9999, 0.5):
        opt = optax.chain(optax.sgd(1.0), parameter_average(d))
        p = {"w": jnp.array([0.0, 3.0, -7.0])}
        state = opt.init(p)
        updates, state = opt.update({"w": jnp.array([-1000.0, 5e4, 0.25])}, state, p)
        np.testing.assert_array_equal(
            averaged_parameters(state)["w"], optax.apply_updates(p, updates)["w"]
        )


def test_resume_refuses_data_whose_standardiser_changed_and_keeps_the_saved_one(tmp_path):
    # the checkpoints are in the units of the standardiser the run started with: resuming on
    # data that standardises differently (takes added to the folder, another --data) would
    # train on in other units and overwrite standardizer.json, losing the run's own units
    data = FakeDataset()

    def interrupt(step, out):
        if step == 2:
            raise KeyboardInterrupt

    run = tmp_path / "run"
    train(fake, CONFIG, run_dir=run, dataset=data, progress=False, on_step=interrupt)
    saved = (run / "standardizer.json").read_text()
    changed = FakeDataset()
    changed.standardizer.pose_mean = changed.standardizer.pose_mean + 0.05
    with pytest.raises(ValueError, match="standardi[sz]er.*changed|changed.*standardi[sz]er"):
        train(fake, CONFIG, run_dir=run, dataset=changed, progress=False, resume=True)
    assert (run / "standardizer.json").read_text() == saved
    # the same data resumes (a float32 round trip of the saved values is not a change)
    resumed = train(fake, CONFIG, run_dir=run, dataset=data, progress=False, resume=True)
    assert resumed.status == "finished"


def test_a_failed_resume_leaves_the_run_as_it_was(tmp_path):
    """A resume whose config cannot restore the checkpoints (another model size) stops with
    one error and leaves config.json, so the run still loads, evaluates and samples."""
    data = FakeDataset()
    run = tmp_path / "run"
    train(fake, CONFIG, run_dir=run, dataset=data, progress=False)
    saved = (run / "config.json").read_text()
    other = dataclasses.replace(CONFIG, model="linear_ar")
    with pytest.raises(ValueError, match="cannot resume .* with this config"):
        train(fake, other, run_dir=run, dataset=data, progress=False, resume=True)
    assert (run / "config.json").read_text() == saved
    load_run(run, dataset=data)
    reseeded = dataclasses.replace(CONFIG, train=dataclasses.replace(CONFIG.train, seed=1))
    with pytest.raises(ValueError, match="train.seed=0 and cannot resume with 1"):
        train(fake, reseeded, run_dir=run, dataset=data, progress=False, resume=True)
    assert (run / "config.json").read_text() == saved


def test_a_failed_refit_leaves_the_fitted_run_as_it_was(tmp_path, monkeypatch):
    """A closed-form run refits on --resume; a refit that fails (here the fit raises) must
    leave config.json and standardizer.json as they were (they were written before the
    fit, so the run then described a model it does not hold)."""
    data = FakeDataset(n=64)
    cfg = dataclasses.replace(CONFIG, model="linear_ar", covariance="diag")
    run = tmp_path / "ar"
    train(baselines, cfg, run_dir=run, dataset=data, progress=False)
    saved = (run / "config.json").read_text()

    def broken(*args, **kwargs):
        raise FloatingPointError("the fit diverged")

    monkeypatch.setattr(baselines, "fit", broken)
    other = dataclasses.replace(cfg, covariance="full")
    with pytest.raises(FloatingPointError):
        train(baselines, other, run_dir=run, dataset=data, progress=False, resume=True)
    assert (run / "config.json").read_text() == saved
    monkeypatch.undo()
    assert load_run(run, dataset=data)[1] == cfg


def test_eval_records_the_checkpoint_it_read(tmp_path):
    """``eval_<split>.json`` said "best" when the run had no best checkpoint and "latest"
    was scored (load_run falls back): it names the checkpoint read and its step."""
    import shutil

    data = FakeDataset()
    run = tmp_path / "run"
    train(fake, CONFIG, run_dir=run, dataset=data, progress=False)
    evaluate_run(run, "val", dataset=data, print_table=False)
    table = json.loads((run / "eval_val.json").read_text())
    assert table["checkpoint"] == "best" and table["step"] == 6
    shutil.rmtree(run / "checkpoints" / "best")
    evaluate_run(run, "val", dataset=data, print_table=False)
    table = json.loads((run / "eval_val.json").read_text())
    assert table["checkpoint"] == "latest" and table["step"] == 6


def test_resume_drops_the_checkpoints_of_the_abandoned_future(tmp_path):
    """After a crash, latest/ can hold a damaged newer step and best/ a step past the
    resume point (validation runs more often than checkpoints). The resumed run starts
    from the newest readable step: the steps after it belong to a trajectory it replaces,
    so they go; otherwise orbax would skip every save not newer than them (silently) and
    best/ would keep a model the resumed run never trained."""
    cfg = dataclasses.replace(
        CONFIG,
        train=dataclasses.replace(
            CONFIG.train, steps=9, eval_every=1, checkpoint_every=3, keep_checkpoints=5
        ),
    )
    data = FakeDataset()

    def crash(step, out):
        if step == 7:  # after step 8: latest holds 3 and 6, best its best of 1..8
            raise RuntimeError("power cut")

    run = tmp_path / "run"
    with pytest.raises(RuntimeError, match="power cut"):
        train(fake, cfg, run_dir=run, dataset=data, progress=False, on_step=crash)
    ck = Checkpointer(run / "checkpoints")
    assert ck.steps("latest") == [3, 6]
    best_before = ck.latest_step("best")
    ck.close()
    assert best_before > 6  # the data's fake losses fall: the best is the newest
    # a damaged newer latest step: resume falls back to 6
    (run / "checkpoints" / "latest" / "7" / "state").mkdir(parents=True)
    slower = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, lr=0.01))
    part = train(fake, slower, run_dir=run, dataset=data, progress=False, resume=True)
    assert part.status == "finished"
    ck = Checkpointer(run / "checkpoints")
    assert 7 not in ck.steps("latest") and ck.latest_step("latest") == 9
    _, best_meta = ck.restore(
        {"params": nnx.state(part.model, nnx.Param), "rest": {}}, which="best"
    )
    ck.close()
    # the best checkpoint is the best this (resumed, slower) run validated after step 6
    assert best_meta["step"] >= 6
    assert best_meta["val_nll"] == pytest.approx(
        min(r["val_nll"] for r in read_metrics(run) if "val_nll" in r and r["step"] > 6)
    )
