"""Diverged samples of a fixed-length Glow against the floor of its coupling scale.

The affine coupling's scale lies in (eps, 1 + eps) (``coupling_eps``); sampling (latent ->
data) divides by it, so a small scale amplifies a tail latent up to 1/eps times per
coupling. This script resamples a trained Glow with the floor raised **at sampling time
only** (the trained weights, a copy of the run with ``coupling_eps`` edited in its
``config.json``), and prints the number of diverged windows (NaN/inf or a joint beyond
``bench.DIVERGED_METRES`` of the root) per floor and temperature, on the run's own test
split. A diagnostic of the cause, not a fix: a raised floor is a slightly different model.
Used for docs/readme/glow.md::

    python benchmarks/glow_coupling_floor.py pretrained:glow-bandai --floors 1e-6,1e-3,1e-2,5e-2
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
from pathlib import Path

import jax
import numpy as np

from motionflows import bench, runs
from motionflows.errors import RunError
from motionflows.run import load_run
from motionflows.windows import pick


def count_diverged(run_dir: Path, floors, temperatures, windows: int, seed: int) -> list[dict]:
    """One row per (floor, temperature): windows sampled, diverged, largest finite |x| (m)."""
    rows, dataset = [], None
    with tempfile.TemporaryDirectory() as tmp:
        for eps in floors:
            copy = Path(tmp) / f"eps{eps:g}"
            shutil.copytree(run_dir, copy)
            payload = json.loads((copy / "config.json").read_text())
            if "coupling_eps" not in payload["config"]:
                raise RunError(f"{run_dir} is not a fixed-length Glow run (no coupling_eps)")
            payload["config"]["coupling_eps"] = float(eps)
            (copy / "config.json").write_text(json.dumps(payload))
            module, _, model, dataset = load_run(copy, dataset=dataset)
            idx = pick(dataset.test, windows, seed=2)
            control = dataset.standardizer.normalize_control(dataset.test.control[idx])
            for temperature in temperatures:
                sampler = bench.make_sampler(module, temperature)
                x = bench.sample_in_chunks(
                    sampler, model, np.asarray(control, np.float32), jax.random.key(seed)
                )
                metres = np.asarray(dataset.standardizer.denormalize_pose(x))
                bad = bench.diverged(metres)
                rows.append({
                    "coupling_eps": float(eps), "temperature": float(temperature),
                    "windows": len(idx), "diverged": int(bad.sum()),
                    "max_abs_m": float(np.abs(metres[~bad]).max()) if (~bad).any() else None,
                })  # fmt: skip
                print(json.dumps(rows[-1]), flush=True)
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run", help="a Glow run directory or pretrained:NAME")
    p.add_argument("--floors", default="1e-6,1e-3,1e-2,5e-2", help="coupling_eps values")
    p.add_argument("--temperatures", default="0.8,1.0")
    p.add_argument("--windows", type=int, default=512, help="test windows sampled (at most)")
    p.add_argument("--seed", type=int, default=20)
    args = p.parse_args(argv)
    try:
        floors = [float(v) for v in args.floors.split(",")]
        temperatures = [float(v) for v in args.temperatures.split(",")]
        count_diverged(runs.resolve_run_dir(args.run), floors, temperatures, args.windows,
                       args.seed)  # fmt: skip
    except (RunError, ValueError) as err:
        print(f"glow_coupling_floor: error: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
