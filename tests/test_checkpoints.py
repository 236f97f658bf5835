"""Checkpoints: stored by name (orbax alone reads them), round trips, and the positional
layout of checkpoints written before (the shipped pretrained models, resumed runs)."""

from __future__ import annotations

import chex
import jax
import jax.numpy as jnp
import numpy as np
import optax
import orbax.checkpoint as ocp
import pytest
from flax import nnx

from motionflows import checkpoints as ck
from motionflows import config as cfg
from motionflows import pretrained, runs
from motionflows.checkpoints import Checkpointer
from motionflows.models.glow import Glow

LOGS = "flows/0/steps/bijectors/2/logs"  # level 0: the K stacked ActNorms (last in the chain)


def _state(hidden: int = 4, seed: int = 0) -> dict:
    """A tiny Glow's params / rest, a step of Adam on them, and a typed PRNG key."""
    model = Glow(6, levels=1, K=2, hidden=hidden, control_dim=0, rngs=nnx.Rngs(seed))
    _, params, rest = nnx.split(model, nnx.Param, ...)
    params = jax.tree.map(lambda p: p + 0.01 * (seed + 1), params)  # not the init values
    opt = optax.adam(1e-3)
    with jax.numpy_dtype_promotion("standard"):  # optax's Adam: float ** int32
        opt_state = opt.update(params, opt.init(params), params)[1]
    return {"params": params, "rest": rest, "opt": opt_state, "rng": {"key": jax.random.key(7)}}


def _templates(state: dict) -> dict:
    return jax.tree.map(jnp.zeros_like, state)


def _save(directory, state, step=3):
    ckpt = Checkpointer(directory)
    ckpt.save(step, state, {"step": step})
    ckpt.close()


def _restore(directory, templates):
    ckpt = Checkpointer(directory)
    try:
        return ckpt.restore(templates)
    finally:
        ckpt.close()


def _same(a, b):
    chex.assert_trees_all_equal_structs(a, b)
    chex.assert_trees_all_close(
        jax.tree.map(np.asarray, ck.named_leaves(a)), jax.tree.map(np.asarray, ck.named_leaves(b))
    )


def test_names_are_the_nnx_state_paths():
    names = ck.named_leaves(_state())
    assert f"params/{LOGS}" in names and f"opt/0/mu/{LOGS}" in names and "opt/0/count" in names
    assert not any(n.endswith("/value") for n in names)  # a Variable's .value is not a name
    chex.assert_shape(names[f"params/{LOGS}"], (2, 12))  # K = 2 steps x 2 D channels
    assert names["rng/key"].dtype == np.uint32  # typed keys are stored as their key data


def test_orbax_alone_lists_and_loads_a_checkpoint_by_name(tmp_path):
    state = _state()
    _save(tmp_path, state, step=5)
    raw = ocp.StandardCheckpointer().restore((tmp_path / "latest" / "5" / "state").absolute())
    leaf = raw["params"]["flows"]["0"]["steps"]["bijectors"]["2"]["logs"]
    np.testing.assert_array_equal(leaf, ck.named_leaves(state)[f"params/{LOGS}"])
    assert int(raw["opt"]["0"]["count"]) == 1
    listed = ck.unnest(raw)
    assert set(listed) == set(ck.named_leaves(state))


def test_round_trip_restores_every_leaf_dtype_and_key(tmp_path):
    state = _state()
    _save(tmp_path, state)
    got, meta = _restore(tmp_path, _templates(state))
    assert meta == {"step": 3}
    _same(got, state)
    assert got["opt"][0].count.dtype == jnp.int32
    assert jnp.issubdtype(got["rng"]["key"].dtype, jax.dtypes.prng_key)
    np.testing.assert_array_equal(
        jax.random.key_data(got["rng"]["key"]), jax.random.key_data(state["rng"]["key"])
    )


def _save_positional(directory, state, step=2):
    """A checkpoint as this module wrote them before the named layout (leaves by position)."""
    mgr = ocp.CheckpointManager(
        (directory / "latest").absolute(),
        options=ocp.CheckpointManagerOptions(create=True, enable_async_checkpointing=False),
    )
    flat = {name: ck.flatten(tree) for name, tree in state.items()}
    args = ocp.args.Composite(
        state=ocp.args.StandardSave(flat), meta=ocp.args.JsonSave({"step": step})
    )
    mgr.save(step, args=args)
    mgr.wait_until_finished()
    mgr.close()


def test_a_positional_checkpoint_from_before_still_loads(tmp_path):
    state = _state()
    _save_positional(tmp_path, state)
    got, meta = _restore(tmp_path, _templates(state))
    assert meta["step"] == 2
    _same(got, state)
    # resuming writes the next step by name; both steps stay readable
    ckpt = Checkpointer(tmp_path)
    ckpt.save(3, got, {"step": 3})
    back, _ = ckpt.restore(_templates(state), step=2)
    ckpt.close()
    _same(back, state)


def test_a_checkpoint_for_another_model_fails_with_one_clear_line(tmp_path):
    old, new = tmp_path / "old", tmp_path / "new"
    _save_positional(old, _state(hidden=4))
    _save(new, _state(hidden=4))
    wider = _templates(_state(hidden=8))  # same leaves, other shapes
    for directory in (old, new):
        with pytest.raises(ValueError, match="changed since the run was saved") as info:
            _restore(directory, wider)
        assert "\n" not in str(info.value)
    fewer = _templates({k: v for k, v in _state().items() if k != "rng"})
    fewer["params"] = {"w": jnp.zeros(3)}  # another architecture altogether
    with pytest.raises(ValueError, match="'w'.*unexpected.*flows/0"):
        _restore(new, fewer)


def test_the_shipped_pretrained_checkpoints_load(tmp_path):
    names = pretrained.available()
    assert names, "no pretrained models shipped"
    for name in names:
        run_dir = pretrained.path(name)
        payload = cfg.read_config_json(run_dir / "config.json")
        module = runs.resolve_experiment(payload["experiment"])
        config = cfg.config_from_json(run_dir / "config.json", module.Config, payload)
        model = nnx.eval_shape(lambda m=module, c=config: m.build(c, key=jax.random.key(0)))
        _, params, rest = nnx.split(model, nnx.Param, ...)
        templates = jax.tree.map(
            lambda s: np.zeros(s.shape, s.dtype), {"params": params, "rest": rest}
        )
        ckpt = Checkpointer(run_dir / "checkpoints")
        try:
            state, meta = ckpt.restore(templates, which="best")
        finally:
            ckpt.close()
        assert ck.all_finite(ck.named_leaves(state)), name
        chex.assert_trees_all_equal_shapes(state["params"], templates["params"])
        assert int(meta["step"]) > 0
