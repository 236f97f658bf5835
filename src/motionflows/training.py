"""The one training loop of motionflows, shared by every experiment module.

``train(module, config, run_dir=...)`` builds the model (``module.build``), optionally
initialises it from the first batch (``module.initialize``), then runs one jitted train
step per batch (:func:`motionflows.optim.make_train_step`: value and gradient of
``module.loss`` over the ``nnx.Param`` leaves, clipping, Adam(W), NaN/inf steps skipped
inside the step and counted). With ``train.ema_decay`` the optimiser also keeps a running
average of the parameters (:func:`motionflows.optim.parameter_average`), which validation,
the returned model and the checkpoints' ``params`` use (the iterate is saved beside it as
``train_params`` for ``resume``).

Determinism: the batch of step ``i`` is ``dataset.batch("train", B, seed=train.seed,
index=i)`` and its key ``fold_in(train_key, i)`` (:func:`motionflows.run.run_keys`), so a
resumed run reproduces the loss curve of an uninterrupted one. Modules defining
``fit(model, dataset[, config=...])`` (the closed-form baselines) are fitted instead.

Bookkeeping (see ``motionflows.runs``): ``config.json``, ``standardizer.json``,
``metrics.jsonl`` (loss, grad_norm, lr, steps_per_s, frames_per_s, skipped; val_nll in
nats/frame in metres, val_bits in bits/frame standardised, val_seconds), ``loss.png``, orbax
checkpoints (``motionflows.checkpoints``: latest N plus best by validation), a progress
bar with ETA on stderr. Ctrl-C (SIGINT) finishes the current step, writes a checkpoint and
returns; ``resume=True`` continues from the latest checkpoint.

A finished run is loaded, scored and sampled by :mod:`motionflows.run`; the command lines
(``motionflows train``, ``python -m experiments.<name>``) are :mod:`motionflows.cli_train`.
Their names stay importable from here.
"""

from __future__ import annotations

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
from flax import nnx

from motionflows import config as cfg
from motionflows import distributed, runs
from motionflows.checkpoints import Checkpointer, CheckpointReadError
from motionflows.compile_cache import cached, jitted_evaluate
from motionflows.errors import RunError
from motionflows.evaluation import likelihood
from motionflows.optim import (
    averaged_parameters,
    gradient_clipping,
    init_guard,
    learning_rate_schedule,
    make_optimizer,
    make_train_step,
    noam_schedule,
)
from motionflows.run import (
    draw_samples,
    evaluate_run,
    load_run,
    load_standardizer,
    run_keys,
    standardizer_changes,
)
from motionflows.sharding import check_batch_size, data_mesh, replicate, shard_batch
from motionflows.windows import split_windows, subset

__all__ = [
    "TrainResult",
    "draw_samples",
    "evaluate_run",
    "gradient_clipping",
    "init_guard",
    "jitted_evaluate",
    "learning_rate_schedule",
    "load_run",
    "load_standardizer",
    "make_optimizer",
    "make_train_step",
    "noam_schedule",
    "train",
    "validate",
    "validation_windows",
]

warnings.filterwarnings("ignore", message="Some donated buffers were not usable")

_CLI_NAMES = ("add_train_arguments", "configure", "experiment_main", "report_errors", "run_train")


