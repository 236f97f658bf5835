"""Data-parallel step over 4 simulated CPU devices == the single-device step."""

import os
import subprocess
import sys
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

SCRIPT = textwrap.dedent(
    """
    import jax, jax.numpy as jnp, numpy as np
    from flax import nnx
    assert jax.device_count() == 4, jax.devices()
    from motionflows.config import TrainConfig
    from motionflows.models.baselines import LinearGaussianAR
    from motionflows.sharding import data_mesh, replicate, shard_batch, check_batch_size
    from motionflows.training import init_guard, make_optimizer, make_train_step

    def loss(model, batch, key):
        ll = model.log_prob(batch["pose"], batch["control"])
        noise = jax.random.normal(key, ()) * 0.0
        return -jnp.mean(ll) / batch["pose"].shape[1] + noise, {"ll": jnp.mean(ll)}

    class Module:
        pass
    module = Module(); module.loss = loss

    model = LinearGaussianAR(2, pose_dim=5, control_dim=2, covariance="full")
    model.weight[...] = 0.1 * jax.random.normal(jax.random.key(0), model.weight[...].shape)
    model.lower[...] = 0.1 * jax.random.normal(jax.random.key(1), (5, 5))
    rng = np.random.default_rng(0)
    batch = {"pose": rng.normal(size=(8, 6, 5)).astype(np.float32),
             "control": rng.normal(size=(8, 6, 2)).astype(np.float32)}
    opt = make_optimizer(TrainConfig(lr=0.1, clip_norm=1.0))
    graphdef, params, rest = nnx.split(model, nnx.Param, ...)
    results = []
    for devices in (jax.devices()[:1], jax.devices()):
        mesh = data_mesh(devices)
        fresh = jax.tree_util.tree_map(jnp.copy, params)  # the step donates its inputs
        p, r, o = replicate((fresh, rest, opt.init(fresh)), mesh)
        step = make_train_step(module, graphdef, opt)
        b = shard_batch(batch, mesh)
        assert len(b["pose"].sharding.device_set) == len(devices)
        guard = init_guard()
        losses = []
        for i in range(3):
            p, o, guard, out = step(p, r, o, guard, b, jax.random.key(i))
            losses.append(float(out["loss"]))
        assert p["weight"][...].sharding.is_fully_replicated
        results.append((losses, [np.asarray(x) for x in jax.tree_util.tree_leaves(p)]))
    (l1, p1), (l4, p4) = results
    np.testing.assert_allclose(l1, l4, rtol=1e-5)
    assert l1[2] < l1[0]
    moved = [not np.allclose(a, np.asarray(b)) for a, b in
             zip(p1, jax.tree_util.tree_leaves(params))]
    assert any(moved)
    for a, b in zip(p1, p4):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
    try:
        check_batch_size(6, data_mesh())
    except ValueError as err:
        assert "divisible" in str(err)
    else:
        raise AssertionError("batch 6 on 4 devices accepted")
    print("OK", l1, l4)
    """
)


def _run_on_devices(script: str, devices: int) -> None:
    """Run ``script`` in a new process on ``devices`` simulated CPU devices; it prints OK."""
    env = dict(os.environ)
    env["XLA_FLAGS"] = f"--xla_force_host_platform_device_count={devices}"
    env["JAX_PLATFORMS"] = "cpu"
    proc = subprocess.run(
        [sys.executable, "-c", script],
        env=env,
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "OK" in proc.stdout


def test_sharded_step_equals_single_device_step():
    _run_on_devices(SCRIPT, 4)


PLACEMENT_SCRIPT = textwrap.dedent(
    """
    import jax, numpy as np
    from flax import nnx
    assert jax.device_count() == 2, jax.devices()
    from experiments import moglow as exp
    from motionflows.bench.speed import make_sampler, sample_in_chunks, time_sampler
    from motionflows.evaluation.likelihood import evaluate_windows
    from motionflows.sharding import data_mesh, data_parallel, replicate, shard_batch

    model = exp.build(exp.PRESETS["smoke"], key=jax.random.key(0))
    graphdef, params, rest = nnx.split(model, nnx.Param, ...)
    leaves, tree = jax.tree.flatten(params)
    keys = jax.random.split(jax.random.key(1), len(leaves))
    params = jax.tree.unflatten(
        tree, [p + 0.05 * jax.random.normal(k, p.shape) for p, k in zip(leaves, keys)])
    model = nnx.merge(graphdef, params, rest)  # non-zero heads: the couplings matter
    mesh = data_mesh()
    rep = replicate(model, mesh)

    def devices(tree):
        return {d for leaf in jax.tree.leaves(tree) for d in leaf.sharding.device_set}

    assert data_parallel(model, 4) == (model, None)  # one device: as it is
    same, m = data_parallel(rep, 4)
    assert same is rep and m is mesh
    one, m = data_parallel(rep, 3)  # 3 rows on 2 devices: the model on one device
    assert m is None and len(devices(one)) == 1

    rng = np.random.default_rng(0)
    pose = rng.normal(size=(6, 16, 63)).astype(np.float32)
    control = rng.normal(size=(6, 16, 3)).astype(np.float32)
    sampler = make_sampler(exp, 0.8)
    key = jax.random.key(2)
    par = sampler(rep, key, shard_batch(control[:4], mesh))
    assert len(par.sharding.device_set) == 2 and not par.sharding.is_fully_replicated
    np.testing.assert_allclose(par, sampler(model, key, control[:4]), atol=1e-4)
    np.testing.assert_allclose(
        sample_in_chunks(sampler, rep, control, key),
        sample_in_chunks(sampler, model, control, key), atol=1e-4)
    for batch in (1, 2):
        assert time_sampler(sampler, rep, control, batch, key, 1)["frames_per_s"] > 0
    for bs in (2, 3):
        a = evaluate_windows(exp, rep, pose, control, batch_size=bs, key=key)
        b = evaluate_windows(exp, model, pose, control, batch_size=bs, key=key)
        assert a.keys() == b.keys()
        for k in a:
            np.testing.assert_allclose(a[k], b[k], rtol=1e-5)
    print("OK")
    """
)


def test_replicated_model_scores_and_samples_data_parallel():
    """A model replicated over 2 devices samples and scores each row once, on its share of
    the devices (or on one device when the rows do not divide), with one device's results."""
    _run_on_devices(PLACEMENT_SCRIPT, 2)
