"""How much foot sliding a control that carries the gait cycle charges a motion out of phase.

The control is the root's displacement per frame, and the root is the hip projected to the
floor and smoothed over time. Smoothed little (Holden et al.'s 0.05 s), the root follows the
hip's sway and its speed changes within a stride, so the control oscillates with the gait
cycle, and a motion is only placed with planted feet on its control when its stride is in
phase with that oscillation. This script measures that on real motion: the ground-truth
poses of Bandai takes, cut into 4 s windows at 20 fps, placed on

* their own control (the ground truth's foot sliding),
* their own control shifted by ``k`` frames (the same motion, its stride out of phase),
* the window's mean control (a control without the gait cycle),

for each root smoothing ``sigma`` (seconds), with the calibrated contact rule of
:func:`motionflows.evaluation.motion.foot_sliding`. Prints a JSON line with the number of
takes, the machine and its load, then one JSON object per sigma. Used for
docs/readme/moglow_quality.md (the sliding study)::

    python benchmarks/control_phase_sliding.py                      # the unseen performer D2-C
    python benchmarks/control_phase_sliding.py --takes 'DIR/*.bvh' --sigmas 0.05,0.333
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import platform
import sys
from pathlib import Path

import numpy as np

from motionflows.data.features import ROOT_SIGMA_S, clip_from_bvh
from motionflows.data.pipeline import make_windows
from motionflows.evaluation.motion import contact_rate, foot_sliding, skate_ratio

SHARED = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
DEFAULT_TAKES = (
    f"{SHARED}/bandai_locomotion_*/dataset-2_*_masculine_*.bvh",
    f"{SHARED}/bandai_locomotion_*/dataset-2_*_normal_*.bvh",
)
FPS, WINDOW, HOP = 20.0, 80, 10


def measure(files, sigma: float, shifts) -> dict:
    """Sliding (m/s) and skate ratio of real poses on their own, shifted and mean controls."""
    clips = [clip_from_bvh(f, FPS, root_sigma_s=sigma) for f in files]
    cut, _ = make_windows(clips, WINDOW, HOP, short="drop")  # complete windows, as the bench's
    pose, control = np.asarray(cut.pose, np.float64), np.asarray(cut.control, np.float64)

    def scores(p, c):
        return {
            "foot_sliding_m_s": round(foot_sliding(p, c, fps=FPS), 4),
            "skate_ratio": round(skate_ratio(p, c, fps=FPS), 4),
        }

    row = {
        "root_sigma_s": round(sigma, 4),
        "windows": len(pose),
        "own_control": scores(pose, control),
    }
    row["contact_rate"] = round(contact_rate(pose), 4)
    for k in shifts:
        row[f"control_shifted_{k}_frames"] = scores(pose[:, k:], control[:, : control.shape[1] - k])
    row["window_mean_control"] = scores(
        pose, np.broadcast_to(control.mean(1, keepdims=True), control.shape)
    )
    row["control_within_window_std"] = {  # m/frame: how much the control moves with the stride
        "forward": round(float(control[..., 0].std(axis=1).mean()), 5),
        "sideways": round(float(control[..., 1].std(axis=1).mean()), 5),
    }
    return row


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--takes", action="append", help="glob of BVH takes (repeatable; "
                        "default: every D2-C take in ../shared/data)")  # fmt: skip
    parser.add_argument("--sigmas", default=f"0.05,0.15,0.25,{ROOT_SIGMA_S:.4f},0.5")
    parser.add_argument("--shifts", default="2,5,10", help="control shifts in frames")
    parser.add_argument("--every", type=int, default=1, help="use every n-th take (speed)")
    args = parser.parse_args(argv)
    try:
        shifts = [int(k) for k in args.shifts.split(",")]
    except ValueError:
        shifts = []
    if args.every < 1 or not shifts or min(shifts) < 1:
        parser.error(
            f"--every must be >= 1 and --shifts whole frames >= 1, comma-separated; got "
            f"{args.every}, {args.shifts!r}"
        )
    files = sorted({f for g in (args.takes or DEFAULT_TAKES) for f in glob.glob(g)})[:: args.every]
    if not files:
        wanted = args.takes or list(DEFAULT_TAKES)
        hint = "pass --takes 'DIR/*.bvh' (the Bandai set: motionflows data download bandai)"
        print(f"error: no BVH take matches {wanted}; {hint}", file=sys.stderr)
        return 2
    print(json.dumps({"takes": len(files), "fps": FPS, "window": WINDOW, "hop": HOP,
                      "machine": platform.processor() or platform.machine(),
                      "load_average": os.getloadavg()[0]}), flush=True)  # fmt: skip
    for sigma in (float(s) for s in args.sigmas.split(",")):
        print(json.dumps(measure(files, sigma, shifts)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
