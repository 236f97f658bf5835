"""A run directory after training: rebuild it, score it, sample it.

``load_run(run_dir)`` rebuilds ``(module, config, model, dataset)`` from ``config.json``,
``standardizer.json`` and the orbax checkpoints alone; ``evaluate_run`` writes the
likelihood table of a split or of other takes (``eval_<split>.json``); ``draw_samples``
turns a control in data units into pose samples in metres. A run's random streams are
:func:`run_keys` of its seed (the trainer uses the same ones).
"""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path
from typing import Any

import jax
import numpy as np
from flax import nnx

from motionflows import config as cfg
from motionflows import runs
from motionflows.checkpoints import Checkpointer
from motionflows.compile_cache import jitted_evaluate
from motionflows.data import Standardizer
from motionflows.data.datasets import SPLITS
from motionflows.errors import RunError
from motionflows.evaluation import likelihood
from motionflows.windows import split_windows


def run_keys(seed: int) -> dict[str, jax.Array]:
    """The run's independent random streams: ``build`` (parameters), ``init``
    (data-dependent init), ``train`` (step ``i`` uses ``fold_in(train, i)``), ``eval``."""
    names = ("build", "init", "train", "eval")
    return dict(zip(names, jax.random.split(jax.random.key(seed), len(names)), strict=True))


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
    return Standardizer.from_dict(d)


def standardizer_changes(run_dir: str | Path, standardizer) -> list[str]:
    """The fields of ``standardizer`` (fitted on data loaded now) that differ from the
    run's ``standardizer.json`` beyond a float32 round trip: not empty when the data
    changed since the run trained (takes added to or removed from its folder, another
    source). A missing or damaged file raises ``RunError`` (:func:`load_standardizer`)."""
    saved = load_standardizer(run_dir).to_dict()
    now = standardizer.to_dict()
    return [
        key
        for key, value in saved.items()
        if not np.allclose(np.asarray(now[key], np.float32), value, rtol=1e-5, atol=1e-7)
    ]


def load_run(
    run_dir: str | Path,
    *,
    checkpoint: str = "best",
    dataset: Any = None,
    load_data: bool = True,
    sampling: dict | None = None,
):
    """Rebuild ``(module, config, model, dataset)`` from a run directory alone.

    ``checkpoint``: "best" (falls back to "latest" if no best exists) or "latest".
    ``dataset``: reuse an already loaded dataset; ``load_data=False`` returns None.
    ``sampling``: values for the experiment's ``SAMPLING_FIELDS`` (see :func:`restore_run`).
    """
    module, config, model, _ = restore_run(run_dir, checkpoint=checkpoint, sampling=sampling)
    if dataset is None and load_data:
        dataset = config.data.load()
    return module, config, model, dataset


