"""Would MoGlow plant its feet if it knew when they stand? The contact-label oracle.

MoGlow's stance foot creeps forward even when drawn from the real history
(docs/readme/moglow_quality.md, "Foot sliding"); the lever the README lists as untried is a
model that knows when a foot stands, e.g. contact channels predicted with the pose. Before
building one, this measures the most such a model could gain: a MoGlow whose control also
carries the *ground truth's* foot contacts of every frame (left, right: the calibrated
"floor" rule of :func:`motionflows.evaluation.motion.foot_contacts`, +1 in contact, -1 not,
computed per window from the poses), in training and when it samples the test controls.
A model that predicts its contacts can know no more than this, so if the true contacts do
not plant its feet, predicted ones will not::

    python benchmarks/contact_oracle.py --out runs/contact_oracle \\
        --baseline runs/moglow/bench-moglow-cpu-bandai-performer-...

Trains the MoGlow that ``motionflows bench --data bandai --budget cpu`` trains (the `cpu`
preset, split by performer; ``--steps``, ``--seed`` and ``--set`` change it) with the two
contact channels into ``OUT/run`` (resumed if it is there), then scores it and every
``--baseline`` run (the same preset without contacts: the bench's own runs) as the bench
scores: 256 complete windows of the unseen performer's takes (``pick(test, 256, seed=2)``),
one temperature for all (0.8), latents from ``fold_in(key(0), 20)``, diversity from the
budget's samples of the first control (32 at `cpu`), ground truth beside. Motion only:
each run's validation NLL is in its ``metrics.jsonl`` (the oracle's conditioned on the true
contacts, so a measure of what they tell the model, not a likelihood comparable with the
baselines'). Writes ``OUT/contact_oracle.json``; a table goes to stdout.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import types
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import experiments.moglow as moglow
from motionflows import bench
from motionflows.bench.benchmark import jsonable
from motionflows.bench.budgets import BUDGET_SIZES, bench_config, parse_data_spec
from motionflows.cli_train import add_set_argument
from motionflows.config import apply_overrides
from motionflows.data.names import CONTROL_DIM
from motionflows.errors import RunError
from motionflows.evaluation.motion import foot_contacts, foot_speeds
from motionflows.run import load_standardizer, restore_run
from motionflows.runs import resolve_run_dir
from motionflows.training import train
from motionflows.windows import pick

NAME = "moglow_contact_oracle"
CONTACT_CHANNELS = 2  # left, right
METRICS = (
    "foot_sliding", "skate_ratio", "contact_rate", "bone_length_std", "jerk", "fd_pose",
    "fd_window3", "diversity", "diverged", "contact_agreement", "told_stance_speed",
)  # fmt: skip


def contact_signs(pose_m: jax.Array) -> jax.Array:
    """Foot contacts of windows as control channels: pose (..., T, 63) in metres (a jax
    array) -> (..., T, 2), +1 where the foot (left, right) is in contact by the ``"floor"``
    rule of :func:`motionflows.evaluation.motion.foot_contacts` (the metrics' rule), -1
    where not."""
    return jnp.where(foot_contacts(pose_m), 1.0, -1.0)


def told_contact_steps(samples_m, control_m, truth_m, fps: float) -> dict:
    """Whether the feet do what the true contacts say: ``contact_agreement``, the fraction
    of (window, frame, foot) whose contact by the floor rule on the samples equals the
    ground truth's, and ``told_stance_speed`` (m/s), the mean horizontal world speed of
    the samples' foot centres (mean of ankle and toe) over the steps t -> t+1 where the
    *ground truth's* foot is in contact at both frames: 0 for a model that stands every
    foot the data stands, whatever its feet's heights."""
    own, truth = foot_contacts(samples_m), foot_contacts(truth_m)
    speed = foot_speeds(samples_m, control_m, fps=fps)
    stands = truth[..., :-1, :] & truth[..., 1:, :]
    return {"contact_agreement": float(np.mean(own == truth)),
            "told_stance_speed": float(speed[stands].mean())}  # fmt: skip


def oracle_experiment(standardizer) -> types.ModuleType:
    """The MoGlow experiment with the true contacts appended to every batch's control
    (C = 3 + 2); registered as ``experiments.moglow_contact_oracle`` so that
    :func:`motionflows.run.restore_run` finds it in this process."""
    mean = jnp.asarray(standardizer.pose_mean)
    std = jnp.asarray(standardizer.pose_std)

    def with_contacts(batch):
        signs = contact_signs(jnp.asarray(batch["pose"]) * std + mean)
        return {**batch, "control": jnp.concatenate([jnp.asarray(batch["control"]), signs], -1)}

    mod = types.ModuleType(f"experiments.{NAME}", __doc__)
    mod.NAME, mod.CAUSAL, mod.Config, mod.PRESETS = NAME, True, moglow.Config, moglow.PRESETS
    mod.SCOPES, mod.VALIDATION_SCOPE = moglow.SCOPES, moglow.VALIDATION_SCOPE
    mod.sample = moglow.sample

    def build(config, *, key):
        return moglow.build(config, key=key, control_dim=CONTROL_DIM + CONTACT_CHANNELS)

    def initialize(model, batch, *, key):
        return moglow.initialize(model, with_contacts(batch), key=key)

    def loss(model, batch, key):
        return moglow.loss(model, with_contacts(batch), key)

    def evaluate(model, batch, key):
        return moglow.evaluate(model, with_contacts(batch), key)

    mod.build, mod.initialize, mod.loss, mod.evaluate = build, initialize, loss, evaluate
    sys.modules[mod.__name__] = mod
    return mod


def score(run_dir: Path, test, idx: np.ndarray, fps: float, *, temperature: float, sizes):
    """Motion metrics of a run's best checkpoint on test windows ``idx`` (metres), sampled
    as the bench samples, with :func:`told_contact_steps`; the oracle (control_dim 5) gets
    the true contacts of each window."""
    exp, config, model, saved = restore_run(run_dir, checkpoint="best")
    st = load_standardizer(run_dir)
    control = st.normalize_control(np.asarray(test.control, np.float32)[idx])
    if model.control_dim > CONTROL_DIM:  # the oracle: the true contacts of each window
        signs = np.where(foot_contacts(np.asarray(test.pose, np.float32)[idx]), 1.0, -1.0)
        control = np.concatenate([control, signs], axis=-1)
    control = np.asarray(control, np.float32)
    key = jax.random.key(0)
    sampler = bench.make_sampler(exp, temperature)
    samples = bench.sample_in_chunks(sampler, model, control, jax.random.fold_in(key, 20))
    one = np.repeat(control[:1], bench.EVAL_CHUNK, axis=0)
    div = bench.sample_in_chunks(sampler, model, one, jax.random.fold_in(key, 21))
    gt_m = np.asarray(test.pose, np.float32)[idx]
    samples_m = np.asarray(st.denormalize_pose(samples), np.float32)
    metrics = bench.motion_metrics(
        samples_m,
        np.asarray(test.control, np.float32)[idx],
        gt_m,
        np.asarray(st.denormalize_pose(div), np.float32)[: sizes["diversity"]],
        fps,
    )
    metrics.pop("prediction", None)
    metrics.update(told_contact_steps(samples_m, test.control[idx], gt_m, fps))
    return {"run": str(run_dir), "step": int(saved["meta"]["step"]),
            "control_dim": int(model.control_dim), **metrics}  # fmt: skip


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", required=True)
    p.add_argument("--steps", type=int, default=None, help="training steps (preset: 8000)")
    p.add_argument("--seed", type=int, default=0, help="training seed (train.seed)")
    add_set_argument(p, "change the MoGlow cpu preset (a config field)")
    p.add_argument("--baseline", nargs="*", default=[], help="runs without contacts to score")
    p.add_argument("--temperature", type=float, default=0.8)
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:  # before the training: a typo must not cost an hour
        baselines = [resolve_run_dir(run) for run in args.baseline]
    except RunError as err:
        print(f"error: --baseline {err}", file=sys.stderr)
        return 2

    out = Path(args.out)
    data = parse_data_spec("bandai", "cpu")
    config, _ = bench_config("moglow", "cpu", data, moglow)
    overrides = [f"train.seed={args.seed}", *args.overrides]
    if args.steps is not None:
        overrides.append(f"train.steps={args.steps}")
    config = apply_overrides(config, overrides)
    training_data = config.data.load()  # the preset's own augmented takes (tempo, mirror)
    exp = oracle_experiment(training_data.standardizer)
    run_dir = out / "run"
    resume = (run_dir / "checkpoints").is_dir()
    train(exp, config, run_dir=run_dir, dataset=training_data, resume=resume, progress=False)

    scored = data.load()  # the bench's frames: the unseen performer's takes as recorded
    sizes = BUDGET_SIZES["cpu"]
    test = scored.test
    idx = pick(test, sizes["motion_windows"], seed=2)
    truth = np.where(foot_contacts(np.asarray(test.pose, np.float32)[idx]), 1.0, -1.0)
    st = training_data.standardizer
    twin = np.asarray(contact_signs(jnp.asarray(st.normalize_pose(test.pose[idx])) *
                                    st.pose_std + st.pose_mean))  # fmt: skip
    fps = float(data.fps)
    gt = bench.motion_metrics(test.pose[idx], test.control[idx], test.pose[idx], None, fps)
    gt["diversity"] = bench.natural_diversity_of(test)
    gt.update(told_contact_steps(test.pose[idx], test.control[idx], test.pose[idx], fps))
    result = {
        "config": dataclasses.asdict(config),
        "temperature": args.temperature,
        "windows": len(idx),
        "contact_rule_agreement": float(np.mean(twin == truth)),
        "ground_truth": {k: gt.get(k) for k in METRICS},
        "runs": [],
    }
    for run in [run_dir, *baselines]:
        row = score(run, test, idx, fps, temperature=args.temperature, sizes=sizes)
        result["runs"].append(row)
        print(json.dumps({k: row.get(k) for k in ("run", "step", "control_dim", *METRICS)}),
              flush=True)  # fmt: skip
    (out / "contact_oracle.json").write_text(json.dumps(jsonable(result), indent=1) + "\n")
    print("| run | contacts given | " + " | ".join(METRICS) + " |")
    print("|---|---|" + "---:|" * len(METRICS))
    rows = [("ground truth", "", result["ground_truth"])]
    rows += [(r["run"], "yes" if r["control_dim"] > CONTROL_DIM else "no", r)
             for r in result["runs"]]  # fmt: skip
    for name, given, r in rows:
        cells = " | ".join("" if r.get(k) is None else f"{r[k]:.3f}" for k in METRICS)
        print(f"| {name} | {given} | {cells} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
