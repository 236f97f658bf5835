"""The optimiser and the one jitted training step of motionflows.

``make_optimizer(train)`` is an optax chain::

    [clip(clip_value)] -> [clip_by_global_norm(clip_norm)] -> adam / adamw(schedule)
        [-> parameter_average(ema_decay)]

with the learning-rate schedule of :func:`learning_rate_schedule` (warm-up, then constant,
cosine or MoGlow's "noam" rule). :func:`make_train_step` is the pure step

    (loss, metrics), grads = value_and_grad(module.loss)(params)   # nnx.Param leaves only

whose update is skipped (params and optimiser state kept, inside the jitted step, no host
sync) when the loss, the gradient norm or the update is NaN/inf; the guard counters of
:func:`init_guard` count such steps.
"""

from __future__ import annotations

import warnings
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax
from flax import nnx

from motionflows import config as cfg


def noam_schedule(lr: float, warmup: int, minimum: float) -> optax.Schedule:
    """The "noam" rule of the official MoGlow / glow-pytorch code, g the step from 0::

        lr(g) = lr * sqrt(W) * min((g + 1) * W^-1.5, (g + 1)^-0.5),  floored at ``minimum``
                once g > W

    a linear warm-up to ``lr`` at g = W - 1, then decay as sqrt(W / (g + 1)). With
    ``minimum == lr`` it is a warm-up followed by a constant ``lr``, but for step g = W
    itself, where the floor does not apply yet (lr sqrt(W / (W + 1)), as the official code's
    ``global_step > warmup_steps``)."""
    w = float(max(1, warmup))

    def schedule(step):
        g = jnp.asarray(step, jnp.float32) + 1.0
        value = lr * jnp.sqrt(w) * jnp.minimum(g * w**-1.5, g**-0.5)
        return jnp.where(g - 1.0 > w, jnp.maximum(value, minimum), value)

    return schedule


def learning_rate_schedule(train: cfg.TrainConfig) -> optax.Schedule:
    """Linear warm-up from 0 over ``warmup_steps``, then constant or cosine decay to
    ``lr * min_lr_ratio`` at ``steps``; or ``"noam"`` (:func:`noam_schedule`, its own
    warm-up over ``warmup_steps``, floor ``lr * min_lr_ratio``). A ratio given to the
    constant schedule, which does not use it, warns (a preset switched to ``constant`` by
    ``--set`` keeps its ratio, so it is not an error)."""
    if train.schedule not in cfg.SCHEDULES:
        raise ValueError(
            f"train.schedule must be one of {', '.join(cfg.SCHEDULES)}, got {train.schedule!r}"
        )
    if train.schedule == "noam":
        return noam_schedule(train.lr, train.warmup_steps, train.lr * train.min_lr_ratio)
    if train.schedule == "constant":
        if train.min_lr_ratio:
            warnings.warn(
                f"train.min_lr_ratio={train.min_lr_ratio:g} is not used: the 'constant' "
                f"schedule keeps lr {train.lr:g} after its warm-up (the ratio sets where "
                "'cosine' ends and the 'noam' floor)",
                UserWarning,
                stacklevel=2,
            )
        after = optax.constant_schedule(train.lr)
    else:
        decay = max(1, train.steps - train.warmup_steps)
        after = optax.cosine_decay_schedule(train.lr, decay, alpha=train.min_lr_ratio)
    if train.warmup_steps <= 0:
        return after
    warm = optax.linear_schedule(0.0, train.lr, train.warmup_steps)
    return optax.join_schedules([warm, after], [train.warmup_steps])


def gradient_clipping(train: cfg.TrainConfig) -> optax.GradientTransformation:
    """[clip(clip_value)] -> [clip_by_global_norm(clip_norm)] (identity when both are None)."""
    parts = []
    if train.clip_value is not None:
        parts.append(optax.clip(train.clip_value))
    if train.clip_norm is not None:
        parts.append(optax.clip_by_global_norm(train.clip_norm))
    return optax.chain(*parts) if parts else optax.identity()


class ParameterAverageState(NamedTuple):
    """The running average of the parameters (a pytree shaped like them, float32) and the
    number of updates averaged (int32)."""

    average: Any
    count: Any


