"""Renamed arguments (one name per concept): the old names still work, with a warning."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from motionflows import bijectors as bj
from motionflows.models.baselines import LinearGaussianAR
from motionflows.models.glow import Glow
from motionflows.models.moglow import MoGlow


def test_flow_steps_are_called_K_and_the_old_names_warn():
    new = MoGlow(6, 2, tau=3, K=2, hidden=8, num_layers=1, rngs=jax.random.key(0))
    with pytest.warns(DeprecationWarning, match="num_steps= is deprecated, use K="):
        old = MoGlow(6, 2, tau=3, num_steps=2, hidden=8, num_layers=1, rngs=jax.random.key(0))
    assert new.K == old.K == old.num_steps == 2
    for a, b in zip(jax.tree.leaves(nnx.state(new)), jax.tree.leaves(nnx.state(old)), strict=True):
        np.testing.assert_array_equal(a, b)  # the same model
    with pytest.raises(TypeError, match="pass K= only"):
        MoGlow(6, 2, tau=3, K=2, num_steps=2, hidden=8, num_layers=1, rngs=jax.random.key(0))
    glow = Glow(6, levels=1, K=2, hidden=4, control_dim=0, rngs=nnx.Rngs(0))
    with pytest.warns(DeprecationWarning, match="steps= is deprecated, use K="):
        old_glow = Glow(6, levels=1, steps=2, hidden=4, control_dim=0, rngs=nnx.Rngs(0))
    assert glow.K == old_glow.K == old_glow.steps == 2
    scan = bj.Scan(lambda r: bj.ActNorm(3), K=2, rngs=nnx.Rngs(0))
    with pytest.warns(DeprecationWarning, match="Scan: num_steps= is deprecated, use K="):
        old_scan = bj.Scan(lambda r: bj.ActNorm(3), num_steps=2, rngs=nnx.Rngs(0))
    assert scan.K == old_scan.K == old_scan.num_steps == len(old_scan.unrolled().bijectors) == 2


def test_the_seed_history_keeps_its_old_names():
    model = LinearGaussianAR(2, pose_dim=6, control_dim=2)
    control = jnp.zeros((1, 4, 2))
    seed = jnp.ones((1, 3, 6))
    x = model.sample(jax.random.key(1), control, seed_history=seed)
    with pytest.warns(DeprecationWarning, match="history= is deprecated, use seed_history="):
        y = model.sample(jax.random.key(1), control, history=seed)
    np.testing.assert_array_equal(x, y)


def test_the_experiments_sample_takes_seed_history_and_warns_on_seed_pose():
    import experiments.moglow as exp

    # residual: even a fresh model (zero coupling heads) adds its change to the seed's pose
    config = dataclasses.replace(exp.PRESETS["smoke"], residual=True)
    model = exp.build(config, key=jax.random.key(0))
    control = jnp.zeros((2, 5, 3))
    seed = jnp.ones((2, 4, 63))
    x = exp.sample(model, control, jax.random.key(1), seed_history=seed)
    with pytest.warns(DeprecationWarning, match="seed_pose= is deprecated, use seed_history="):
        y = exp.sample(model, control, jax.random.key(1), seed_pose=seed)
    np.testing.assert_array_equal(x, y)
    assert not np.allclose(x, exp.sample(model, control, jax.random.key(1)))  # it is used
    with pytest.raises(TypeError, match="pass seed_history= only"):
        exp.sample(model, control, jax.random.key(1), seed_history=seed, seed_pose=seed)


def test_the_bench_chunked_sampler_has_its_own_name():
    from motionflows import bench, run

    with pytest.warns(DeprecationWarning, match="use bench.sample_in_chunks"):
        old = bench.draw_samples
    assert old is bench.sample_in_chunks and bench.sample_in_chunks is not run.draw_samples
