"""How a sampler's motion degrades over a long run: bone-length drift, foot sliding and jerk
per block of seconds of one long control.

For each run (a run directory or ``pretrained:NAME``) it samples ``--samples`` rollouts of
``--seconds`` of the control ``--control`` (a preset name, a ``.npy`` or a ``.bvh``) and
prints, per ``--block``-second block:

* bone error (m): mean over samples and bones of |length - its mean over the first second|
  (a rigid skeleton that keeps its proportions gives 0);
* foot sliding (m/s, calibrated ``floor`` contact rule) and contact rate;
* world jerk (m/s^3).

Used for the long-run table of docs/readme/moglow_quality.md::

    python benchmarks/long_run_drift.py pretrained:moglow-bandai runs/quality/X/run \\
        --control walk-turn-run --seconds 12 --samples 8 --temperature 0.6

and, with ``--spans`` (named stretches of the control instead of equal blocks), for the
README's demo-control table (walk, turning walk, run of ``walk-turn-run``)::

    python benchmarks/long_run_drift.py pretrained:moglow-bandai pretrained:vae_lstm-bandai \\
        --seconds 8 --samples 64 --spans 0-2,2-4,5-8

Blocks need a model that samples any length (MoGlow, the VAE-LSTM); ``--spans`` takes the
fixed-length Glow too, with a warning: samples longer than its training window are out of
its training distribution.
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from motionflows.data import load_control
from motionflows.errors import RunError
from motionflows.evaluation.motion import bone_lengths, contact_rate, foot_sliding, jerk
from motionflows.pretrained.model import PretrainedModel
from motionflows.runs import resolve_run_dir


def drift_table(
    pose: np.ndarray,
    control: np.ndarray,
    *,
    fps: float,
    block: int,
    reference: int,
    spans: list[tuple[int, int]] | None = None,
) -> list[dict]:
    """Per block of ``block`` frames (or per ``(start, stop)`` frame span of ``spans``): bone
    error, foot sliding, contact rate, jerk.

    pose (B, T, 63) metres, control (B, T, 3) data units; ``reference`` frames at the start
    give each sample's reference bone lengths.
    """
    bones = bone_lengths(pose)  # (B, T, 20)
    error = np.abs(bones - bones[:, :reference].mean(1, keepdims=True)).mean(-1).mean(0)
    if spans is None:
        spans = [(a, a + block) for a in range(0, pose.shape[1] - block + 1, block)]
    rows = []
    for start, stop in spans:
        s = slice(start, stop)
        rows.append(
            {
                "seconds": [start / fps, stop / fps],
                "bone_error_m": float(error[s].mean()),
                "foot_sliding_m_s": foot_sliding(pose[:, s], control[:, s], fps=fps),
                "contact_rate": contact_rate(pose[:, s]),
                "jerk_m_s3": jerk(pose[:, s], fps=fps, control=control[:, s]),
            }
        )
    return rows


def _parse_spans(text: str, seconds: float) -> list[tuple[float, float]]:
    """``"0-2,2-4"`` -> [(0.0, 2.0), (2.0, 4.0)], each 0 <= A < B <= ``seconds``."""
    spans = []
    for part in text.split(","):
        a, sep, b = part.strip().partition("-")
        try:
            start, stop = float(a), float(b)
        except ValueError:
            raise ValueError(f"{part!r} is not A-B in seconds, e.g. 0-2") from None
        if not sep or not 0 <= start < stop <= seconds:
            raise ValueError(f"{part!r} must be A-B with 0 <= A < B <= --seconds ({seconds:g})")
        spans.append((start, stop))
    return spans


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="+", help="run directories or pretrained:NAME")
    p.add_argument("--control", default="walk-turn-run")
    p.add_argument("--seconds", type=float, default=12.0)
    p.add_argument("--samples", type=int, default=8)
    p.add_argument(
        "--temperature",
        type=float,
        default=None,
        help="default: each model's validated temperature",
    )
    p.add_argument("--block", type=float, default=2.0, help="seconds per block")
    p.add_argument(
        "--spans",
        default=None,
        help="comma-separated A-B spans in seconds (e.g. 0-2,2-4,5-8) instead of blocks",
    )
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    if args.samples < 1 or not args.block > 0 or not args.seconds > 0:
        p.error(
            f"--samples must be >= 1 and --block and --seconds > 0, got {args.samples}, "
            f"{args.block:g}, {args.seconds:g}"
        )
    try:
        spans_s = None if args.spans is None else _parse_spans(args.spans, args.seconds)
    except ValueError as e:
        print(f"long_run_drift: --spans {args.spans!r}: {e}", file=sys.stderr)
        return 2
    for spec in args.runs:
        try:
            model = PretrainedModel.from_run(resolve_run_dir(spec))
        except RunError as e:
            print(f"long_run_drift: {e}", file=sys.stderr)
            return 2
        if model.fixed_length and spans_s is None:
            print(
                f"{spec}: a fixed-length model has no rollout to drift; long runs need a "
                "model that samples any length (--spans scores stretches of one sample)",
                file=sys.stderr,
            )
            return 2
        fps = model.fps
        try:
            control = load_control(args.control, seconds=args.seconds, fps=fps)
        except (ValueError, OSError) as e:
            print(f"long_run_drift: --control {args.control!r}: {e}", file=sys.stderr)
            return 2
        control = np.repeat(control[None], args.samples, 0)
        temperature = model.temperature if args.temperature is None else args.temperature
        try:
            pose = model.sample(control, seed=args.seed, temperature=temperature)
        except ValueError as e:
            print(f"long_run_drift: {spec}: {e}", file=sys.stderr)
            return 2
        spans = None if spans_s is None else [(round(a * fps), round(b * fps)) for a, b in spans_s]
        rows = drift_table(
            pose,
            control,
            fps=fps,
            block=max(1, round(args.block * fps)),
            reference=round(fps),
            spans=spans,
        )
        print(
            json.dumps(
                {
                    "run": spec,
                    "temperature": temperature,
                    "control": args.control,
                    "samples": args.samples,
                    "blocks": rows,
                }
            )
        )
        head = " | ".join(f"{r['seconds'][0]:g}-{r['seconds'][1]:g} s" for r in rows)
        print(
            f"# {spec} (T = {temperature:g}, {args.samples} x {args.seconds:g} s "
            f"{args.control})\n| | {head} |"
        )
        for key, fmt in (
            ("bone_error_m", "{:.3f}"),
            ("foot_sliding_m_s", "{:.2f}"),
            ("contact_rate", "{:.2f}"),
            ("jerk_m_s3", "{:.0f}"),
        ):
            print(f"| {key} | " + " | ".join(fmt.format(r[key]) for r in rows) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
