"""Tried 2026-12-04 and reverted: MoGlow sampled with its planted feet held inside the loop
(``MoGlow.sample(..., constraint=stance_constraint(standardizer, ...))``), scored beside the
same model's own samples. Usage (a run directory, a temperature, then one JSON object of
``stance_constraint`` options per sampler; env SPLIT=val|test, N windows, CKPT)::

    SPLIT=test N=256 CKPT=best python benchmarks/stance_hold.py RUN 0.8 '{"contact_height": 0.015}'
"""

import json
import os
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from motionflows import bench
from motionflows.inference import inference_copy
from motionflows.stance import stance_constraint
from motionflows.training import load_run
from motionflows.windows import pick, standardized

run = Path(sys.argv[1])
temp = float(sys.argv[2])
settings = [json.loads(a) for a in sys.argv[3:]]
exp, config, model, dataset = load_run(run, checkpoint=os.environ.get("CKPT", "latest"))

part = dataset.split(os.environ.get("SPLIT", "test"))
idx = pick(part, int(os.environ.get("N", "64")), seed=2)
_, ctrl = standardized(dataset.standardizer, part, idx)
gt_m = np.asarray(part.pose, np.float32)[idx]
control_m = np.asarray(part.control, np.float32)[idx]
st = dataset.standardizer
fps = float(config.data.fps)
m = inference_copy(model)
key = jax.random.key(0)
gt = bench.motion_metrics(gt_m, control_m, gt_m, None, fps)
print("gt", {k: round(float(v), 4) for k, v in gt.items() if np.isscalar(v)})
for s in [None] + settings:
    cons = None if s is None else stance_constraint(st, **s)
    f = jax.jit(lambda k, c: m.sample(k, c, temperature=temp, constraint=cons))  # noqa: B023

    def sampler(model_, k, c):
        return f(k, jnp.asarray(c))  # noqa: B023

    t0 = time.time()
    samples = bench.sample_in_chunks(sampler, None, ctrl, jax.random.fold_in(key, 20))
    one = np.repeat(ctrl[:1], bench.EVAL_CHUNK, axis=0)
    div = bench.sample_in_chunks(sampler, None, one, jax.random.fold_in(key, 21))[:16]
    met = bench.motion_metrics(
        np.asarray(st.denormalize_pose(samples), np.float32),
        control_m,
        gt_m,
        np.asarray(st.denormalize_pose(div), np.float32),
        fps,
    )
    met.pop("prediction", None)
    print(
        s,
        {k: round(float(v), 4) for k, v in met.items() if np.isscalar(v)},
        f"{time.time() - t0:.0f}s",
        flush=True,
    )
