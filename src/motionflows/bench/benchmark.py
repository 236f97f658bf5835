"""The benchmark's orchestration: one model through train/reuse, likelihood, per-frame NLL,
sampling speed and motion quality; then every model, the plots, GIFs and the report.

One failing part of one model is recorded in the results (``<part>_error``) instead of
aborting the report, unless ``strict``.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import time
import traceback
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from motionflows.bench import plots, report
from motionflows.bench.budgets import (
    BUDGET_NOTES,
    BUDGET_SIZES,
    BUDGETS,
    EVAL_CHUNK,
    bench_config,
    check_overrides,
    load_experiment,
    parse_data_spec,
    parse_models,
)
from motionflows.bench.reuse import (
    data_tag,
    fit_seconds,
    log,
    obtain_run,
    sampling_fields_of,
    train_speed,
)
from motionflows.bench.scoring import (
    MOTION_METRICS,
    data_references,
    foot_locked,
    merge_splits,
    motion_metrics,
    natural_diversity_of,
    per_frame_nll,
    score_likelihood,
)
from motionflows.bench.short_takes import (
    drawing,
    held_control,
    pick_short,
    score_short_takes,
    short_take_spans,
    take_kinds,
)
from motionflows.bench.speed import (
    count_params,
    describe_machine,
    make_sampler,
    sample_in_chunks,
    time_sampler,
)
from motionflows.config import DataConfig, to_dict
from motionflows.errors import RunError
from motionflows.windows import complete_windows, pick, standardized


class _Section:
    """Run one part of a model's benchmark, timing it; record a failure instead of aborting
    (unless ``strict``), so one broken model or metric does not lose the whole report."""

    def __init__(self, entry: dict, key: str, strict: bool, progress):
        self.entry, self.key, self.strict, self.progress = entry, key, strict, progress

    def __enter__(self):
        self.t0, self.c0 = time.perf_counter(), time.process_time()
        return self

    def __exit__(self, kind, err, tb):
        name = self.key.replace("_error", "") if self.key != "error" else "train+likelihood"
        self.entry.setdefault("timings", {})[name] = {
            "wall_s": time.perf_counter() - self.t0,
            "cpu_s": time.process_time() - self.c0,
        }
        if err is None or not isinstance(err, Exception):
            return False
        text = f"{kind.__name__}: {err}"
        self.entry[self.key] = text
        trace = "".join(traceback.format_exception(kind, err, tb))[-2000:]
        log(self.progress, f"FAILED ({self.key}): {text}\n{trace}")
        return not self.strict


@dataclasses.dataclass
class _Loaded:
    """A trained model ready to score: its experiment, run config, data and jitted evaluate."""

    exp: Any
    config: Any
    model: Any
    dataset: Any
    run_dir: Path
    evaluate_fn: Any
    chunk: int


def _obtain(
    name, entry, *, data, budget, sizes, runs_dir, retrain, progress, dataset, overrides,
    training_bars,
):  # fmt: skip
    """Train or reuse the model's run, fill the provenance of ``entry``, load the model."""
    import jax

    from motionflows import training

    exp = load_experiment(name)
    config, prov = bench_config(name, budget, data, exp, overrides)
    entry.update(prov, config=to_dict(config))
    # --set data.tempo & co. (TRAINING_DATA_SETTABLE): this model trains on its own
    # training takes (augmented, or a share of them), and is scored on the bench's frames
    # in its own standardised units
    own_training_data = config.data != data
    c0 = time.process_time()
    run_dir, reused, secs = obtain_run(
        name, exp, config, prov, runs_dir=Path(runs_dir), budget=budget, data_tag=data_tag(data),
        retrain=retrain, progress=progress, dataset=None if own_training_data else dataset,
        training_bars=training_bars,
    )  # fmt: skip
    entry.setdefault("timings", {})["train"] = {"wall_s": secs, "cpu_s": time.process_time() - c0}
    entry.update(run_dir=str(run_dir), reused=reused, train_seconds=secs, steps=config.train.steps)
    # a reused run may differ in the sampling-only fields: load it with the requested ones
    sampling = {f: getattr(config, f) for f in sampling_fields_of(exp)}
    _, run_config, model, dataset = training.load_run(
        run_dir, checkpoint="best", dataset=dataset, sampling=sampling
    )
    if own_training_data:
        from motionflows.run import load_standardizer

        dataset = dataset.with_standardizer(load_standardizer(run_dir))
    entry["params"] = count_params(model)
    if int(run_config.train.steps) > 0:
        # placed as the training loop places it (replicated over the data mesh), so the
        # evaluate compiled for its validation is reused (same shapes and shardings)
        from motionflows.sharding import data_mesh, replicate

        model = replicate(model, data_mesh())
    tc = run_config.train
    chunk = min(
        tc.val_batch_size or tc.batch_size or EVAL_CHUNK,
        len(complete_windows(dataset.test)),
        sizes["eval_windows"],
        len(complete_windows(dataset.train)),
        sizes["train_windows"],
    )
    return _Loaded(exp, run_config, model, dataset, run_dir, jax.jit(exp.evaluate), chunk)


