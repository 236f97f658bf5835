"""Likelihood tables: per-window log-likelihoods -> per-frame numbers in stated units.

Every experiment's ``evaluate(model, batch, key)`` returns per-window log-likelihoods
``ll`` (nats, standardised space, shape (B,)) for each of its scopes. A scope covers
``n`` scored frames per window. With the standardiser ``s = (x - mean) / std`` the density
in metres is ``p_m(x) = p_s(s) * |ds/dx| = p_s(s) * exp(n * log_det_per_frame)`` with
``log_det_per_frame = -sum(log std)``, so

    nats/frame (metres)        = -(ll + n * log_det_per_frame) / n
    bits/frame (standardised)  = -ll / (n * ln 2)

(the second is the official MoGlow code's unit). The two are never mixed in one column.
Means come with a bootstrap 95% interval over windows.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

LN2 = math.log(2.0)


def _as_ll(ll: Any) -> np.ndarray:
    arr = np.asarray(ll, dtype=np.float64).reshape(-1)
    if arr.size == 0:
        raise ValueError("no log-likelihoods given: evaluate at least one window")
    return arr


def nats_per_frame_metres(ll: Any, n_frames: int, log_det_per_frame: float) -> np.ndarray:
    """Per-window NLL in nats per frame in metres: ``-(ll + n * log_det_per_frame) / n``.

    ``ll``: (N,) log-likelihoods in nats in standardised space of ``n_frames`` frames each.
    """
    if n_frames <= 0:
        raise ValueError(f"n_frames must be positive, got {n_frames}")
    return -(_as_ll(ll) + n_frames * float(log_det_per_frame)) / n_frames


def bits_per_frame_standardized(ll: Any, n_frames: int) -> np.ndarray:
    """Per-window NLL in bits per frame in standardised space: ``-ll / (n * ln 2)``."""
    if n_frames <= 0:
        raise ValueError(f"n_frames must be positive, got {n_frames}")
    return -_as_ll(ll) / (n_frames * LN2)


def bootstrap_ci(
    values: Any, *, num: int = 1000, level: float = 0.95, seed: int = 0
) -> tuple[float, float, float]:
    """Mean of ``values`` and a percentile bootstrap interval: ``(mean, low, high)``.

    Resamples the N values with replacement ``num`` times (numpy ``default_rng(seed)``)
    and returns the (1 - level) / 2 and (1 + level) / 2 quantiles of the resampled means.
    With a single value the interval collapses to it.
    """
    v = _as_ll(values)
    mean = float(v.mean())
    if v.size == 1:
        return mean, mean, mean
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, v.size, size=(num, v.size))
    means = v[idx].mean(axis=1)
    lo, hi = np.quantile(means, [(1 - level) / 2, (1 + level) / 2])
    return mean, float(lo), float(hi)


def likelihood_rows(
    lls: Mapping[str, Any],
    n_frames: Mapping[str, int] | int,
    log_det_per_frame: float,
    *,
    scopes: Mapping[str, Any] | None = None,
    num_bootstrap: int = 1000,
    seed: int = 0,
) -> list[dict]:
    """One table row per scope from per-window log-likelihoods.

    ``lls[key]``: (N,) nats in standardised space; ``n_frames[key]`` (or one int for all):
    frames scored per window. ``scopes[key]`` (a ``motionflows.config.Scope``) adds the
    description and whether the score is a bound. Each row holds ``scope``, ``description``,
    ``bound``, ``windows``, ``scored_frames_per_window``, ``nats_per_frame_metres`` (mean),
    ``nats_per_frame_metres_ci95`` ([low, high]), ``bits_per_frame_std`` (mean),
    ``bits_per_frame_std_ci95``.
    """
    order = list(scopes or {}) + sorted(lls)
    keys = sorted(lls, key=lambda k: (k != "window", order.index(k)))
    rows = []
    for key in keys:
        ll = lls[key]
        n = n_frames if isinstance(n_frames, int) else int(n_frames[key])
        nats = nats_per_frame_metres(ll, n, log_det_per_frame)
        bits = bits_per_frame_standardized(ll, n)
        if not (np.all(np.isfinite(nats))):
            bad = int(np.sum(~np.isfinite(nats)))
            raise ValueError(f"scope {key!r}: {bad} of {nats.size} log-likelihoods are not finite")
        nm, nlo, nhi = bootstrap_ci(nats, num=num_bootstrap, seed=seed)
        bm, blo, bhi = bootstrap_ci(bits, num=num_bootstrap, seed=seed)
        scope = (scopes or {}).get(key)
        rows.append(
            {
                "scope": key,
                "description": getattr(scope, "description", ""),
                "bound": bool(getattr(scope, "bound", False)),
                "windows": int(nats.size),
                "scored_frames_per_window": n,
                "nats_per_frame_metres": nm,
                "nats_per_frame_metres_ci95": [nlo, nhi],
                "bits_per_frame_std": bm,
                "bits_per_frame_std_ci95": [blo, bhi],
            }
        )
    return rows


def format_table(rows: list[dict], *, title: str | None = None) -> str:
    """A plain-text table of :func:`likelihood_rows` output, units and scored frames stated."""
    w = max([12] + [len(r["scope"]) + (8 if r["bound"] else 0) for r in rows])
    head = (
        f"{'scope':<{w}} {'NLL nats/frame (metres)':>30} {'NLL bits/frame (std)':>28} "
        f"{'windows':>8} {'frames/window':>13}"
    )
    lines = [title] if title else []
    lines += [head, "-" * len(head)]
    for r in rows:
        scope = r["scope"] + (" (bound)" if r["bound"] else "")
        nlo, nhi = r["nats_per_frame_metres_ci95"]
        blo, bhi = r["bits_per_frame_std_ci95"]
        nats = f"{r['nats_per_frame_metres']:.3f} [{nlo:.3f}, {nhi:.3f}]"
        bits = f"{r['bits_per_frame_std']:.3f} [{blo:.3f}, {bhi:.3f}]"
        lines.append(
            f"{scope:<{w}} {nats:>30} {bits:>28} {r['windows']:>8} "
            f"{r['scored_frames_per_window']:>13}"
        )
    lines.append(
        "NLL = negative log-likelihood per scored frame (63-dim pose), lower is better; "
        "[95% bootstrap interval over windows]. Metres include the standardiser Jacobian."
    )
    for r in rows:
        if r["description"]:
            lines.append(f"  {r['scope']}: {r['description']}")
    return "\n".join(lines)


def scored_frames(scopes: Mapping[str, Any] | None, key: str, window: int, config: Any = None):
    """Frames per window scored by ``key``: the scope's ``scored_frames`` or the whole window."""
    scope = (scopes or {}).get(key)
    if scope is None or not hasattr(scope, "scored_frames"):
        return int(window)
    return scope.scored_frames(window, config)


