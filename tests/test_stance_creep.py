"""benchmarks/stance_creep.py: the one-step stance measure sees a foot drawn ahead."""

from __future__ import annotations

import jax
import numpy as np
from flax import nnx

from motionflows.data.pipeline import make_windows
from motionflows.data.synthetic import straight_walk
from motionflows.models.moglow import MoGlow


def test_stance_steps_see_a_forward_creep_and_one_step_runs(benchmark_script):
    creep = benchmark_script("stance_creep")
    cut, _ = make_windows([straight_walk(1.2, 6.0, seed=s) for s in range(2)], 40, 20)
    pose, control = np.asarray(cut.pose, np.float64), np.asarray(cut.control, np.float64)
    tau = 4
    real = creep.stance_steps(pose, pose, control, tau, fps=20.0)
    # every drawn frame 1 cm ahead of the real one (facing +z in the root frame)
    ahead = pose.reshape(*pose.shape[:-1], 21, 3).copy()
    ahead[..., 2] += 0.01
    drawn = creep.stance_steps(pose, ahead.reshape(pose.shape), control, tau, fps=20.0)
    assert real["stance_steps"] == drawn["stance_steps"] > 0
    assert abs(drawn["forward_m_s"] - real["forward_m_s"] - 0.2) < 2e-3  # 1 cm x 20 fps
    assert drawn["speed_m_s"] > real["speed_m_s"]

    for embedding in (0, 8):  # the flow steps as the model runs them (cond_embedding too)
        model = MoGlow(tau=tau, K=1, hidden=8, num_layers=1, residual=True,
                       cond_embedding=embedding, rngs=nnx.Rngs(0))  # fmt: skip
        x = creep.one_step(model, pose[:2], control[:2], jax.random.key(0), 0.0)
        assert x.shape == (2, 40 - tau, 63) and np.all(np.isfinite(np.asarray(x)))