def _likelihood(loaded: _Loaded, sizes: dict, key) -> tuple[dict, dict]:
    """(test rows, train rows) of every scope, ``{scope: row}``."""
    import jax

    rows = []
    for i, (split, limit) in enumerate((("test", "eval_windows"), ("train", "train_windows"))):
        rows.append(
            score_likelihood(
                loaded.exp, loaded.model, loaded.config, loaded.dataset, split,
                limit=sizes[limit], key=jax.random.fold_in(key, i + 1),
                num_bootstrap=sizes["bootstrap"], evaluate_fn=loaded.evaluate_fn,
                chunk=loaded.chunk,
            )
        )  # fmt: skip
    return rows[0], rows[1]


def _window_mean(test: dict, log_det_per_frame: float) -> float | None:
    """Mean window log-likelihood (nats, standardised) of the scored test windows."""
    row = test.get("window")
    if row is None:
        return None
    return -(row["nats_per_frame_metres"] + log_det_per_frame) * row["scored_frames_per_window"]


def _samples(loaded: _Loaded, sampler, motion_idx, sizes: dict, key) -> tuple[np.ndarray, ...]:
    """(samples for the motion controls, samples under the first control), metres."""
    import jax

    st = loaded.dataset.standardizer
    _, ctrl = standardized(st, loaded.dataset.test, motion_idx)
    samples = sample_in_chunks(sampler, loaded.model, ctrl, jax.random.fold_in(key, 20))
    one = np.repeat(ctrl[:1], EVAL_CHUNK, axis=0)
    div = sample_in_chunks(sampler, loaded.model, one, jax.random.fold_in(key, 21))
    return (
        np.asarray(st.denormalize_pose(samples), np.float32),
        np.asarray(st.denormalize_pose(div), np.float32)[: sizes["diversity"]],
    )