def __getattr__(name: str):
    # the command line lives in motionflows.cli_train (it imports this module)
    if name in _CLI_NAMES or name == "main":
        from motionflows import cli_train

        return getattr(cli_train, "experiment_main" if name == "main" else name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


@dataclasses.dataclass
class TrainResult:
    """What :func:`train` returns. ``status``: finished | fitted | interrupted | nonfinite."""

    model: Any
    run_dir: Path
    step: int
    status: str
    best_val_nll: float | None = None
    last_metrics: dict = dataclasses.field(default_factory=dict)


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
    pose, control = split_windows(dataset, split, batch_size=bs, fallback_batches=tc.eval_batches)
    idx = subset(len(pose), limit, seed=0)
    return pose[idx], control[idx]


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
    config = cfg.resolve_compute_dtype(config)  # config.json names the precision used
    run_dir = Path(run_dir)
    tc = config.train
    ckdir = run_dir / "checkpoints"
    if not resume and ckdir.is_dir() and any(ckdir.glob("*/*")):
        raise RunError(
            f"{run_dir} already holds checkpoints: pass --resume to continue it, or choose "
            "another --run-name"
        )
    check_steps(module, config, use_fit=use_fit)
    if resume and not (run_dir / "config.json").is_file():
        raise RunError(f"cannot resume {run_dir}: it is not a run directory (no config.json)")
    dataset = config.data.load() if dataset is None else dataset
    # a resumed run keeps the device counts of its earlier segments: one trained partly on
    # another count is another training (the bench reuses a run only on its own count)
    earlier: Any = ()
    if resume:
        saved = cfg.read_config_json(run_dir / "config.json")
        _check_same_standardizer(run_dir, dataset.standardizer)
        _check_same_training(run_dir, saved, tc)
        earlier = cfg.saved_device_counts(saved)
    mesh = data_mesh() if mesh is None else mesh

    def write_run_files() -> None:
        if not _primary():  # the other processes of a multi-process run write nothing here
            return
        cfg.save_config(
            run_dir / "config.json",
            experiment=module.NAME,
            preset=preset,
            config=config,
            devices=mesh.size,  # of its latest segment
            device_counts=earlier,
        )
        payload = json.dumps(dataset.standardizer.to_dict(), indent=2) + "\n"
        (run_dir / "standardizer.json").write_text(payload)

    if _primary():
        for sub in ("checkpoints", "samples"):
            (run_dir / sub).mkdir(parents=True, exist_ok=True)
    fitted = use_fit and hasattr(module, "fit")
    if not resume:  # a resume writes them once its model exists: a failure leaves the run
        write_run_files()
    keys = run_keys(tc.seed)
    model = module.build(config, key=keys["build"])
    ckpt = Checkpointer(ckdir, keep=tc.keep_checkpoints)
    eval_fn = jitted_evaluate(module)
    base_meta = {"seed": tc.seed, "rng": np.asarray(jax.random.key_data(keys["train"])).tolist()}
    try:
        if fitted:  # a closed-form model refits on --resume: its files after the new fit
            after = write_run_files if resume else None
            return _fit(
                module, config, model, dataset, run_dir, ckpt, eval_fn, keys, base_meta, after
            )
        loop = _Loop(module, config, dataset, run_dir, ckpt, eval_fn, keys, base_meta, mesh=mesh)
        loop.start_from(model, resume=resume)
        if resume:  # only now: a config that cannot restore the run leaves its files alone
            write_run_files()
        return loop.run(progress=progress, on_step=on_step)
    finally:
        ckpt.close()


def check_steps(module, config, *, use_fit: bool = True) -> None:
    """RunError unless a gradient-trained run has ``train.steps >= 1`` (0 trained nothing,
    saved no checkpoint, and its evaluation then failed); a closed-form fit needs none."""
    if config.train.steps < 1 and not (use_fit and hasattr(module, "fit")):
        raise RunError(
            f"train.steps must be >= 1 for {module.NAME} (it trains by gradient steps; got "
            f"{config.train.steps}): pass --steps N"
        )


def _fit(module, config, model, dataset, run_dir, ckpt, eval_fn, keys, base_meta, on_fitted=None):
    """The closed-form fit, its validation and checkpoint; ``on_fitted()`` (a refit's run
    files) is called once the fit and its validation have succeeded."""
    t0 = time.perf_counter()
    kwargs = {"config": config} if "config" in inspect.signature(module.fit).parameters else {}
    model = module.fit(model, dataset, **kwargs)
    seconds = time.perf_counter() - t0
    val = validate(module, config, model, dataset, key=keys["eval"], evaluate_fn=eval_fn)
    if on_fitted is not None:
        on_fitted()
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


def _check_same_training(run_dir: Path, payload: dict, tc: cfg.TrainConfig) -> None:
    """RunError if a resume changes ``train.seed`` (the batches and keys of every step) or
    turns ``train.ema_decay`` on or off: the checkpoints' ``params`` are the average in a
    run with it and the iterate in one without (another decay is fine: the same state).
    ``payload``: the run's ``config.json`` (:func:`motionflows.config.read_config_json`)."""
    saved = payload["config"].get("train", {})
    if "seed" in saved and saved["seed"] != tc.seed:
        raise RunError(
            f"{run_dir} was trained with train.seed={saved['seed']} and cannot resume with "
            f"{tc.seed}: the seed picks every batch and random key, so the run would be "
            "neither seed's; resume without changing train.seed, or start a new run"
        )
    before = saved.get("ema_decay")
    if (before is None) != (tc.ema_decay is None):
        raise RunError(
            f"{run_dir} was trained with train.ema_decay={before} and cannot resume with "
            f"{tc.ema_decay}: its checkpoints hold "
            f"{'no' if before is None else 'a'} parameter average; resume without changing "
            "train.ema_decay, or start a new run"
        )


def _check_same_standardizer(run_dir: Path, standardizer) -> None:
    """RunError if ``run_dir``'s saved ``standardizer.json`` differs from ``standardizer``
    (fitted on the data now loaded): the checkpoints are in the saved one's units, so the
    data changed since the run started (takes added, another ``--data``)."""
    if not (run_dir / "standardizer.json").is_file():
        return
    changed = standardizer_changes(run_dir, standardizer)
    if changed:
        raise RunError(
            f"cannot resume {run_dir}: its training data changed since it started (the "
            f"standardizer fitted on the data now differs in {', '.join(changed)} from its "
            "standardizer.json); resume with the data it trained on, or start a new run"
        )


class _Loop:
    """One gradient-trained run between steps: the split model (``params``, ``rest``), the
    optimiser state, the non-finite guard, the best validation NLL, and the step outputs
    not logged yet (logged in one host sync every ``train.log_every`` steps)."""

    def __init__(self, module, config, dataset, run_dir, ckpt, eval_fn, keys, base_meta, *, mesh):
        self.module, self.config, self.dataset, self.run_dir = module, config, dataset, run_dir
        self.ckpt, self.eval_fn, self.keys, self.base_meta = ckpt, eval_fn, keys, base_meta
        self.tc = tc = config.train
        self.mesh = mesh
        check_batch_size(tc.batch_size, self.mesh)
        self.schedule = learning_rate_schedule(tc)
        self.optimizer = make_optimizer(tc, self.schedule)
        self.start, self.best, self.guard = 0, None, init_guard()
        self.pending: list = []
        self.last_row: dict = {}
        self.frames = 0  # pose frames per batch

    def start_from(self, model, *, resume: bool) -> None:
        """Restore the latest checkpoint (``resume``) or initialise ``model``; place the
        state on the mesh and get the (cached) jitted step."""
        tc, run_dir = self.tc, self.run_dir
        if resume and self.ckpt.latest_step() is not None:
            graphdef, params, rest = nnx.split(model, nnx.Param, ...)
            templates = {"params": params, "rest": rest, "opt": self.optimizer.init(params)}
            if tc.ema_decay is not None:  # "params" holds the average; the iterate is apart
                templates["train_params"] = params
            try:
                state, meta = self.ckpt.restore(templates, which="latest")
            except CheckpointReadError:
                raise
            except ValueError as err:
                raise RunError(
                    f"cannot resume {run_dir} with this config: {err}; resume with the "
                    "settings it was trained with (drop the --set or --preset that changes "
                    "the model), or start a new run"
                ) from None
            params = state["train_params" if tc.ema_decay is not None else "params"]
            rest, opt_state = state["rest"], state["opt"]
            self.start, self.best = int(meta["step"]), meta.get("best_val_nll")
            if self.ckpt.drop_after(self.start, "best"):  # validated on another trajectory
                self.best = None  # the next validation saves the best again
            self.ckpt.drop_after(self.start, "latest")  # damaged steps restore skipped
            skipped = jnp.asarray(meta.get("skipped", 0), jnp.int32)
            self.guard = {**init_guard(), "skipped": skipped}
            if _primary():
                runs.truncate_metrics(run_dir, self.start)
            print(f"resumed {run_dir} at step {self.start}", file=sys.stderr)
        else:
            if resume:
                print(f"no checkpoint in {run_dir}: starting from step 0", file=sys.stderr)
            if _primary():
                runs.truncate_metrics(run_dir, -1)
            if hasattr(self.module, "initialize"):
                first = self.dataset.batch("train", tc.batch_size, seed=tc.seed, index=0)
                extra = {}
                if "standardizer" in inspect.signature(self.module.initialize).parameters:
                    extra["standardizer"] = self.dataset.standardizer
                model = self.module.initialize(model, first, key=self.keys["init"], **extra)
            graphdef, params, rest = nnx.split(model, nnx.Param, ...)
            opt_state = self.optimizer.init(params)
        # the guard too: a guard off the mesh would make the second step compile again
        state = replicate((params, rest, opt_state, self.guard), self.mesh)
        self.params, self.rest, self.opt_state, self.guard = state
        self.graphdef = graphdef
        self.step_fn = cached(
            ("step", self.module.loss, graphdef, tc),
            lambda: make_train_step(self.module, graphdef, self.optimizer),
        )

    def model_params(self):
        """The parameters the model is used with: the running average of
        ``train.ema_decay`` when it is set (:func:`motionflows.optim.parameter_average`),
        else the training iterate."""
        average = averaged_parameters(self.opt_state)
        return self.params if average is None else average

    def model(self):
        return nnx.merge(self.graphdef, self.model_params(), self.rest)

    def save(self, step: int, which: str = "latest", extra: dict | None = None) -> None:
        meta = {
            **self.base_meta,
            "step": step,
            "data_index": step,
            "best_val_nll": self.best,
            "skipped": int(self.guard["skipped"]),
            **(extra or {}),
        }
        # "params" are the ones to use (sampling, eval, export read only them); with an
        # average, the training iterate goes beside them for --resume
        state = {"params": self.model_params(), "rest": self.rest, "opt": self.opt_state}
        if self.tc.ema_decay is not None:  # as start_from reads it back
            state["train_params"] = self.params
        self.ckpt.save(step, state, meta, which=which)

    def log(self, done: int, bar) -> None:
        """Average the pending step outputs into one metrics row (one host sync)."""
        outs, self.pending = jax.device_get(self.pending), []
        now = time.perf_counter()
        rate = (done - self.step_log) / max(now - self.t_log, 1e-9)
        self.t_log, self.step_log = now, done
        ok = [o for o in outs if bool(o["finite"])]
        row: dict[str, Any] = {"step": done}
        for k in outs[-1]:
            if k != "finite":
                vals = [v for v in (_scalar(o[k]) for o in ok) if isinstance(v, int | float)]
                row[k] = float(np.mean(vals)) if vals else None
        row.update(
            # the lr of the last applied update: a skipped step keeps the optimiser state of
            # the step before, its schedule count with it
            lr=float(self.schedule(max(done - 1 - int(self.guard["skipped"]), 0))),
            steps_per_s=rate,
            frames_per_s=rate * self.frames,
            skipped=int(self.guard["skipped"]),
            nonfinite_run=int(self.guard["consecutive"]),
        )
        self.last_row = row
        if _primary():
            runs.append_metrics(self.run_dir, row)
        loss_txt = f"{row['loss']:.4f}" if row["loss"] is not None else "nan"
        bar.update(done, f"loss {loss_txt} {rate:.2f} it/s")

    def validate(self, done: int, windows) -> None:
        """Validation row at step ``done`` (with ``val_seconds``, the pass's wall time, the
        first one's including compilation); a new best validation NLL is checkpointed."""
        t0 = time.perf_counter()
        val = validate(
            self.module, self.config, self.model(), self.dataset, key=self.keys["eval"],
            evaluate_fn=self.eval_fn, windows=windows,
        )  # fmt: skip
        seconds = time.perf_counter() - t0  # validate returns floats: the pass has finished
        if _primary():
            row = {"step": done, **{k: _scalar(v) for k, v in val.items()}}
            runs.append_metrics(self.run_dir, {**row, "val_seconds": seconds})
            if time.perf_counter() - self.t_plot > 60.0:  # plotting costs ~1 s
                runs.plot_losses(self.run_dir)
                self.t_plot = time.perf_counter()
        if math.isfinite(val["val_nll"]) and (self.best is None or val["val_nll"] < self.best):
            self.best = val["val_nll"]
            self.save(done, "best", val)

    def step(self, step: int) -> dict:
        """Dispatch training step ``step`` (asynchronous: no host sync); its outputs."""
        tc = self.tc
        batch = self.dataset.batch("train", tc.batch_size, seed=tc.seed, index=step)
        self.frames = int(np.prod(np.shape(batch["pose"])[:2]))
        batch = shard_batch(batch, self.mesh)
        distributed.trace_local_rows(step, batch)
        key = jax.random.fold_in(self.keys["train"], step)
        self.params, self.opt_state, self.guard, out = self.step_fn(
            self.params, self.rest, self.opt_state, self.guard, batch, key
        )
        self.pending.append(out)
        return out

    def run(self, *, progress: bool, on_step) -> TrainResult:
        """Steps ``start .. train.steps`` with logging, validation and checkpoints."""
        tc = self.tc
        val_windows = validation_windows(self.config, self.dataset)
        bar = runs.Progress(tc.steps, self.start, enabled=progress)
        self.t_log, self.step_log = time.perf_counter(), self.start
        self.t_plot = self.t_log
        status, completed = "finished", self.start  # steps whose update is in the state
        with _StopFlag() as stop:
            try:
                for step in range(self.start, tc.steps):
                    if stop.requested:
                        status = "interrupted"
                        break
                    out = self.step(step)
                    completed = done = step + 1
                    if on_step is not None:
                        on_step(step, out)
                    if done % tc.log_every == 0 or done == tc.steps:
                        self.log(done, bar)
                        if int(self.guard["peak"]) >= tc.max_nonfinite:
                            status = "nonfinite"
                            break
                    if done % tc.eval_every == 0 or done == tc.steps:
                        self.validate(done, val_windows)
                    if done % tc.checkpoint_every == 0 or done == tc.steps:
                        self.save(done)
                    if not self.pending:  # steps/s measure training only, not validation
                        self.t_log = time.perf_counter()
            except KeyboardInterrupt:  # a second Ctrl-C, or raised by code called in the loop
                status = "interrupted"
                if self._donated():
                    bar.close()
                    print(
                        "\ninterrupted inside a step: no new checkpoint (the latest is step "
                        f"{self.ckpt.latest_step()})",
                        file=sys.stderr,
                    )
                    raise
        if self.pending:  # outputs of steps not logged yet (an interrupt between log points)
            self.log(completed, bar)
        bar.close()
        return self.finish(completed, status)

    def _donated(self) -> bool:
        """Whether the state was donated to a step that did not return (interrupted inside)."""
        leaves = jax.tree_util.tree_leaves((self.params, self.opt_state))
        return any(getattr(x, "is_deleted", lambda: False)() for x in leaves)

    def finish(self, step: int, status: str) -> TrainResult:
        """Checkpoint an interrupted or non-finite run, write the status row and the plot."""
        tc, guard = self.tc, self.guard
        if status == "interrupted":
            self.save(step)
            print(
                f"\ninterrupted at step {step}: checkpoint saved in "
                f"{self.run_dir / 'checkpoints'}; continue with --resume",
                file=sys.stderr,
            )
        elif status == "nonfinite":
            self.save(step)
            print(
                f"stopped at step {step}: {int(guard['peak'])} consecutive steps had a NaN/inf "
                f"loss or gradient (train.max_nonfinite={tc.max_nonfinite}); they were skipped "
                f"({int(guard['skipped'])} in all) and the last good state is checkpointed. "
                "Try a lower train.lr, train.clip_norm, or check the data.",
                file=sys.stderr,
            )
        if _primary():
            runs.append_metrics(self.run_dir, {"step": step, "status": status})
            runs.plot_losses(self.run_dir)
        return TrainResult(self.model(), self.run_dir, step, status, self.best, self.last_row)
