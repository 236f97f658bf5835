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
    x = exp.sample(model, jax.random.key(1), control, seed_history=seed)
    with pytest.warns(DeprecationWarning, match="seed_pose= is deprecated, use seed_history="):
        y = exp.sample(model, jax.random.key(1), control, seed_pose=seed)
    np.testing.assert_array_equal(x, y)
    assert not np.allclose(x, exp.sample(model, jax.random.key(1), control))  # it is used
    with pytest.raises(TypeError, match="pass seed_history= only"):
        exp.sample(model, jax.random.key(1), control, seed_history=seed, seed_pose=seed)


@pytest.mark.parametrize("name", ["moglow", "glow_fixed", "vae_lstm", "baselines"])
def test_every_experiment_samples_key_first_and_warns_on_the_old_order(name):
    """One argument order for ``sample``: the experiments' ``(model, key, control)`` is the
    models' ``model.sample(key, control)``; the old ``(model, control, key)`` gives the same
    poses with a DeprecationWarning, also under jit (the swap is decided by type)."""
    import importlib

    exp = importlib.import_module(f"experiments.{name}")
    model = exp.build(exp.PRESETS["smoke"], key=jax.random.key(0))
    control = jax.random.normal(jax.random.key(2), (2, 8, 3))
    key = jax.random.key(1)
    x = exp.sample(model, key, control, temperature=0.7)
    assert x.shape == (2, 8, 63) and np.all(np.isfinite(x))
    assert not np.allclose(x, exp.sample(model, jax.random.key(3), control, temperature=0.7))
    with pytest.warns(DeprecationWarning, match=r"use \(model, key, control\)"):
        y = exp.sample(model, control, key, temperature=0.7)
    np.testing.assert_array_equal(x, y)
    with pytest.warns(DeprecationWarning, match="deprecated"):
        z = jax.jit(lambda m, c, k: exp.sample(m, c, k, temperature=0.7))(model, control, key)
    np.testing.assert_allclose(x, z, rtol=1e-4, atol=1e-4)  # jit vs eager: float rounding


def test_the_library_calls_an_old_order_experiment_in_its_own_order():
    """A third-party experiment written against the old contract ``sample(model, control,
    key)`` keeps working through ``runs.experiment_sample`` (a DeprecationWarning); one in
    the new order is called ``(model, key, control)``."""
    import types

    from motionflows import runs

    calls = []

    def old(model, control, key, *, temperature=1.0):
        calls.append(("old", control, key, temperature))
        return control

    def new(model, key, control, *, temperature=1.0):
        calls.append(("new", control, key, temperature))
        return control

    key, control = jax.random.key(0), jnp.ones((1, 2, 3))
    with pytest.warns(DeprecationWarning, match=r"toy_old.sample\(model, control, key\)"):
        runs.experiment_sample(
            types.SimpleNamespace(sample=old, __name__="toy_old"),
            None,
            key,
            control,
            temperature=0.5,
        )
    runs.experiment_sample(
        types.SimpleNamespace(sample=new, __name__="toy_new"), None, key, control, temperature=0.5
    )
    for kind, c, k, t in calls:
        assert c is control and k is key and t == 0.5, kind
    assert [c[0] for c in calls] == ["old", "new"]


def test_the_bench_chunked_sampler_has_its_own_name():
    from motionflows import bench, run

    with pytest.warns(DeprecationWarning, match="use bench.sample_in_chunks"):
        old = bench.draw_samples
    assert old is bench.sample_in_chunks and bench.sample_in_chunks is not run.draw_samples