def bench_model(
    name: str,
    *,
    data: DataConfig,
    budget: str,
    sizes: dict,
    runs_dir: Path,
    temperature: float,
    seed: int,
    retrain: bool,
    strict: bool,
    progress,
    motion_idx: np.ndarray | None = None,
    likelihood_only: bool = False,
    dataset=None,
    overrides: Sequence[str] = (),
    training_bars: bool = True,
    foot_lock: bool = False,
    short: dict | None = None,
) -> dict:
    """Everything the report holds about one model; ``entry["_samples"]`` (metres, not saved
    to JSON) keeps the motion samples for the GIFs. ``foot_lock`` also scores the same
    samples after the foot-lock post-process (``entry["motion_foot_lock"]``). ``short``
    ({"idx", "span"}: the test takes shorter than a window) adds the motion on them
    (``entry["motion_short_takes"]``, with ``foot_lock`` also
    ``entry["motion_short_takes_foot_lock"]``)."""
    import jax

    entry: dict[str, Any] = {}
    key = jax.random.key(seed)
    with _Section(entry, "error", strict, progress):
        loaded = _obtain(
            name, entry, data=data, budget=budget, sizes=sizes, runs_dir=runs_dir,
            retrain=retrain, progress=progress, dataset=dataset, overrides=overrides,
            training_bars=training_bars,
        )  # fmt: skip
        log(progress, f"{name}: likelihood on test and train windows")
        test, train = _likelihood(loaded, sizes, key)
        window = int(np.asarray(loaded.dataset.test.pose).shape[1])
        entry["likelihood"] = merge_splits(test, train)
        for lik in entry["likelihood"].values():
            n = int(lik["test"]["scored_frames_per_window"])
            lik["frames_label"] = f"{n} (frames {window - n + 1}..{window})"
        entry["speed"] = {
            "train_frames_per_s": train_speed(loaded.run_dir),
            "fit_seconds": fit_seconds(loaded.run_dir),
        }
    if "error" in entry or likelihood_only:
        return entry
    with _Section(entry, "per_frame_error", strict, progress):
        log_det = float(loaded.dataset.standardizer.log_det_per_frame)
        entry["per_frame_nll"] = per_frame_nll(
            loaded.exp, loaded.model, loaded.dataset, limit=sizes["eval_windows"],
            key=jax.random.fold_in(key, 3), points=sizes["prefix_points"],
            causal=bool(getattr(loaded.exp, "CAUSAL", False)),
            evaluate_fn=loaded.evaluate_fn, chunk=loaded.chunk,
            full_window_mean=_window_mean(test, log_det),
        )  # fmt: skip
    sampler = make_sampler(loaded.exp, temperature)
    with _Section(entry, "speed_error", strict, progress):
        log(progress, f"{name}: sampling speed at batch 1 and {EVAL_CHUNK}")
        _, ctrl = standardized(loaded.dataset.standardizer, loaded.dataset.test, motion_idx)
        for b in (1, EVAL_CHUNK):
            sp = time_sampler(
                sampler, loaded.model, ctrl, b, jax.random.fold_in(key, 10 + b),
                sizes["speed_repeats"],
            )  # fmt: skip
            entry["speed"][f"sample_frames_per_s_b{b}"] = sp["frames_per_s"]
            entry["speed"][f"compile_s_b{b}"] = sp["compile_s"]
    with _Section(entry, "motion_error", strict, progress):
        log(progress, f"{name}: samples for {len(motion_idx)} test controls, motion metrics")
        samples_m, div_m = _samples(loaded, sampler, motion_idx, sizes, key)
        gt_m = np.asarray(loaded.dataset.test.pose, np.float32)[motion_idx]
        control_m = np.asarray(loaded.dataset.test.control, np.float32)[motion_idx]
        entry["motion"] = motion_metrics(samples_m, control_m, gt_m, div_m, float(data.fps))
        entry["_samples"] = samples_m
        if foot_lock:
            log(progress, f"{name}: the same samples after the foot lock, motion metrics")
            div_control = np.repeat(control_m[:1], len(div_m), axis=0)
            entry["motion_foot_lock"] = motion_metrics(
                foot_locked(samples_m, control_m), control_m, gt_m,
                foot_locked(div_m, div_control), float(data.fps),
            )  # fmt: skip
    if short is not None:
        with _Section(entry, "motion_short_takes_error", strict, progress):
            log(progress, f"{name}: samples for {len(short['idx'])} short test takes")
            test, st = loaded.dataset.test, loaded.dataset.standardizer
            sample = drawing(sampler, loaded.model, st, jax.random.fold_in(key, 30))
            drawn_m = np.asarray(sample(held_control(test, short["idx"])), np.float32)
            score = functools.partial(
                score_short_takes, test, short["idx"], short["span"], float(data.fps)
            )
            entry["motion_short_takes"] = score(sample=lambda control_m: drawn_m)
            if foot_lock:  # the same draws after the foot lock
                entry["motion_short_takes_foot_lock"] = score(
                    sample=lambda control_m: foot_locked(drawn_m, control_m)
                )
    return entry


def render_gif(sample_m, reference_m, control_m, path: Path, fps: float, title: str) -> None:
    """One GIF: the model's sample beside the ground truth (a second panel, same camera) for
    the same test control, both moved along the trajectory integrated from that control."""
    from motionflows import render

    render.animate(sample_m, control_m, path, fps=fps, title=title, compare=reference_m)


def command_line(data: str, models: Sequence[str], budget: str, out: str, extra: str = "") -> str:
    """The ``motionflows bench`` command that reproduces a report."""
    return (
        f"motionflows bench --data {data} --models {','.join(models)} --budget {budget} "
        f"--out {out}{extra}"
    )


def jsonable(obj: Any) -> Any:
    """Recursively turn numpy / JAX values into JSON types (NaN/inf -> None)."""
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [jsonable(v) for v in obj]
    if isinstance(obj, str | bool) or obj is None:
        return obj
    if isinstance(obj, int | np.integer):
        return int(obj)
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return jsonable(dataclasses.asdict(obj))
    arr = np.asarray(obj)
    if arr.dtype.kind not in "fciub":
        return str(obj)
    if arr.ndim:
        return [jsonable(v) for v in arr.tolist()]
    if arr.dtype.kind in "iub":
        return int(arr)
    v = float(arr)
    return v if math.isfinite(v) else None