def restore_run(run_dir: str | Path, *, checkpoint: str = "best", sampling: dict | None = None):
    """``(module, config, model, saved)``: the run's model with the parameters of its
    ``checkpoint`` ("best", falling back to "latest"; or "latest"), restored once.
    ``saved`` = ``{"which": the checkpoint read, "meta": its metadata}`` (``meta["step"]``
    is the step of the newest complete checkpoint, the one restored).

    ``sampling``: ``{field: value}`` for fields in the experiment's ``SAMPLING_FIELDS``
    (e.g. the VAE-LSTM's ``sampler``), which change how the trained model samples, not its
    parameters: the model is built with them in place of the saved values. Any other field
    is a ``RunError`` (it would not match the checkpoint)."""
    run_dir = runs.check_run_dir(run_dir)
    payload = cfg.read_config_json(run_dir / "config.json")
    module = runs.resolve_experiment(payload["experiment"])
    config = cfg.config_from_json(run_dir / "config.json", module.Config, payload)
    if sampling:
        allowed = tuple(getattr(module, "SAMPLING_FIELDS", ()))
        bad = sorted(set(sampling) - set(allowed))
        if bad:
            raise RunError(
                f"{bad} cannot be changed when loading {run_dir}: only the experiment's "
                f"SAMPLING_FIELDS {list(allowed)} can (other fields need a new training)"
            )
        config = dataclasses.replace(config, **sampling)
    model = module.build(config, key=run_keys(config.train.seed)["build"])
    graphdef, params, rest = nnx.split(model, nnx.Param, ...)
    ckpt = Checkpointer(run_dir / "checkpoints", keep=config.train.keep_checkpoints)
    try:
        which = checkpoint
        if which == "best" and ckpt.latest_step("best") is None:
            which = "latest"
        if ckpt.latest_step(which) is None:
            raise RunError(f"{run_dir} has no checkpoint yet (train it first)")
        state, meta = ckpt.restore({"params": params, "rest": rest}, which=which)
    finally:
        ckpt.close()
    model = nnx.merge(graphdef, state["params"], state["rest"])
    return module, config, model, {"which": which, "meta": meta}


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
    module, config, model, saved = restore_run(run_dir, checkpoint=checkpoint)
    if data is None:
        dataset = config.data.load() if dataset is None else dataset
        bs = batch_size or config.train.val_batch_size or config.train.batch_size
        pose, control = split_windows(
            dataset, split, batch_size=bs, fallback_batches=config.train.eval_batches
        )
        ldpf = float(dataset.standardizer.log_det_per_frame)
        name, what, extra = split, f"{split} split", {}
    else:
        bs = batch_size or config.train.val_batch_size or config.train.batch_size
        std = load_standardizer(run_dir)
        pose, control, name, what, extra = _takes(std, config, data, label, skeleton)
        ldpf = float(std.log_det_per_frame)
    lls = likelihood.evaluate_windows(
        module, model, pose, control, batch_size=bs, key=run_keys(config.train.seed)["eval"],
        evaluate_fn=jitted_evaluate(module),
    )  # fmt: skip
    window = pose.shape[1]
    frames = {k: likelihood.scored_frames(module.SCOPES, k, window, config) for k in lls}
    rows = likelihood.likelihood_rows(lls, frames, ldpf, scopes=module.SCOPES)
    out_dir = Path(run_dir if out_dir is None else out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    likelihood.write_eval(
        out_dir / f"eval_{name}.json", rows, split=split if data is None else name,
        experiment=module.NAME, window=window, log_det_per_frame=ldpf,
        checkpoint=saved["which"], step=int(saved["meta"]["step"]), **extra,
    )  # fmt: skip
    if print_table:
        title = f"{module.NAME} — {what}, {pose.shape[0]} windows of {window} frames"
        print(likelihood.format_table(rows, title=f"{title} ({Path(run_dir)})"))
    return rows


def _takes(std, config, data: str, label: str | None, skeleton: str):
    """(pose, control, output name, description, JSON extras) of the windows of the takes
    of ``data``, cut as the run's windows and standardised with the run's standardiser."""
    from motionflows.data.takes import load_takes

    takes = load_takes(
        data, fps=float(config.data.fps), window=int(config.data.window),
        hop=int(config.data.hop), skeleton=skeleton, root_sigma_s=config.data.root_sigma_s,
    )  # fmt: skip
    pose = np.asarray(std.normalize_pose(takes.windows.pose), np.float32)
    control = np.asarray(std.normalize_control(takes.windows.control), np.float32)
    used = sorted(set(np.asarray(takes.windows.take).tolist()))
    for item in takes.skipped:
        print(f"skipped take {item}: shorter than one window", file=sys.stderr)
    extra = {"data": str(data), "takes": used, "skipped": takes.skipped}
    return pose, control, data_label(label or takes.label), f"{len(used)} takes of {data}", extra


def data_label(text: str) -> str:
    """The ``eval_<label>.json`` label of other takes: ``text`` made safe as part of a file
    name (letters, digits, ``-``, ``_``, ``.``), and prefixed ``takes_`` when it is a split's
    name, so that scoring a folder called ``test`` never overwrites the test split's table.

    >>> data_label("D2 C/"), data_label("test")
    ('D2_C', 'takes_test')
    """
    out = "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in str(text)).strip("._")
    out = out or "data"
    return f"takes_{out}" if out in SPLITS else out


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
    def draw(model, key, control):
        return runs.experiment_sample(module, model, key, control, temperature=temperature)

    pose_std = np.asarray(draw(model, jax.random.key(seed), c_std))
    if not np.all(np.isfinite(pose_std)):
        raise RunError("the sampled poses hold NaN/inf; try a lower temperature")
    return np.asarray(standardizer.denormalize_pose(pose_std), np.float32)
