"""The bench's scores: likelihood tables, NLL by frame position, and motion metrics.

Likelihood: each experiment's ``evaluate`` gives per-window log-likelihoods in nats in
standardised space for the scopes of its ``SCOPES``; ``motionflows.evaluation.likelihood``
turns them into NLL in nats/frame in metres, -(log p_std + F * log_det_per_frame) / F, and
bits/frame standardised, -log p_std / (F * ln 2), with F the scored frames, mean and a
bootstrap 95% interval over windows. Motion metrics come from
``motionflows.evaluation.motion``; diverged samples are counted and left out.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from motionflows.bench.budgets import EVAL_CHUNK
from motionflows.errors import RunError
from motionflows.runs import window_scope_evaluate
from motionflows.windows import complete_windows, pick, standardized, subset

DIVERGED_METRES = 10.0
"""A sample with a coordinate beyond this in its root frame (any joint, any axis, height
included) or a NaN/inf counts as diverged."""

MOTION_METRICS: dict[str, dict[str, str]] = {
    "foot_sliding": {"label": "foot sliding", "unit": "m/s"},
    "skate_ratio": {"label": "skate ratio", "unit": "fraction"},
    "contact_rate": {"label": "foot contact rate", "unit": "fraction"},
    "bone_length_std": {"label": "bone-length std", "unit": "m"},
    "jerk": {"label": "jerk (world)", "unit": "m/s^3"},
    "fd_pose": {"label": "FD poses", "unit": "m^2"},
    "fd_window3": {"label": "FD 3-frame windows", "unit": "m^2"},
    "diversity": {"label": "diversity, one control", "unit": "m"},
    "pose_error": {"label": "pose error", "unit": "m"},
    "motion_error": {"label": "motion error", "unit": "m"},
    "diverged": {"label": "diverged samples", "unit": "fraction"},
}
"""Motion metrics in report order (all from ``motionflows.evaluation.motion``)."""


def evaluate_windows(exp, model, pose, control, *, key, evaluate_fn=None, chunk=EVAL_CHUNK):
    """``{scope: (N,)}`` log-likelihoods (nats, standardised) in padded chunks."""
    from motionflows.evaluation.likelihood import evaluate_windows as evaluate

    return evaluate(exp, model, pose, control, batch_size=chunk, key=key, evaluate_fn=evaluate_fn)


def score_likelihood(
    exp,
    model,
    config,
    dataset,
    split: str,
    *,
    limit: int,
    key,
    num_bootstrap: int,
    evaluate_fn=None,
    chunk: int = EVAL_CHUNK,
) -> dict:
    """Likelihood rows of one split, ``{scope: row}`` (``likelihood_rows``), on at most
    ``limit`` complete windows, for the scopes the experiment declares in ``SCOPES``."""
    from motionflows.evaluation.likelihood import likelihood_rows, scored_frames

    windows = dataset.split(split)
    idx = pick(windows, limit, seed=1)
    if len(idx) == 0:
        raise RunError(
            f"the {split} split has no complete windows; use more data or a shorter window"
        )
    pose, control = standardized(dataset.standardizer, windows, idx)
    lls = evaluate_windows(exp, model, pose, control, key=key, evaluate_fn=evaluate_fn, chunk=chunk)
    scopes = exp.SCOPES
    lls = {k: v for k, v in lls.items() if k in scopes}
    frames = {k: int(scored_frames(scopes, k, pose.shape[1], config)) for k in lls}
    ldpf = float(dataset.standardizer.log_det_per_frame)
    rows = likelihood_rows(lls, frames, ldpf, scopes=scopes, num_bootstrap=num_bootstrap, seed=0)
    return {r["scope"]: r for r in rows}


def merge_splits(test: dict, train: dict) -> dict:
    """``{scope: {description, bound, frames, test: row, train: row}}``."""
    return {
        scope: {
            "description": row.get("description", ""),
            "bound": row.get("bound", False),
            "frames": row.get("scored_frames_per_window"),
            "test": row,
            "train": train.get(scope),
        }
        for scope, row in test.items()
    }


def per_frame_nll(
    exp,
    model,
    dataset,
    *,
    limit: int,
    key,
    points: int,
    causal: bool,
    evaluate_fn=None,
    chunk: int = EVAL_CHUNK,
    full_window_mean: float | None = None,
) -> dict:
    """Test NLL (nats/frame, metres) against the frame position in the window.

    Exact in both routes: the model's own per-frame log-densities (``model.frame_log_prob``,
    the baselines), or, for a causal model (``CAUSAL``: the score of frames 1..t does not
    depend on later frames), differences of whole-window scores of prefixes 1..t:
    log p(x_s..t | x_<s, c) = log p(x_1:t | c_1:t) - log p(x_1:s-1 | c_1:s-1), averaged over
    the frames of each block. A prefix is scored by the experiment's ``window_log_prob``
    when it has one (MoGlow's ``evaluate`` also scores scopes that need more frames), else
    by the ``window`` scope of its ``evaluate``. ``full_window_mean``: the mean window
    log-likelihood of the same windows, already computed. Not available otherwise.
    """
    idx = pick(dataset.test, limit, seed=1)
    pose, control = standardized(dataset.standardizer, dataset.test, idx)
    log_det = float(dataset.standardizer.log_det_per_frame)
    if callable(getattr(model, "frame_log_prob", None)):
        ll = _frame_log_probs(model, pose, control)
        if ll.shape == pose.shape[:2]:
            return {
                "available": True,
                "method": "exact per frame",
                "positions": list(range(pose.shape[1])),
                "nats_per_frame_metres": (-(ll.mean(0) + log_det)).tolist(),
            }
    if not causal:
        return {"available": False, "method": _unavailable(exp)}
    evaluate_fn = window_scope_evaluate(exp) or evaluate_fn

    t_len = pose.shape[1]
    ends = sorted(set(np.linspace(0, t_len, points + 1).round().astype(int).tolist()) - {0})
    totals = [0.0]
    for end in ends:
        if end == t_len and full_window_mean is not None:
            totals.append(float(full_window_mean))  # already scored on these windows
            continue
        lls = evaluate_windows(
            exp, model, pose[:, :end], control[:, :end], key=key, evaluate_fn=evaluate_fn,
            chunk=chunk,
        )  # fmt: skip
        totals.append(float(np.mean(lls["window"])))
    starts = [0] + ends[:-1]
    blocks = list(zip(starts, ends, strict=True))
    return {
        "available": True,
        "method": f"prefix differences, {len(ends)} blocks",
        "positions": [(s + e - 1) / 2 for s, e in blocks],
        "nats_per_frame_metres": [
            -((totals[k + 1] - totals[k]) / (e - s) + log_det) for k, (s, e) in enumerate(blocks)
        ],
    }


def _frame_log_probs(model, pose: np.ndarray, control: np.ndarray) -> np.ndarray:
    """(N, T) ``model.frame_log_prob`` in chunks (a model without control takes pose only)."""
    import inspect

    import jax

    takes_control = len(inspect.signature(model.frame_log_prob).parameters) > 1

    def frames(m, p, c):
        return m.frame_log_prob(p, c) if takes_control else m.frame_log_prob(p)

    fn = jax.jit(frames)
    parts = [
        np.asarray(fn(model, pose[s : s + EVAL_CHUNK], control[s : s + EVAL_CHUNK]), np.float64)
        for s in range(0, len(pose), EVAL_CHUNK)
    ]
    return np.concatenate(parts)


def _unavailable(exp) -> str:
    """Why a non-causal experiment has no per-frame NLL."""
    why = (
        "it gives only bounds"
        if all(s.bound for s in exp.SCOPES.values())
        else "it scores a window jointly"
    )
    return (
        f"not available: {getattr(exp, 'NAME', exp.__name__)} is not causal ({why}), so no "
        "per-frame split of its likelihood is exact"
    )


def diverged(samples_m) -> np.ndarray:
    """(N,) bool: sample n holds NaN/inf or a root-frame coordinate beyond
    :data:`DIVERGED_METRES`."""
    x = np.asarray(samples_m, np.float64).reshape(len(samples_m), -1)
    return ~np.all(np.isfinite(x) & (np.abs(x) <= DIVERGED_METRES), axis=1)


def foot_locked(samples_m, control_m) -> np.ndarray:
    """``samples_m`` (N, T, 63) metres after :func:`motionflows.foot_lock.foot_lock` with
    their controls (N, T, 3); diverged samples (:func:`diverged`) are left as drawn, so
    :func:`motion_metrics` counts them as before. The bench's ``--foot-lock`` rows."""
    from motionflows.foot_lock import foot_lock

    out = np.array(samples_m, np.float32)
    ok = ~diverged(out)
    if ok.any():
        out[ok] = foot_lock(out[ok], np.asarray(control_m, np.float32)[ok])
    return out


def natural_diversity_of(windows, idx=None) -> float | None:
    """The ground-truth row's diversity: :func:`motionflows.evaluation.motion.natural_diversity`
    of every complete window of a split (or of the windows ``idx``), each paired with the
    window of another take whose control is closest (None when the split has fewer than two
    takes)."""
    from motionflows.evaluation import motion as mm

    idx = complete_windows(windows) if idx is None else idx
    takes = getattr(windows, "take", None)
    takes = None if takes is None else np.asarray(takes)[idx]
    try:
        return mm.natural_diversity(
            np.asarray(windows.pose)[idx], np.asarray(windows.control)[idx], takes=takes
        )
    except ValueError:
        return None


REFERENCE_WINDOWS = 4096
"""At most this many complete training windows (a fixed random subset beyond it) make the
reference rows: the natural diversity compares every pair, so memory grows with its square
(4096 windows: 134 MB)."""


def data_references(train_windows, reference_m, control_m, fps: float) -> dict:
    """Two rows of real motion beside the ground truth, from the complete windows of the
    training split (metres; at most :data:`REFERENCE_WINDOWS` of them, a fixed random
    subset), scored with the test rows' metrics:

    * ``"training_takes"``: the training performers' motion on its own controls: what a
      model that reproduced its training data exactly would score, as far as a metric does
      not depend on the control asked (foot sliding, skate ratio, contact rate, bone-length
      std and jerk of all those windows; FDs against the test windows ``reference_m``
      (N, T, 63); the split's natural diversity; no errors: no test control was asked);
    * ``"nearest_training_window"``: for each test control ``control_m`` (N, T, 3), the
      training window whose control is closest (:func:`motionflows.evaluation.motion.
      nearest_control`), placed on the test control and scored as a model's sample is
      (diversity n/a: one motion per control). Motion matching over whole windows: real
      motion of the training performers, chosen for the control.
    """
    from motionflows.evaluation import motion as mm

    idx = complete_windows(train_windows)
    idx = idx[subset(len(idx), REFERENCE_WINDOWS, seed=3)]
    pose = np.asarray(train_windows.pose)[idx].astype(np.float64)  # only the capped windows
    control = np.asarray(train_windows.control)[idx].astype(np.float64)
    reference_m = np.asarray(reference_m, np.float64)
    own: dict[str, Any] = dict(mm.motion_quality(pose, control, fps=fps))
    own.update(
        diverged=0.0,
        fd_pose=mm.frechet_pose_distance(reference_m, pose),
        fd_window3=mm.frechet_window_distance(reference_m, pose, frames=3),
        diversity=natural_diversity_of(train_windows, idx),
        pose_error=None,
        motion_error=None,
        windows=len(idx),
    )
    nearest = mm.nearest_control(control_m, control)
    matched = motion_metrics(pose[nearest], control_m, reference_m, None, fps)
    matched["windows"] = len(idx)
    return {"training_takes": own, "nearest_training_window": matched}


def motion_metrics(samples_m, control_m, reference_m, diversity_m, fps: float) -> dict:
    """Motion-quality metrics of ``samples_m`` (N, T, 63) metres for controls ``control_m``
    against the ground truth ``reference_m`` (N, T, 63); ``diversity_m`` (M, T, 63) are M
    samples under one control (None for the ground truth, which has one motion per control).

    Returns the scalars of :data:`MOTION_METRICS` plus ``"prediction"``: the per-time errors.
    Diverged samples (see :func:`diverged`) are counted in ``"diverged"`` and left out of
    every other metric, their ground-truth windows with them: the Frechet distances compare
    the samples with the real motion of the same controls (so with diverged samples each
    model's reference set is its own subset of the windows). Diverged draws of
    ``diversity_m`` are dropped from the diversity without a count. ValueError when all
    samples diverged.
    """
    from motionflows.evaluation import motion as mm

    samples_m = np.asarray(samples_m, np.float64)
    ok = ~diverged(samples_m)
    if not ok.any():
        raise ValueError(
            f"all {len(samples_m)} samples diverged (NaN/inf or beyond {DIVERGED_METRES:g} m); "
            "no motion metrics"
        )
    samples_m, control_m = samples_m[ok], np.asarray(control_m)[ok]
    reference_m = np.asarray(reference_m)[ok]
    if diversity_m is not None:
        diversity_m = np.asarray(diversity_m)[~diverged(diversity_m)]
    out: dict[str, Any] = dict(mm.motion_quality(samples_m, control_m, fps=fps))
    out["diverged"] = 1.0 - float(ok.mean())
    out["fd_pose"] = mm.frechet_pose_distance(reference_m, samples_m)
    out["fd_window3"] = mm.frechet_window_distance(reference_m, samples_m, frames=3)
    out["diversity"] = (
        None
        if diversity_m is None or len(diversity_m) < 2
        else mm.diversity(np.asarray(diversity_m)[:, None])
    )
    window = samples_m.shape[1]
    frames = [f for f in mm.prediction_frames(fps) if f < window] or [window - 1]
    pose_err = mm.pose_error(samples_m, reference_m, frames=frames)
    motion_err = mm.motion_error(samples_m, reference_m, control_m, frames=frames)
    out["pose_error"] = float(np.mean(pose_err))
    out["motion_error"] = float(np.mean(motion_err))
    out["prediction"] = {
        "frames": frames,
        "seconds": [f / fps for f in frames],
        "pose_error": pose_err.tolist(),
        "motion_error": motion_err.tolist(),
        "num_samples": 1,
    }
    return out