def _dataset_info(dataset) -> dict:
    info = dict(getattr(dataset, "info", {}) or {})
    for split in ("train", "val", "test"):
        ws = dataset.split(split)
        info[f"windows_{split}"] = int(len(ws.pose))
        info[f"complete_windows_{split}"] = int(len(complete_windows(ws)))
    return jsonable(info)


def _test_data(dataset, data_cfg: DataConfig, test_data: str | None, progress):
    """(dataset, test-data note): the dataset with its test split swapped for the takes of
    ``test_data`` when given."""
    if not test_data:
        return dataset, {"spec": None, "note": "the test split of --data"}
    from motionflows.data.takes import load_takes

    takes = load_takes(
        test_data, fps=float(data_cfg.fps), window=int(data_cfg.window), hop=int(data_cfg.hop),
        skeleton=data_cfg.skeleton, root_sigma_s=data_cfg.root_sigma_s,
    )  # fmt: skip
    log(progress, f"test data: {len(takes.windows)} windows of {test_data}")
    names = sorted(set(np.asarray(takes.windows.take).tolist()))
    seen = {str(t) for split in ("train", "val") for t in np.asarray(dataset.split(split).take)}
    shared = [name for name in names if str(name) in seen]
    note = f"every complete window of the takes of {test_data} (not the test split)"
    if shared:
        which = f"{len(shared)} of its {len(names)} takes are also training or validation takes "
        which += f"of --data (e.g. {', '.join(map(str, shared[:3]))})"
        note += f"; {which}: not held out"
        warnings.warn(
            f"--test-data {test_data}: {which}, so their scores are not held out; give takes "
            "the models never saw",
            stacklevel=2,
        )
    return dataset.with_test(takes.windows, test_data=str(test_data)), {
        "spec": str(test_data),
        "label": takes.label,
        "takes": names,
        "shared_with_training": shared,
        "skipped": takes.skipped,
        "windows": len(takes.windows),
        "note": note,
    }


def _performer_split(names, data_cfg, budget, sizes, runs_dir, options, progress) -> dict:
    """Retrain every model on a split by performer and score train/test likelihood."""
    data_p = dataclasses.replace(data_cfg, split_by="performer")
    split: dict[str, Any] = {"config": to_dict(data_p), "models": {}}
    try:
        ds = data_p.load()
        split["info"] = info = _dataset_info(ds)
        performers = info.get("performers") or {}
        split["train"] = ", ".join(performers.get("train", [])) or "?"
        split["test"] = ", ".join(performers.get("test", [])) or "?"
    except Exception as err:  # noqa: BLE001
        if options["strict"]:
            raise
        return {"skipped": f"the data do not allow a split by performer ({err})"}
    for name in names:
        log(progress, f"== {name} (split by performer)")
        split["models"][name] = bench_model(
            name, data=data_p, budget=budget, sizes=sizes, runs_dir=runs_dir, progress=progress,
            likelihood_only=True, dataset=ds, **options,
        )  # fmt: skip
    return split


def _check(budget: str, temperature: Any) -> None:
    if budget not in BUDGETS:
        raise RunError(f"--budget {budget!r}: choose from {list(BUDGETS)}")
    if not (
        isinstance(temperature, int | float) and math.isfinite(temperature) and temperature >= 0
    ):
        raise ValueError(f"--temperature must be a finite number >= 0, got {temperature!r}")


def _results_head(command, data, data_cfg, dataset, test_info, budget, sizes, names, **kw):
    """The results dict before any model: provenance, data, machine, sizes."""
    return {
        "command": command,
        "created": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "budget": budget,
        "budget_note": BUDGET_NOTES[budget],
        "data": {"spec": data, "config": to_dict(data_cfg), "info": _dataset_info(dataset)},
        "test_data": test_info,
        "window": int(np.asarray(dataset.test.pose).shape[1]),
        "temperature": float(kw["temperature"]),
        "seed": int(kw["seed"]),
        "bootstrap": sizes["bootstrap"],
        "motion_windows": kw["motion_windows"],
        "diversity_samples": sizes["diversity"],
        "train_windows_note": (
            f"at most {sizes['train_windows']} training windows (a fixed random subset; "
            "mirrored copies included where the pipeline augments)"
        ),
        "machine": describe_machine(),
        "model_order": list(names),
        "models": {},
    }