def parameter_average(decay: float) -> optax.GradientTransformation:
    """Polyak averaging of the parameters, as the last link of an optax chain.

    The updates pass through unchanged; after the n-th update p_n the state holds the
    debiased exponential average of p_1 .. p_n,

        average_n = sum_k (1 - d) d^(n - k) p_k / (1 - d^n)
                  = average_{n-1} + (p_n - average_{n-1}) (1 - d) / (1 - d^n),

    so it averages the iterates over the last ~1 / (1 - d) steps and, before that many
    steps, all of them equally (d^n of the initial parameters stayed in the average
    before 2026-12-07: 37 % after 1000 steps of d = 0.999). Before the first update it
    holds the initial parameters (after any data-dependent initialisation). Read it with
    :func:`averaged_parameters`. Skipping a step (the trainer's non-finite guard keeps the
    old optimiser state) skips its average update too.
    """
    d = float(decay)
    if not 0.0 < d < 1.0:
        raise ValueError(f"parameter_average needs 0 < decay < 1, got {decay}")

    def init(params):
        average = jax.tree_util.tree_map(jnp.copy, params)  # own buffers
        return ParameterAverageState(average, jnp.zeros((), jnp.int32))

    def update(updates, state, params=None):
        if params is None:
            raise ValueError("parameter_average needs the parameters: update(g, s, params)")
        new = optax.apply_updates(params, updates)
        count = state.count + 1
        d32 = jnp.float32(d)  # one precision for both sides of the ratio
        rate = jnp.where(count == 1, 1.0, (1 - d32) / (1 - d32 ** count.astype(jnp.float32)))
        average = jax.tree_util.tree_map(
            lambda a, p: (1 - rate) * a + rate * p,  # exactly p_1 after the first update
            state.average,
            new,
        )
        return updates, ParameterAverageState(average, count)

    return optax.GradientTransformation(init, update)


def averaged_parameters(opt_state: Any) -> Any | None:
    """The running average of :func:`parameter_average` held in ``opt_state``, or None when
    the optimiser has none."""

    def is_average(node):
        return isinstance(node, ParameterAverageState)

    found = [
        node
        for node in jax.tree_util.tree_leaves(opt_state, is_leaf=is_average)
        if is_average(node)
    ]
    return found[0].average if found else None


def make_optimizer(
    train: cfg.TrainConfig, schedule: optax.Schedule | None = None
) -> optax.GradientTransformation:
    """optax chain: [clip(clip_value)] -> [clip_by_global_norm(clip_norm)] -> adam / adamw
    -> [parameter_average(ema_decay)], at the learning rate ``schedule`` (by default
    :func:`learning_rate_schedule` of ``train``; a caller that also logs the rate passes the
    one it built).

    ``weight_decay`` w acts on every parameter. With "adam" it is an L2 penalty, as
    ``torch.optim.Adam``'s: w * p is added to the clipped gradient before Adam's moments.
    With "adamw" it is decoupled (Loshchilov & Hutter): p -= lr_t * w * p beside Adam's step.
    """
    parts = [gradient_clipping(train)]
    lr = learning_rate_schedule(train) if schedule is None else schedule
    if train.optimizer == "adam":
        if train.weight_decay:
            parts.append(optax.add_decayed_weights(train.weight_decay))
        parts.append(optax.adam(lr, b1=train.b1, b2=train.b2, eps=train.eps))
    elif train.optimizer == "adamw":
        parts.append(
            optax.adamw(
                lr, b1=train.b1, b2=train.b2, eps=train.eps, weight_decay=train.weight_decay
            )
        )
    else:
        raise ValueError(f"train.optimizer must be 'adam' or 'adamw', got {train.optimizer!r}")
    if train.ema_decay is not None:
        parts.append(parameter_average(train.ema_decay))
    return optax.chain(*parts)


def init_guard() -> dict[str, jax.Array]:
    """Non-finite guard counters: current run of bad steps, its maximum, total skipped."""
    z = jnp.zeros((), jnp.int32)
    return {"consecutive": z, "peak": z, "skipped": z}


def make_train_step(module: Any, graphdef: Any, optimizer: optax.GradientTransformation):
    """The jitted step ``(params, rest, opt_state, guard, batch, key) -> (params, opt_state,
    guard, out)``; ``params`` and ``opt_state`` are donated. ``out`` holds ``loss``,
    ``grad_norm``, ``finite`` and the module's metrics. A non-finite loss, gradient norm or
    update leaves params and optimiser state unchanged (``jnp.where``: no host sync)."""

    def step(params, rest, opt_state, guard, batch, key):
        def objective(p):
            model = nnx.merge(graphdef, p, rest)
            return module.loss(model, batch, key)

        (loss, metrics), grads = jax.value_and_grad(objective, has_aux=True)(params)
        grad_norm = optax.tree.norm(grads)
        # optax's Adam bias correction computes ``decay ** count`` (float ** int32), which
        # strict dtype promotion refuses; the library's own maths stays strict-clean.
        with jax.numpy_dtype_promotion("standard"):
            updates, new_opt = optimizer.update(grads, opt_state, params)
        new_params = optax.apply_updates(params, updates)
        finite = (
            jnp.isfinite(loss) & jnp.isfinite(grad_norm) & jnp.isfinite(optax.tree.norm(updates))
        )

        def keep(new, old):
            return jax.tree_util.tree_map(lambda a, b: jnp.where(finite, a, b), new, old)

        consecutive = jnp.where(finite, 0, guard["consecutive"] + 1).astype(jnp.int32)
        guard = {
            "consecutive": consecutive,
            "peak": jnp.maximum(guard["peak"], consecutive),
            "skipped": guard["skipped"] + (~finite).astype(jnp.int32),
        }
        out = {"loss": loss, "grad_norm": grad_norm, "finite": finite, **dict(metrics)}
        return keep(new_params, params), keep(new_opt, opt_state), guard, out

    return jax.jit(step, donate_argnums=(0, 2))
