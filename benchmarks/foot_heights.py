"""Where a model's feet are when they should be on the floor: the lowest foot's height per
second, and how long its strides take, beside the ground truth's.

Real feet touch the floor (y = 0 in the features) at least once a second while walking or
running, so the lowest foot height of each 1 s block is ~0 in every block. A sampler whose
stance height wanders (a ``residual`` MoGlow integrates its height changes) has blocks whose
lowest foot floats above or sinks below the floor; the calibrated contact rule, which
measures heights from each window's 5th-percentile floor, then misses stance frames
(a low contact rate) and the foot sliding it reports is of fewer, less certain contacts.

For the takes ``--takes`` (default: every Bandai take of the performer D2-C in
``../shared/data``) cut into 4 s windows at 20 fps, and each run (a run directory or
``pretrained:NAME``) sampled on those windows' controls, it prints one JSON object per
source:

* ``block_min_height_cm``: mean and std, over every window's 1 s blocks, of the lowest foot
  height in the block (cm; ground truth ~0 and ~0), and ``within_window_std``, its std
  within a window (the wander over 4 s);
* ``height_above_floor_cm``: 10th, 25th and 50th percentile of the feet's heights above the
  window's floor (the contact rule's floor);
* ``contact_rate`` and ``foot_sliding_m_s`` (the calibrated rule, on the windows'
  controls; for the ground truth, how much the takes' own feet slide by that rule), and
  under ``absolute_1.5cm`` the same two by the ``"absolute"`` rule at 1.5 cm above y = 0
  (the features' floor; on D2-C's takes it scores the ground truth as the calibrated rule
  does, and a sampler whose feet sink below the floor cannot take the floor down with it),
  ``jerk`` (m/s^3, world) and ``fd_pose`` (m^2, against the ground truth windows);
* ``stride``: over the windows whose control walks straight ahead (0.6-2 m/s forward, under
  0.5 rad of turn in 4 s; the same windows for every source, since they share controls),
  the median stride period (s, :func:`motionflows.evaluation.motion.stride_period`) and
  stride length (m, period x the control's speed), the fraction of windows with a
  period found, and ``feet_reach_m``: the median over those windows of how far the feet
  reach apart along the walking direction (5th to 95th percentile of the left ankle's lead
  over the right, root frame; 0.86-0.93 of the stride length in the Bandai takes). Feet
  that reach less far than the root travels per stride must slide to keep up.

With ``--foot-lock`` each model's row is followed by two of the same samples locked: by
:func:`motionflows.foot_lock.foot_lock` and by
:class:`motionflows.foot_lock.StreamingFootLock` (frame by frame from each window's first
frame, as ``motionflows play --foot-lock`` does), with ``moved_cm``: how far the lock moved
the joints (:func:`moved_cm`).

Used for docs/readme/moglow_quality.md (stance heights, strides, foot lock)::

    python benchmarks/foot_heights.py pretrained:moglow-bandai pretrained:vae_lstm-bandai
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import platform
import sys

import numpy as np

from motionflows.data.features import clip_from_bvh, integrate_root
from motionflows.data.names import FOOT_JOINTS
from motionflows.data.pipeline import make_windows
from motionflows.errors import RunError
from motionflows.evaluation.motion import (
    _joints,
    contact_floor,
    contact_rate,
    foot_heights,
    foot_sliding,
    frechet_pose_distance,
    jerk,
    stride_period,
    to_global,
)
from motionflows.foot_lock import StreamingFootLock, _to_root_frame, foot_lock
from motionflows.pretrained.model import PretrainedModel
from motionflows.runs import resolve_run_dir

SHARED = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "shared", "data")
DEFAULT_TAKES = (  # the performer D2-C: the masculine and normal styles of dataset 2
    f"{SHARED}/bandai_locomotion_*/dataset-2_*_masculine_*.bvh",
    f"{SHARED}/bandai_locomotion_*/dataset-2_*_normal_*.bvh",
)
FPS, WINDOW, HOP = 20.0, 80, 40
ABS = {"rule": "absolute", "contact_height": 0.015}  # floor y = 0, not the window's own


def stance_heights(pose: np.ndarray, *, fps: float) -> dict:
    """The block and floor statistics above for poses (N, T, 63) in metres."""
    heights = foot_heights(_joints(np.asarray(pose, np.float64)))  # (N, T, 2)
    n, t = heights.shape[:2]
    block = round(fps)
    lowest = heights[:, : t - t % block].min(-1).reshape(n, -1, block).min(-1) * 100.0
    above = (heights.reshape(n, -1) - contact_floor(heights)[:, None]) * 100.0
    return {
        "block_min_height_cm": {
            "mean": round(float(lowest.mean()), 3),
            "std": round(float(lowest.std()), 3),
            "within_window_std": round(float(lowest.std(axis=1).mean()), 3),
        },
        "height_above_floor_cm": {
            f"p{q}": round(float(np.percentile(above, q)), 2) for q in (10, 25, 50)
        },
        "contact_rate": round(contact_rate(pose), 4),
    }


def strides(pose: np.ndarray, control: np.ndarray, *, fps: float) -> dict:
    """Median stride period and length over the straight-walking windows of ``control``."""
    speed = control[..., 0].mean(-1) * fps
    walking = (speed >= 0.6) & (speed <= 2.0) & (np.abs(control[..., 2].sum(-1)) < 0.5)
    period = stride_period(pose[walking], fps=fps)
    found = ~np.isnan(period)
    joints = _joints(np.asarray(pose[walking], np.float64))
    ahead = joints[..., FOOT_JOINTS[0], 2] - joints[..., FOOT_JOINTS[2], 2]  # left - right, fwd
    reach = np.percentile(ahead, 95, axis=-1) - np.percentile(ahead, 5, axis=-1)
    row = {"walking_windows": int(walking.sum()), "found": round(float(found.mean()), 3)}
    if found.any():
        row["period_s"] = round(float(np.median(period[found])), 3)
        row["length_m"] = round(float(np.median((period * speed[walking])[found])), 3)
    row["feet_reach_m"] = round(float(np.median(reach)), 3) if reach.size else None
    return row


def moved_cm(locked: np.ndarray, sample: np.ndarray) -> dict:
    """How far a lock moved the joints of poses (N, T, 63) metres: the median, 99th
    percentile and maximum over the frames of each frame's largest joint move (the length
    of its 3D displacement, cm; before 2026-12-07 the largest single coordinate change,
    up to sqrt(3) less)."""
    joints = (np.asarray(locked) - np.asarray(sample)).reshape(*np.shape(sample)[:-1], -1, 3)
    move = np.linalg.norm(joints, axis=-1).max(-1).ravel() * 100.0
    return {k: round(float(np.percentile(move, q)), 2) for k, q in
            (("p50", 50), ("p99", 99), ("max", 100))}  # fmt: skip


def streamed_lock(pose: np.ndarray, control: np.ndarray, *, fps: float) -> np.ndarray:
    """Poses (N, T, 63) locked frame by frame by a fresh StreamingFootLock per window."""
    out = np.empty_like(pose)
    for i, (p, c) in enumerate(zip(pose, control, strict=True)):
        world, yaw = _joints(to_global(p, c)), integrate_root(c)[1]
        lock = StreamingFootLock(fps=fps)
        held = np.stack([lock.step(w, a) for w, a in zip(world, yaw, strict=True)])
        out[i] = p + _to_root_frame(held - world, yaw).reshape(p.shape)
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="*", help="run directories or pretrained:NAME")
    p.add_argument("--takes", action="append", help="glob of BVH takes (repeatable)")
    p.add_argument("--windows", type=int, default=256, help="at most this many windows")
    p.add_argument("--temperature", type=float, default=None, help="default: each model's")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--foot-lock", action="store_true", help="also score the samples locked")
    args = p.parse_args(argv)
    files = sorted({f for g in (args.takes or DEFAULT_TAKES) for f in glob.glob(g)})
    if not files:
        hint = "pass --takes 'DIR/*.bvh' (the Bandai set: motionflows data download bandai)"
        print(f"foot_heights: no BVH take matches {args.takes or DEFAULT_TAKES}; {hint}",
              file=sys.stderr)  # fmt: skip
        return 2
    models = []
    for spec in args.runs:
        try:
            models.append((spec, PretrainedModel.from_run(resolve_run_dir(spec))))
        except RunError as e:
            print(f"foot_heights: {e}", file=sys.stderr)
            return 2
    cut, _ = make_windows([clip_from_bvh(f, FPS) for f in files], WINDOW, HOP, short="drop")
    pick = np.linspace(0, len(cut.pose) - 1, min(args.windows, len(cut.pose))).round().astype(int)
    pose, control = np.asarray(cut.pose)[pick], np.asarray(cut.control)[pick]
    print(json.dumps({"takes": len(files), "windows": len(pick), "fps": FPS, "window": WINDOW,
                      "machine": platform.processor() or platform.machine(),
                      "load_average": os.getloadavg()[0]}))  # fmt: skip

    def row(p):
        return {
            **stance_heights(p, fps=FPS),
            "foot_sliding_m_s": round(float(foot_sliding(p, control, fps=FPS)), 4),
            "absolute_1.5cm": {  # the same, with contacts below 1.5 cm above y = 0
                "foot_sliding_m_s": round(float(foot_sliding(p, control, fps=FPS, **ABS)), 4),
                "contact_rate": round(contact_rate(p, **ABS), 4),
            },
            "jerk": round(float(jerk(p, fps=FPS, control=control)), 1),
            "fd_pose": round(float(frechet_pose_distance(pose, p)), 4),
            "stride": strides(p, control, fps=FPS),
        }

    print(json.dumps({"source": "ground truth", **row(pose)}))
    for spec, model in models:
        temperature = model.temperature if args.temperature is None else args.temperature
        sample = np.asarray(model.sample(control, seed=args.seed, temperature=temperature))
        sample = sample.astype(np.float64)
        print(json.dumps({"source": spec, "temperature": temperature, **row(sample)}))
        if not args.foot_lock:
            continue
        for how, locked in (
            ("foot lock", foot_lock(sample, control)),
            ("streaming foot lock", streamed_lock(sample, control, fps=FPS)),
        ):
            print(json.dumps({"source": f"{spec} + {how}", "temperature": temperature,
                              **row(locked), "moved_cm": moved_cm(locked, sample)}))  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