def _figures(results: dict, samples: dict, out: Path, gt_m, control_m, *, fps, sizes, gifs,
             strict, progress) -> dict:  # fmt: skip
    """Write the plots and (``gifs``) one GIF per model, and for a model scored with
    ``foot_lock`` a second of the same sample after the foot lock; the ``plots`` entry."""
    figures: dict[str, Any] = {}
    if plots.plot_per_frame_nll(results, out / "nll_per_frame.png"):
        figures["per_frame_nll"] = "nll_per_frame.png"
    if plots.plot_metric_bars(results, out / "motion_metrics.png"):
        figures["metrics"] = "motion_metrics.png"
    if not (gifs and samples):
        return figures
    (out / "gifs").mkdir(exist_ok=True)
    figures["gifs"] = {}
    n = min(sizes["gif_frames"], gt_m.shape[1])
    for name, s in samples.items():
        with _Section(results["models"][name], "gif_error", strict, progress):
            title = f"{name} sample (T={results['temperature']:g}), beside the ground truth"
            render_gif(s[0, :n], gt_m[0, :n], control_m[0, :n], out / "gifs" / f"{name}.gif",
                       fps, title)  # fmt: skip
            figures["gifs"][name] = f"gifs/{name}.gif"
            if results["models"][name].get("motion_foot_lock"):
                locked = foot_locked(s[:1], control_m[:1])[0, :n]  # as the scored samples
                path = out / "gifs" / f"{name}_foot-lock.gif"
                render_gif(locked, gt_m[0, :n], control_m[0, :n], path, fps, f"{title}, foot lock")
                figures["gifs"][f"{name} + foot lock"] = f"gifs/{name}_foot-lock.gif"
    return figures


