"""The one training loop of motionflows, shared by every experiment module.

``train(module, config, run_dir=...)`` builds the model (``module.build``), optionally
initialises it from the first batch (``module.initialize``), then runs one jitted train
step per batch:

    (loss, metrics), grads = value_and_grad(module.loss)(params)   # nnx.Param leaves only
    grads -> [clip values] -> [clip global norm] -> adam(w) with warm-up schedule
    a step whose loss, gradient norm or update is NaN/inf is skipped inside the jitted
    step (params and optimiser state kept) and counted.

Determinism: the batch of step ``i`` is ``dataset.batch("train", B, seed=train.seed,
index=i)`` and its key ``fold_in(train_key, i)``, so a resumed run reproduces the loss curve
of an uninterrupted one. Modules defining ``fit(model, dataset[, config=...])`` (the
closed-form baselines) are fitted instead of trained.

Bookkeeping (see ``motionflows.runs``): ``config.json``, ``standardizer.json``,
``metrics.jsonl`` (loss, grad_norm, lr, steps_per_s, frames_per_s, skipped; val_nll in
nats/frame in metres and val_bits in bits/frame standardised), ``loss.png``, orbax
checkpoints (``motionflows.checkpoints``: latest N plus best by validation), a progress
bar with ETA on stderr. Ctrl-C (SIGINT) finishes the current step, writes a checkpoint and
returns; ``resume=True`` continues from the latest checkpoint.

Every experiment module gets its command line from :func:`experiment_main`::

    if __name__ == "__main__":
        import sys
        from motionflows.training import experiment_main
        sys.exit(experiment_main(sys.modules[__name__]))
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import inspect
import json
import math
import signal
import sys
import threading
import time
import warnings
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import nnx

from motionflows import config as cfg
from motionflows import distributed, runs
from motionflows.checkpoints import Checkpointer
from motionflows.errors import RunError
from motionflows.evaluation import likelihood
from motionflows.sharding import check_batch_size, data_mesh, replicate, shard_batch

__all__ = [
    "TrainResult",
    "draw_samples",
    "evaluate_run",
    "experiment_main",
    "gradient_clipping",
    "learning_rate_schedule",
    "load_run",
    "load_standardizer",
    "main",
    "make_optimizer",
    "make_train_step",
    "train",
    "validate",
    "validation_windows",
]

warnings.filterwarnings("ignore", message="Some donated buffers were not usable")


# ---------------------------------------------------------------------------- optimiser


def noam_schedule(lr: float, warmup: int, minimum: float) -> optax.Schedule:
    """The "noam" rule of the official MoGlow / glow-pytorch code, g the step from 0::

        lr(g) = lr * sqrt(W) * min((g + 1) * W^-1.5, (g + 1)^-0.5),  floored at ``minimum``
                once g > W

    a linear warm-up to ``lr`` at g = W - 1, then decay as sqrt(W / (g + 1)). With
    ``minimum == lr`` it is a warm-up followed by a constant ``lr``."""
    w = float(max(1, warmup))

    def schedule(step):
        g = jnp.asarray(step, jnp.float32) + 1.0
        value = lr * jnp.sqrt(w) * jnp.minimum(g * w**-1.5, g**-0.5)
        return jnp.where(g - 1.0 > w, jnp.maximum(value, minimum), value)

    return schedule


def learning_rate_schedule(train: cfg.TrainConfig) -> optax.Schedule:
    """Linear warm-up from 0 over ``warmup_steps``, then constant or cosine decay to
    ``lr * min_lr_ratio`` at ``steps``; or ``"noam"`` (:func:`noam_schedule`, its own
    warm-up over ``warmup_steps``, floor ``lr * min_lr_ratio``)."""
    if train.schedule not in cfg.SCHEDULES:
        raise ValueError(
            f"train.schedule must be one of {', '.join(cfg.SCHEDULES)}, got {train.schedule!r}"
        )
    if train.schedule == "noam":
        return noam_schedule(train.lr, train.warmup_steps, train.lr * train.min_lr_ratio)
    if train.schedule == "constant":
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


def make_optimizer(train: cfg.TrainConfig) -> optax.GradientTransformation:
    """optax chain: [clip(clip_value)] -> [clip_by_global_norm(clip_norm)] -> adam / adamw."""
    parts = [gradient_clipping(train)]
    lr = learning_rate_schedule(train)
    if train.optimizer == "adam":
        parts.append(optax.adam(lr, b1=train.b1, b2=train.b2, eps=train.eps))
    elif train.optimizer == "adamw":
        parts.append(
            optax.adamw(
                lr, b1=train.b1, b2=train.b2, eps=train.eps, weight_decay=train.weight_decay
            )
        )
    else:
        raise ValueError(f"train.optimizer must be 'adam' or 'adamw', got {train.optimizer!r}")
    return optax.chain(*parts)


def init_guard() -> dict[str, jax.Array]:
    """Non-finite guard counters: current run of bad steps, its maximum, total skipped."""
    z = jnp.zeros((), jnp.int32)
    return {"consecutive": z, "peak": z, "skipped": z}


_JIT_CACHE: dict = {}


def _cached(key: Any, build: Any) -> Any:
    """Reuse jitted functions (and so their compilations) across train()/load_run() calls."""
    try:
        hash(key)
    except TypeError:
        return build()
    if key not in _JIT_CACHE:
        if len(_JIT_CACHE) >= 16:
            _JIT_CACHE.pop(next(iter(_JIT_CACHE)))
        _JIT_CACHE[key] = build()
    return _JIT_CACHE[key]


def jitted_evaluate(module: Any):
    """``jax.jit(module.evaluate)``, one per evaluate function."""
    return _cached(("evaluate", module.evaluate), lambda: jax.jit(module.evaluate))


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


# ------------------------------------------------------------------------------- helpers


@dataclasses.dataclass
class TrainResult:
    """What :func:`train` returns. ``status``: finished | fitted | interrupted | nonfinite."""

    model: Any
    run_dir: Path
    step: int
    status: str
    best_val_nll: float | None = None
    last_metrics: dict = dataclasses.field(default_factory=dict)


def _keys(seed: int) -> dict[str, jax.Array]:
    base = jax.random.key(seed)
    names = ("build", "init", "train", "eval")
    return dict(zip(names, jax.random.split(base, len(names)), strict=True))


def _main_key(lls: dict, scopes: dict | None = None, preferred: str | None = None) -> str:
    """The score behind ``val_nll`` (and the best checkpoint): the module's
    ``VALIDATION_SCOPE`` when it declares one, else "window", else its first SCOPE."""
    if preferred in lls:
        return preferred
    if "window" in lls:
        return "window"
    return next((k for k in (scopes or {}) if k in lls), next(iter(lls)))


def validation_windows(config: Any, dataset: Any, split: str = "val"):
    """The fixed validation subset: ``train.eval_batches * batch`` complete windows of
    ``split`` drawn once with seed 0 (all of them if the split is smaller), standardised."""
    tc = config.train
    bs = tc.val_batch_size or tc.batch_size
    limit = max(1, tc.eval_batches) * bs
    pose, control = _split_windows(dataset, split, batch_size=bs, fallback_batches=tc.eval_batches)
    if len(pose) > limit:
        idx = np.sort(np.random.default_rng(0).permutation(len(pose))[:limit])
        pose, control = pose[idx], control[idx]
    return pose, control


def validate(
    module: Any,
    config: Any,
    model: Any,
    dataset: Any,
    *,
    key: jax.Array,
    evaluate_fn: Any = None,
    split: str = "val",
    windows: Any = None,
) -> dict:
    """Validation NLL on :func:`validation_windows`: ``val_nll`` (nats/frame, metres) and
    ``val_bits`` (bits/frame, standardised) of the module's ``VALIDATION_SCOPE`` (else the
    ``window`` scope, else the first scope), plus ``val_<scope>_nll`` for every scope."""
    tc = config.train
    pose, control = windows if windows is not None else validation_windows(config, dataset, split)
    lls = likelihood.evaluate_windows(
        module,
        model,
        pose,
        control,
        batch_size=tc.val_batch_size or tc.batch_size,
        key=key,
        evaluate_fn=evaluate_fn or jitted_evaluate(module),
    )
    window = pose.shape[1]
    ldpf = float(dataset.standardizer.log_det_per_frame)
    out = {}
    for k, ll in lls.items():
        n = likelihood.scored_frames(getattr(module, "SCOPES", {}), k, window, config)
        out[f"val_{k}_nll"] = float(np.mean(likelihood.nats_per_frame_metres(ll, n, ldpf)))
        if k == _main_key(
            lls, getattr(module, "SCOPES", {}), getattr(module, "VALIDATION_SCOPE", None)
        ):
            out["val_nll"] = out[f"val_{k}_nll"]
            out["val_bits"] = float(np.mean(likelihood.bits_per_frame_standardized(ll, n)))
    return out


class _StopFlag:
    """SIGINT handler: the first Ctrl-C asks the loop to stop after the current step."""

    def __init__(self):
        self.requested = False
        self._old = None

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            self._old = signal.getsignal(signal.SIGINT)

            def handler(signum, frame):
                if self.requested:  # a second Ctrl-C: stop now
                    raise KeyboardInterrupt
                self.requested = True

            signal.signal(signal.SIGINT, handler)
        return self

    def __exit__(self, *exc):
        if self._old is not None:
            signal.signal(signal.SIGINT, self._old)
        return False


def _standardizer_dict(dataset: Any) -> dict:
    std = dataset.standardizer
    if hasattr(std, "to_dict"):
        return std.to_dict()
    return {
        k: np.asarray(getattr(std, k)).tolist()
        for k in ("pose_mean", "pose_std", "control_mean", "control_std")
    }


def _write_json(path: Path, payload: Any) -> None:
    path.write_text(json.dumps(payload, indent=2) + "\n")


def _primary() -> bool:
    return jax.process_index() == 0


def _scalar(x: Any) -> Any:
    x = np.asarray(x)
    if x.size != 1:
        return None
    v = x.item()
    if isinstance(v, float) and not math.isfinite(v):
        return None  # JSON has no NaN: a non-finite value is logged as null
    return v


# ---------------------------------------------------------------------------------- train


def train(
    module: Any,
    config: Any,
    *,
    run_dir: str | Path,
    preset: str | None = None,
    resume: bool = False,
    dataset: Any = None,
    progress: bool = True,
    use_fit: bool = True,
    mesh: Any = None,
    on_step: Any = None,
) -> TrainResult:
    """Train (or fit) ``module``'s model with ``config`` into ``run_dir``.

    ``resume=True`` continues from the latest checkpoint of ``run_dir`` (same loss curve as
    an uninterrupted run). ``dataset`` defaults to ``config.data.load()``. ``mesh`` defaults
    to a ``data`` mesh over all devices. ``on_step(step, out)`` is called after each step
    is dispatched (testing hook; ``out`` holds device arrays).
    """
    module = runs.resolve_experiment(module)
    run_dir = Path(run_dir)
    tc = config.train
    ckdir = run_dir / "checkpoints"
    if not resume and ckdir.is_dir() and any(ckdir.glob("*/*")):
        raise RunError(
            f"{run_dir} already holds checkpoints: pass --resume to continue it, or choose "
            "another --run-name"
        )
    if resume and not (run_dir / "config.json").is_file():
        raise RunError(f"cannot resume {run_dir}: it is not a run directory (no config.json)")
    dataset = config.data.load() if dataset is None else dataset
    if _primary():  # the other processes of a multi-process run write nothing here
        for sub in ("checkpoints", "samples"):
            (run_dir / sub).mkdir(parents=True, exist_ok=True)
        cfg.save_config(
            run_dir / "config.json", experiment=module.NAME, preset=preset, config=config
        )
        _write_json(run_dir / "standardizer.json", _standardizer_dict(dataset))
    keys = _keys(tc.seed)
    model = module.build(config, key=keys["build"])
    ckpt = Checkpointer(ckdir, keep=tc.keep_checkpoints)
    eval_fn = jitted_evaluate(module)
    base_meta = {"seed": tc.seed, "rng": np.asarray(jax.random.key_data(keys["train"])).tolist()}
    try:
        if use_fit and hasattr(module, "fit"):
            return _fit(module, config, model, dataset, run_dir, ckpt, eval_fn, keys, base_meta)
        return _train_loop(
            module,
            config,
            model,
            dataset,
            run_dir,
            ckpt,
            eval_fn,
            keys,
            base_meta,
            resume=resume,
            progress=progress,
            mesh=mesh,
            on_step=on_step,
        )
    finally:
        ckpt.close()


def _fit(module, config, model, dataset, run_dir, ckpt, eval_fn, keys, base_meta):
    t0 = time.perf_counter()
    kwargs = {"config": config} if "config" in inspect.signature(module.fit).parameters else {}
    model = module.fit(model, dataset, **kwargs)
    seconds = time.perf_counter() - t0
    val = validate(module, config, model, dataset, key=keys["eval"], evaluate_fn=eval_fn)
    graphdef, params, rest = nnx.split(model, nnx.Param, ...)
    meta = {**base_meta, "step": 0, "data_index": 0, "fit": True, **val}
    state = {"params": params, "rest": rest}
    ckpt.save(0, state, meta, which="latest")
    ckpt.save(0, state, meta, which="best")
    row = {"step": 0, "fit": "closed-form", "fit_seconds": seconds, **val, "status": "fitted"}
    runs.truncate_metrics(run_dir, -1)
    runs.append_metrics(run_dir, row)
    print(
        f"fitted {module.NAME} in closed form in {seconds:.1f} s: val NLL "
        f"{val['val_nll']:.3f} nats/frame (metres)",
        file=sys.stderr,
    )
    return TrainResult(model, run_dir, 0, "fitted", val["val_nll"], row)


def _train_loop(
    module,
    config,
    model,
    dataset,
    run_dir,
    ckpt,
    eval_fn,
    keys,
    base_meta,
    *,
    resume,
    progress,
    mesh,
    on_step,
):
    tc = config.train
    mesh = data_mesh() if mesh is None else mesh
    check_batch_size(tc.batch_size, mesh)
    optimizer = make_optimizer(tc)
    schedule = learning_rate_schedule(tc)
    start, best = 0, None
    guard = init_guard()
    if resume and ckpt.latest_step() is not None:
        graphdef, params, rest = nnx.split(model, nnx.Param, ...)
        templates = {"params": params, "rest": rest, "opt": optimizer.init(params)}
        state, meta = ckpt.restore(templates, which="latest")
        params, rest, opt_state = state["params"], state["rest"], state["opt"]
        start = int(meta["step"])
        best = meta.get("best_val_nll")
        guard = {**init_guard(), "skipped": jnp.asarray(meta.get("skipped", 0), jnp.int32)}
        if _primary():
            runs.truncate_metrics(run_dir, start)
        print(f"resumed {run_dir} at step {start}", file=sys.stderr)
    else:
        if resume:
            print(f"no checkpoint in {run_dir}: starting from step 0", file=sys.stderr)
        if _primary():
            runs.truncate_metrics(run_dir, -1)
        if hasattr(module, "initialize"):
            first = dataset.batch("train", tc.batch_size, seed=tc.seed, index=0)
            model = module.initialize(model, first, key=keys["init"])
        graphdef, params, rest = nnx.split(model, nnx.Param, ...)
        opt_state = optimizer.init(params)
    # the guard too: a guard off the mesh would make the second step compile again
    params, rest, opt_state, guard = replicate((params, rest, opt_state, guard), mesh)
    step_fn = _cached(
        ("step", module.loss, graphdef, tc), lambda: make_train_step(module, graphdef, optimizer)
    )

    def current_model():
        return nnx.merge(graphdef, params, rest)

    def save(step, which="latest", extra=None):
        meta = {
            **base_meta,
            "step": step,
            "data_index": step,
            "best_val_nll": best,
            "skipped": int(guard["skipped"]),
            **(extra or {}),
        }
        ckpt.save(step, {"params": params, "rest": rest, "opt": opt_state}, meta, which=which)

    val_windows = validation_windows(config, dataset)
    bar = runs.Progress(tc.steps, start, enabled=progress)
    pending: list = []
    t_log, step_log = time.perf_counter(), start
    t_plot = t_log
    status, last_row, frames = "finished", {}, 0
    completed = start  # steps whose update is in params / opt_state

    def log(done):
        """Average the pending step outputs into one metrics row (one host sync)."""
        nonlocal pending, t_log, step_log, last_row
        outs = jax.device_get(pending)
        now = time.perf_counter()
        rate = (done - step_log) / max(now - t_log, 1e-9)
        t_log, step_log, pending = now, done, []
        ok = [o for o in outs if bool(o["finite"])]
        row = {"step": done}
        for k in outs[-1]:
            if k == "finite":
                continue
            vals = [_scalar(o[k]) for o in ok]
            vals = [v for v in vals if isinstance(v, int | float)]
            row[k] = float(np.mean(vals)) if vals else None
        row.update(
            {
                "lr": float(schedule(done - 1)),
                "steps_per_s": rate,
                "frames_per_s": rate * frames,
                "skipped": int(guard["skipped"]),
                "nonfinite_run": int(guard["consecutive"]),
            }
        )
        last_row = row
        if _primary():
            runs.append_metrics(run_dir, row)
        loss_txt = f"{row['loss']:.4f}" if row["loss"] is not None else "nan"
        bar.update(done, f"loss {loss_txt} {rate:.2f} it/s")

    with _StopFlag() as stop:
        try:
            for step in range(start, tc.steps):
                if stop.requested:
                    status = "interrupted"
                    break
                batch = dataset.batch("train", tc.batch_size, seed=tc.seed, index=step)
                frames = int(np.prod(np.shape(batch["pose"])[:2]))
                batch = shard_batch(batch, mesh)
                distributed.trace_local_rows(step, batch)
                key = jax.random.fold_in(keys["train"], step)
                params, opt_state, guard, out = step_fn(params, rest, opt_state, guard, batch, key)
                completed = done = step + 1
                pending.append(out)
                if on_step is not None:
                    on_step(step, out)
                if done % tc.log_every == 0 or done == tc.steps:
                    log(done)
                    if int(guard["peak"]) >= tc.max_nonfinite:
                        status = "nonfinite"
                        break
                if done % tc.eval_every == 0 or done == tc.steps:
                    val = validate(
                        module,
                        config,
                        current_model(),
                        dataset,
                        key=keys["eval"],
                        evaluate_fn=eval_fn,
                        windows=val_windows,
                    )
                    if _primary():
                        runs.append_metrics(
                            run_dir, {"step": done, **{k: _scalar(v) for k, v in val.items()}}
                        )
                        if time.perf_counter() - t_plot > 60.0:  # plotting costs ~1 s
                            runs.plot_losses(run_dir)
                            t_plot = time.perf_counter()
                    val_nll = val["val_nll"]
                    if math.isfinite(val_nll) and (best is None or val_nll < best):
                        best = val_nll
                        save(done, "best", val)
                if done % tc.checkpoint_every == 0 or done == tc.steps:
                    save(done)
                if not pending:  # steps/s measure training only, not validation or saving
                    t_log = time.perf_counter()
        except KeyboardInterrupt:  # raised by a second Ctrl-C, or by code called in the loop
            status = "interrupted"
            if any(
                getattr(x, "is_deleted", lambda: False)()
                for x in jax.tree_util.tree_leaves((params, opt_state))
            ):  # interrupted inside the step, after its inputs were donated
                bar.close()
                print(
                    f"\ninterrupted inside a step: no new checkpoint (the latest is step "
                    f"{ckpt.latest_step()})",
                    file=sys.stderr,
                )
                raise
    step = completed
    if pending:  # outputs of steps not logged yet (an interrupt between log points)
        log(step)
    bar.close()
    if status == "interrupted":
        save(step)
        print(
            f"\ninterrupted at step {step}: checkpoint saved in {run_dir / 'checkpoints'}; "
            f"continue with --resume",
            file=sys.stderr,
        )
    elif status == "nonfinite":
        save(step)
        print(
            f"stopped at step {step}: {int(guard['peak'])} consecutive steps had a NaN/inf "
            f"loss or gradient (train.max_nonfinite={tc.max_nonfinite}); they were skipped "
            f"({int(guard['skipped'])} in all) and the last good state is checkpointed. "
            "Try a lower train.lr, train.clip_norm, or check the data.",
            file=sys.stderr,
        )
    if _primary():
        runs.append_metrics(run_dir, {"step": step, "status": status})
        runs.plot_losses(run_dir)
    return TrainResult(current_model(), run_dir, step, status, best, last_row)


# ---------------------------------------------------------------------------- load / eval


class _Standardizer:
    """Fallback standardiser read from ``standardizer.json`` (the data layer's own class is
    used when it can read the file)."""

    def __init__(self, d: dict):
        self.pose_mean = np.asarray(d["pose_mean"], np.float32)
        self.pose_std = np.asarray(d["pose_std"], np.float32)
        self.control_mean = np.asarray(d["control_mean"], np.float32)
        self.control_std = np.asarray(d["control_std"], np.float32)

    @property
    def log_det_per_frame(self) -> float:
        return float(-np.sum(np.log(self.pose_std)))

    def normalize_pose(self, x):
        return (np.asarray(x) - self.pose_mean) / self.pose_std

    def denormalize_pose(self, x):
        return np.asarray(x) * self.pose_std + self.pose_mean

    def normalize_control(self, c):
        return (np.asarray(c) - self.control_mean) / self.control_std

    def denormalize_control(self, c):
        return np.asarray(c) * self.control_std + self.control_mean

    def to_dict(self) -> dict:
        return {
            k: getattr(self, k).tolist()
            for k in ("pose_mean", "pose_std", "control_mean", "control_std")
        }


def load_standardizer(run_dir: str | Path):
    """The run's standardiser from ``standardizer.json`` (no dataset needed); a missing or
    damaged file raises ``RunError`` naming it."""
    path = Path(run_dir) / "standardizer.json"
    fix = "copy it back from a backup, or train the run again (it is written at the start)"
    try:
        d = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise RunError(f"{path} is missing: sampling needs the run's standardiser; {fix}") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise RunError(f"{path} cannot be read ({err}); {fix}") from None
    keys = ("pose_mean", "pose_std", "control_mean", "control_std")
    if not isinstance(d, dict) or any(k not in d for k in keys):
        raise RunError(f"{path} lacks one of the fields {list(keys)}; {fix}")
    for k in keys:
        try:
            arr = np.asarray(d[k], np.float64)
        except (TypeError, ValueError):
            arr = np.zeros(0)
        size = np.size(d[f"{k.split('_')[0]}_mean"])
        if arr.ndim != 1 or arr.size == 0 or arr.size != size or not np.all(np.isfinite(arr)):
            raise RunError(f"{path}: field {k!r} must be a list of finite numbers; {fix}")
        if k.endswith("_std") and not np.all(arr > 0):
            raise RunError(f"{path}: field {k!r} must be positive everywhere; {fix}")
    try:
        from motionflows.data import Standardizer

        return Standardizer.from_dict(d)
    except (ImportError, AttributeError, KeyError, TypeError):
        return _Standardizer(d)


def load_run(
    run_dir: str | Path, *, checkpoint: str = "best", dataset: Any = None, load_data: bool = True
):
    """Rebuild ``(module, config, model, dataset)`` from a run directory alone.

    ``checkpoint``: "best" (falls back to "latest" if no best exists) or "latest".
    ``dataset``: reuse an already loaded dataset; ``load_data=False`` returns None.
    """
    run_dir = runs.check_run_dir(run_dir)
    payload = cfg.read_config_json(run_dir / "config.json")
    module = runs.resolve_experiment(payload["experiment"])
    config = cfg.config_from_json(run_dir / "config.json", module.Config, payload)
    model = module.build(config, key=_keys(config.train.seed)["build"])
    graphdef, params, rest = nnx.split(model, nnx.Param, ...)
    ckpt = Checkpointer(run_dir / "checkpoints", keep=config.train.keep_checkpoints)
    try:
        which = checkpoint
        if which == "best" and ckpt.latest_step("best") is None:
            which = "latest"
        if ckpt.latest_step(which) is None:
            raise RunError(f"{run_dir} has no checkpoint yet (train it first)")
        state, _ = ckpt.restore({"params": params, "rest": rest}, which=which)
    finally:
        ckpt.close()
    model = nnx.merge(graphdef, state["params"], state["rest"])
    if dataset is None and load_data:
        dataset = config.data.load()
    return module, config, model, dataset


def _split_windows(
    dataset: Any, split: str, *, batch_size: int = 32, fallback_batches: int = 8
) -> tuple[np.ndarray, np.ndarray]:
    """Standardised (pose, control) of every complete window of ``split`` (windows padded
    past the end of a short take, ``WindowSet.valid`` False somewhere, are left out).

    A dataset without window arrays or a standardiser that can normalise them is read
    through ``dataset.batch(split, batch_size, seed=0, index=i)`` instead (enough batches
    to cover the split once, or ``fallback_batches`` if its size is unknown)."""
    try:
        return _split_arrays(dataset, split)
    except AttributeError:
        pass
    try:
        n = len(getattr(dataset, split).pose)
        count = -(-n // batch_size)
    except (AttributeError, TypeError):
        n, count = None, max(1, fallback_batches)
    batches = [dataset.batch(split, batch_size, seed=0, index=i) for i in range(count)]
    pose = np.concatenate([np.asarray(b["pose"], np.float32) for b in batches])[:n]
    control = np.concatenate([np.asarray(b["control"], np.float32) for b in batches])[:n]
    return pose, control


def _split_arrays(dataset: Any, split: str) -> tuple[np.ndarray, np.ndarray]:
    ws = dataset.split(split) if hasattr(dataset, "split") else getattr(dataset, split)
    if hasattr(dataset, "arrays"):
        arr = dataset.arrays(split)
        pose, control = np.asarray(arr["pose"]), np.asarray(arr["control"])
    else:
        std = dataset.standardizer
        pose = np.asarray(std.normalize_pose(np.asarray(ws.pose)), np.float32)
        control = np.asarray(std.normalize_control(np.asarray(ws.control)), np.float32)
    valid = getattr(ws, "valid", None)
    if valid is not None:
        keep = np.asarray(valid).reshape(len(pose), -1).all(axis=1)
        pose, control = pose[keep], control[keep]
    if len(pose) == 0:
        raise RunError(f"the {split} split has no complete windows to evaluate")
    return pose.astype(np.float32), control.astype(np.float32)


def evaluate_run(
    run_dir: str | Path,
    split: str = "test",
    *,
    data: str | None = None,
    label: str | None = None,
    skeleton: str = "bandai",
    checkpoint: str = "best",
    dataset: Any = None,
    batch_size: int | None = None,
    print_table: bool = True,
    out_dir: str | Path | None = None,
) -> list[dict]:
    """Score every complete window of ``split``, or of the takes of ``data``; write
    ``eval_<split>.json`` (``eval_<label>.json``) into ``out_dir`` (default: the run
    directory) and print the table.

    ``data``: other takes (``"bvh:DIR"``, ``"bandai:DIR"``, a folder or one ``.bvh``; see
    :mod:`motionflows.data.takes`), cut into the run's windows at the run's fps and
    standardised with the run's own standardiser (never refitted); ``label`` names the
    output (default: the folder's name) and ``skeleton`` maps the BVH joints. Takes too short
    for one window are listed as skipped in the JSON and on stderr.
    """
    extra: dict[str, Any] = {}
    if data is None:
        module, config, model, dataset = load_run(run_dir, checkpoint=checkpoint, dataset=dataset)
        bs = batch_size or config.train.val_batch_size or config.train.batch_size
        pose, control = _split_windows(
            dataset, split, batch_size=bs, fallback_batches=config.train.eval_batches
        )
        ldpf = float(dataset.standardizer.log_det_per_frame)
        name, what = split, f"{split} split"
    else:
        from motionflows.data.takes import load_takes

        module, config, model, _ = load_run(run_dir, checkpoint=checkpoint, load_data=False)
        bs = batch_size or config.train.val_batch_size or config.train.batch_size
        std = load_standardizer(run_dir)
        takes = load_takes(
            data,
            fps=float(config.data.fps),
            window=int(config.data.window),
            hop=int(config.data.hop),
            skeleton=skeleton,
        )
        pose = np.asarray(std.normalize_pose(takes.windows.pose), np.float32)
        control = np.asarray(std.normalize_control(takes.windows.control), np.float32)
        ldpf = float(std.log_det_per_frame)
        name = _file_label(label or takes.label)
        used = sorted(set(np.asarray(takes.windows.take).tolist()))
        what = f"{len(used)} takes of {data}"
        extra = {"data": str(data), "takes": used, "skipped": takes.skipped}
        for item in takes.skipped:
            print(f"skipped take {item}: shorter than one window", file=sys.stderr)
    lls = likelihood.evaluate_windows(
        module,
        model,
        pose,
        control,
        batch_size=bs,
        key=_keys(config.train.seed)["eval"],
        evaluate_fn=jitted_evaluate(module),
    )
    window = pose.shape[1]
    scopes = getattr(module, "SCOPES", {})
    frames = {k: likelihood.scored_frames(scopes, k, window, config) for k in lls}
    rows = likelihood.likelihood_rows(lls, frames, ldpf, scopes=scopes)
    out_dir = Path(run_dir if out_dir is None else out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    likelihood.write_eval(
        out_dir / f"eval_{name}.json",
        rows,
        split=split if data is None else name,
        experiment=module.NAME,
        window=window,
        checkpoint=checkpoint,
        log_det_per_frame=ldpf,
        **extra,
    )
    if print_table:
        print(
            likelihood.format_table(
                rows,
                title=f"{module.NAME} — {what}, {pose.shape[0]} windows of {window} "
                f"frames ({Path(run_dir)})",
            )
        )
    return rows


def _file_label(text: str) -> str:
    """``text`` made safe as part of a file name (letters, digits, ``-``, ``_``, ``.``)."""
    out = "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in str(text)).strip("._")
    return out or "data"


def draw_samples(
    module: Any,
    model: Any,
    standardizer: Any,
    control: np.ndarray,
    *,
    num: int = 1,
    temperature: float = 1.0,
    seed: int = 0,
) -> np.ndarray:
    """Sample ``num`` pose sequences (num, T, 63) in metres for one control (T, 3) given
    in data units (m/frame, rad/frame): standardise, one jitted ``module.sample``,
    de-standardise. Raises ``RunError`` if the samples hold NaN/inf."""
    control = np.asarray(control, np.float32)
    if control.ndim != 2:
        raise ValueError(f"control must be (T, 3), got {control.shape}")
    c_std = np.asarray(standardizer.normalize_control(control), np.float32)
    c_std = np.ascontiguousarray(np.broadcast_to(c_std, (num, *c_std.shape)))
    temperature = float(temperature)

    @jax.jit
    def draw(model, control, key):
        return module.sample(model, control, key, temperature=temperature)

    pose_std = np.asarray(draw(model, c_std, jax.random.key(seed)))
    if not np.all(np.isfinite(pose_std)):
        raise RunError("the sampled poses hold NaN/inf; try a lower temperature")
    return np.asarray(standardizer.denormalize_pose(pose_std), np.float32)


# ------------------------------------------------------------------------ command line


def add_train_arguments(parser: argparse.ArgumentParser) -> None:
    """The flags shared by ``python -m experiments.<name>`` and ``motionflows train``."""
    parser.add_argument("--preset", default="quick", help="named config (default: quick)")
    parser.add_argument(
        "--data", default=None, help="synthetic | bandai | bandai:DIR | bvh:DIR | DIR"
    )
    parser.add_argument("--steps", type=int, default=None, help="training steps (train.steps)")
    parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        nargs="+",
        default=[],
        metavar="KEY=VALUE",
        help="config override, e.g. train.lr=1e-3",
    )
    parser.add_argument("--run-name", default=None, help="run directory name")
    parser.add_argument("--runs-dir", default="runs", help="root of run directories")
    parser.add_argument(
        "--resume",
        action="store_true",
        help="continue --run-name (or the latest run) from its checkpoint",
    )
    parser.add_argument("--no-eval", action="store_true", help="skip the final test table")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def configure(module: Any, args: argparse.Namespace) -> tuple[Any, str | None, Path]:
    """(config, preset, run_dir) from parsed train flags (resume reads config.json)."""
    overrides = [item for group in args.overrides for item in group]
    if args.resume:
        run_dir = (
            Path(args.runs_dir) / module.NAME / args.run_name
            if args.run_name
            else runs.latest_run(args.runs_dir, module.NAME)
        )
        if run_dir is None:
            raise RunError(f"no run of {module.NAME} under {args.runs_dir}/ to resume")
        run_dir = runs.check_run_dir(run_dir)
        _, preset, config = cfg.load_config(run_dir / "config.json", module.Config)
    else:
        if args.preset not in module.PRESETS:
            raise RunError(
                f"unknown preset {args.preset!r} for {module.NAME}; "
                f"available: {sorted(module.PRESETS)}"
            )
        preset, config = args.preset, module.PRESETS[args.preset]
        run_dir = Path(args.runs_dir) / module.NAME / (args.run_name or runs.new_run_name(preset))
    if args.data is not None:
        config = dataclasses.replace(
            config, data=dataclasses.replace(config.data, **runs.parse_data(args.data))
        )
    if args.steps is not None:
        if args.steps < 0:
            raise RunError(f"--steps must be >= 0, got {args.steps}")
        config = dataclasses.replace(
            config, train=dataclasses.replace(config.train, steps=args.steps)
        )
    try:
        config = cfg.apply_overrides(config, overrides)
    except ValueError as err:
        raise RunError(str(err)) from None
    return config, preset, run_dir


def run_train(module: Any, args: argparse.Namespace) -> int:
    """Train from parsed flags, then print the test table; the exit code."""
    distributed.configure_cpu_threads()  # before JAX starts its CPU backend
    if distributed.initialize():  # MOTIONFLOWS_COORDINATOR etc. (see motionflows.distributed)
        print(
            f"process {jax.process_index()} of {jax.process_count()}, "
            f"{jax.device_count()} devices in all",
            file=sys.stderr,
        )
    module = runs.resolve_experiment(module)
    config, preset, run_dir = configure(module, args)
    distributed.check_same_config(module.NAME, config)
    print(f"run directory: {run_dir}", file=sys.stderr)
    dataset = config.data.load()
    result = train(
        module,
        config,
        run_dir=run_dir,
        preset=preset,
        resume=args.resume,
        dataset=dataset,
        progress=not args.no_progress,
    )
    if result.status in ("interrupted", "nonfinite"):
        return 130 if result.status == "interrupted" else 1
    if not args.no_eval and _primary():
        evaluate_run(run_dir, "test", dataset=dataset)
    print(f"done: {run_dir}", file=sys.stderr)
    return 0


def report_errors(fn, *args) -> int:
    """Run ``fn(*args)``; user errors become one line on stderr and exit code 2."""
    from motionflows.checkpoints import CheckpointWriteError
    from motionflows.errors import MotionDataError

    try:
        return fn(*args)
    except (RunError, MotionDataError, FileNotFoundError, CheckpointWriteError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except ValueError as err:  # bad config values and shapes, with the fix in the message
        print(f"error: {err}", file=sys.stderr)
        return 2
    except OSError as err:  # a full disk, a file where a folder should be, no permission
        import errno

        where = f" ({err.filename})" if err.filename else ""
        fix = {
            errno.ENOSPC: "free disk space and run the command again (--resume continues)",
            errno.EEXIST: "a file is in the way: choose another path",
            errno.ENOTDIR: "a file is in the way: choose another path",
            errno.EACCES: "no permission: choose a folder you can write to",
        }.get(err.errno, "check the path")
        print(f"error: {err.strerror or err}{where}; {fix}", file=sys.stderr)
        return 2
    except MemoryError:
        print("error: out of memory; use smaller inputs or a smaller batch", file=sys.stderr)
        return 2


def experiment_main(module: Any, argv: list[str] | None = None) -> int:
    """Command line of ``python -m experiments.<name>``; returns the exit code."""
    name = getattr(module, "NAME", "experiment")
    parser = argparse.ArgumentParser(
        prog=f"python -m experiments.{name}",
        description=(module.__doc__ or "").strip().split("\n")[0],
    )
    add_train_arguments(parser)
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:
        return int(exc.code or 0)
    with contextlib.suppress(KeyboardInterrupt):
        return report_errors(run_train, module, args)
    return 130


main = experiment_main