def evaluate_windows(
    module: Any,
    model: Any,
    pose: np.ndarray,
    control: np.ndarray,
    *,
    batch_size: int,
    key: Any,
    evaluate_fn: Any = None,
) -> dict[str, np.ndarray]:
    """Run ``module.evaluate`` over all windows (standardised (N, T, D) arrays) in batches.

    The last batch is padded by repeating windows (the padding is dropped), so one compiled
    shape serves every batch. A model replicated over several devices scores each batch
    data-parallel (:func:`motionflows.sharding.data_parallel`). ``evaluate_fn(model, batch,
    key)`` may be a pre-jitted ``module.evaluate``. Returns ``{scope: (N,) float64}``.
    """
    import jax

    if pose.ndim != 3 or control.ndim != 3 or pose.shape[:2] != control.shape[:2]:
        raise ValueError(
            f"expected pose (N, T, D) and control (N, T, C) with equal N, T; got "
            f"{pose.shape} and {control.shape}"
        )
    n = pose.shape[0]
    if n == 0:
        raise ValueError("the split has no windows to evaluate")
    from motionflows.sharding import data_parallel, shard_batch

    fn = evaluate_fn or jax.jit(module.evaluate)
    bs = max(1, min(batch_size, n))
    model, mesh = data_parallel(model, bs)
    out: dict[str, list] = {}
    for b, start in enumerate(range(0, n, bs)):
        idx = np.arange(start, start + bs) % n
        batch = {
            "pose": np.asarray(pose[idx], np.float32),
            "control": np.asarray(control[idx], np.float32),
        }
        if mesh is not None:
            batch = shard_batch(batch, mesh)
        res = fn(model, batch, jax.random.fold_in(key, b))
        keep = min(bs, n - start)
        for k, v in res.items():
            out.setdefault(k, []).append(np.asarray(v, np.float64)[:keep])
    return {k: np.concatenate(v) for k, v in out.items()}


def write_eval(path: Any, rows: list[dict], **extra: Any) -> None:
    """Write ``eval_<split>.json``: ``{"rows": rows, **extra}``."""
    Path(path).write_text(json.dumps({"rows": rows, **extra}, indent=2) + "\n")