def run_benchmark(
    data: str = "synthetic",
    models: str | Sequence[str] | None = None,
    budget: str = "smoke",
    out: str | Path = "runs/bench",
    runs_dir: str | Path = "runs",
    *,
    temperature: float = 1.0,
    seed: int = 0,
    performer_split: bool | None = None,
    retrain: bool = False,
    gifs: bool = True,
    strict: bool = False,
    command: str | None = None,
    progress=print,
    test_data: str | None = None,
    overrides: Sequence[str] = (),
    training_bars: bool = True,
    foot_lock: bool = False,
) -> dict:
    """Train (or reuse) every model on one data configuration, score, sample, time and report.

    Writes ``out/BENCHMARK.md``, ``out/results.json``, ``out/nll_per_frame.png``,
    ``out/motion_metrics.png`` and ``out/gifs/<model>.gif``; returns the results dict (the
    content of ``results.json``). ``models``: names or a comma-separated string (default:
    every registered model). ``performer_split`` (default: on for Bandai data) also trains
    every model on a split by performer and reports its train/test NLL. ``strict`` raises on
    the first failure instead of recording it in the report. ``test_data`` (``bvh:DIR``,
    ``bandai:DIR``, a folder) replaces the test split: every table is computed on the
    complete windows of those takes (cut at the bench's fps, window and hop, standardised
    with the training standardiser). ``overrides``: ``key=value`` config changes (``--set``,
    e.g. ``train.seed=1``) applied to every model whose config has the key.
    ``training_bars=False`` trains without progress bars (``--no-progress``); the
    time-stamped ``progress`` lines stay. ``foot_lock`` (``--foot-lock``) adds, under each
    model's motion row, the same samples scored after the foot-lock post-process
    (:func:`motionflows.foot_lock.foot_lock`), labelled as such.
    """
    wall0 = time.perf_counter()
    _check(budget, temperature)
    names = parse_models(models)
    data_cfg = parse_data_spec(data, budget)
    check_overrides(names, budget, data_cfg, overrides)
    sizes = BUDGET_SIZES[budget]
    out, runs_dir = Path(out), Path(runs_dir)
    out.mkdir(parents=True, exist_ok=True)
    log(progress, f"loading {data} data ({data_cfg.source}, window {data_cfg.window})")
    dataset, test_info = _test_data(data_cfg.load(), data_cfg, test_data, progress)
    if len(complete_windows(dataset.test)) < 2:
        raise RunError(
            f"--data {data}: the test split has fewer than 2 complete windows; "
            "use more takes or a shorter window"
        )
    motion_idx = pick(dataset.test, sizes["motion_windows"], seed=2)
    gt_m = np.asarray(dataset.test.pose, np.float32)[motion_idx]
    control_m = np.asarray(dataset.test.control, np.float32)[motion_idx]
    results = _results_head(
        command or command_line(data, names, budget, str(out)), data, data_cfg, dataset,
        test_info, budget, sizes, names, temperature=temperature, seed=seed,
        motion_windows=len(motion_idx),
    )  # fmt: skip
    with _Section(results, "ground_truth_error", strict, progress):
        gt = motion_metrics(gt_m, control_m, gt_m, None, float(data_cfg.fps))
        gt["diversity"] = natural_diversity_of(dataset.test)
        results["ground_truth"] = {"motion": gt}
    results.setdefault("ground_truth", {"motion": None})
    short = _short_takes(results, dataset, sizes, float(data_cfg.fps), strict, progress)
    with _Section(results, "references_error", strict, progress):
        results["references"] = data_references(dataset.train, gt_m, control_m, float(data_cfg.fps))
    results.update(motion_metrics=dict(MOTION_METRICS), motion_note=report.MOTION_NOTE)
    options = dict(
        temperature=temperature, seed=seed, retrain=retrain, strict=strict, overrides=overrides,
        training_bars=training_bars, foot_lock=foot_lock,
    )  # fmt: skip
    samples = {}
    for name in names:
        log(progress, f"== {name}")
        t0 = time.perf_counter()
        entry = bench_model(
            name, data=data_cfg, budget=budget, sizes=sizes, runs_dir=runs_dir,
            progress=progress, motion_idx=motion_idx, dataset=dataset, short=short, **options,
        )  # fmt: skip
        if "_samples" in entry:
            samples[name] = entry.pop("_samples")
        entry["bench_seconds"] = time.perf_counter() - t0
        results["models"][name] = entry
    if performer_split is None:  # (the cpu budget's main split already is by performer)
        performer_split = data_cfg.source == "bandai" and data_cfg.split_by == "take"
    if performer_split:
        results["performer_split"] = _performer_split(
            names, data_cfg, budget, sizes, runs_dir, options, progress
        )
    return _write(results, samples, out, gt_m, control_m, fps=float(data_cfg.fps), sizes=sizes,
                  gifs=gifs, strict=strict, progress=progress, wall0=wall0)  # fmt: skip


def _short_takes(results: dict, dataset, sizes: dict, fps: float, strict, progress):
    """The short test takes the models also sample ({"idx", "span"}), or None when there are
    none; ``results["short_takes"]`` describes them and the ground truth's motion on them is
    ``results["ground_truth"]["motion_short_takes"]``."""
    span = short_take_spans(int(np.asarray(dataset.test.pose).shape[1]), sizes)
    idx = pick_short(dataset.test, span[1], sizes["motion_windows"]) if span else []
    if len(idx) == 0:
        return None
    results["short_takes"] = {
        "windows": len(idx),
        "frames": list(span),
        "kinds": take_kinds(dataset.test, idx),
    }
    with _Section(results, "short_takes_error", strict, progress):
        results["ground_truth"]["motion_short_takes"] = score_short_takes(
            dataset.test, idx, span, fps
        )
    return {"idx": idx, "span": span}


def _write(results, samples, out: Path, gt_m, control_m, *, wall0, progress, **figure_args):
    """Plots, GIFs, ``results.json`` and ``BENCHMARK.md``; the JSON-able results."""
    results["per_frame_notes"] = {
        name: pf["method"]
        for name, entry in results["models"].items()
        if (pf := entry.get("per_frame_nll")) and not pf.get("available")
    }
    results["plots"] = _figures(
        results, samples, out, gt_m, control_m, progress=progress, **figure_args
    )
    results["wall_seconds"] = time.perf_counter() - wall0
    results = jsonable(results)
    (out / "results.json").write_text(json.dumps(results, indent=2) + "\n")
    report.write_markdown(results, out / "BENCHMARK.md")
    log(
        progress,
        f"wrote {out / 'BENCHMARK.md'} and {out / 'results.json'} "
        f"in {results['wall_seconds']:.0f} s",
    )
    return results
