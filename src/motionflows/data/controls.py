"""Control trajectories for sampling: named presets and user files.

A control is (T, 3) float32 per frame in the DESIGN units: ``forward`` (m/frame),
``sideways`` (m/frame, + = left), ``turn`` (rad/frame, + = counter-clockwise seen from
above, i.e. a left turn). Presets are built in m/s and rad/s and divided by ``fps``;
changes between phases are smoothed over about 0.5 s.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from motionflows.data.features import ROOT_SIGMA_S, clip_from_bvh, gaussian_smooth
from motionflows.data.names import CONTROL_DIM, DEFAULT_FPS

WALK, RUN, BACK, SIDE = 1.1, 2.4, -0.85, 0.5  # m/s (Bandai dev-set means)

PRESETS: tuple[str, ...] = (
    "stand", "walk", "run", "walk-turn-left", "walk-turn-right", "walk-then-run",
    "walk-turn-run", "figure-eight", "sidestep-left", "sidestep-right", "walk-back",
)  # fmt: skip


def canonical_preset(name: str) -> str | None:
    """The preset ``name`` refers to, spelling-tolerant (case, ``_`` or ``-``,
    ``figure8`` / ``figure-8``), or None when it names none."""
    key = str(name).strip().lower().replace("_", "-").replace(" ", "-")
    key = {
        "figure8": "figure-eight",
        "figure-8": "figure-eight",
        "figureeight": "figure-eight",
    }.get(key, key)
    return key if key in PRESETS else None


def _phases(u: np.ndarray, name: str) -> np.ndarray:
    """(T, 3) m/s, m/s, rad/s as a function of normalised time u in [0, 1)."""
    fwd, side, turn = np.zeros_like(u), np.zeros_like(u), np.zeros_like(u)
    if name == "stand":
        pass
    elif name == "walk":
        fwd[:] = WALK
    elif name == "run":
        fwd[:] = RUN
    elif name in ("walk-turn-left", "walk-turn-right"):
        fwd[:] = WALK  # the turn is set in preset()
    elif name == "walk-then-run":
        fwd[:] = np.where(u < 0.5, WALK, RUN)
    elif name == "walk-turn-run":
        fwd[:] = np.where(u < 0.6, WALK, RUN)  # the turn is set in preset()
    elif name == "figure-eight":
        fwd[:] = WALK
        turn[:] = np.where(u < 0.5, 1.0, -1.0)
    elif name in ("sidestep-left", "sidestep-right"):
        side[:] = SIDE if name.endswith("left") else -SIDE
    elif name == "walk-back":
        fwd[:] = BACK
    return np.stack([fwd, side, turn], -1)


def preset(name: str, seconds: float, fps: float = DEFAULT_FPS) -> np.ndarray:
    """Control trajectory ``name`` of ``round(seconds * fps)`` frames, (T, 3) float32.

    ``walk-turn-left/right`` turn by about 90 degrees in the middle third; ``figure-eight``
    makes a full left circle then a full right circle at walking speed.
    """
    canonical = canonical_preset(name)
    if canonical is None:
        raise ValueError(f"unknown control preset {name!r}; valid: {', '.join(PRESETS)}")
    name = canonical
    if not (np.isfinite(seconds) and seconds > 0 and np.isfinite(fps) and fps > 0):
        raise ValueError(f"seconds and fps must be positive, got {seconds}, {fps}")
    n = max(1, int(round(seconds * fps)))
    u = (np.arange(n) + 0.5) / n
    c = _phases(u, name)
    if name == "figure-eight":
        # one full circle each way over the clip
        c[:, 2] = np.where(u < 0.5, 1.0, -1.0) * 2 * np.pi / (0.5 * n / fps)
    if name in ("walk-turn-left", "walk-turn-right", "walk-turn-run"):
        sign = -1.0 if name.endswith("right") else 1.0
        lo, hi = (0.25, 0.5) if name == "walk-turn-run" else (0.35, 0.65)
        mask = (u >= lo) & (u < hi)
        c[mask, 2] = sign * np.deg2rad(90.0) / max(mask.sum() / fps, 1e-9)
    total_turn = c[:, 2].sum()
    c = gaussian_smooth(c, 0.25 * fps) if name != "figure-eight" else c
    if total_turn != 0:  # keep the exact total heading change through the smoothing
        c[:, 2] *= total_turn / c[:, 2].sum() if c[:, 2].sum() != 0 else 1.0
    return (c / fps).astype(np.float32)


def validate_control(control, *, path: str | None = None) -> np.ndarray:
    """Check a (T, 3) finite control array and return it as float32."""
    where = f" in {path}" if path else ""
    arr = np.asarray(control)
    if arr.ndim != 2 or arr.shape[1] != CONTROL_DIM or arr.shape[0] < 1:
        raise ValueError(
            f"control{where} must have shape (T, {CONTROL_DIM}) = (forward m/frame, sideways "
            f"m/frame, turn rad/frame), got {arr.shape}"
        )
    if not (np.issubdtype(arr.dtype, np.integer) or np.issubdtype(arr.dtype, np.floating)):
        raise ValueError(f"control{where} must hold real numbers, got dtype {arr.dtype}")
    bad = ~np.isfinite(arr).all(axis=1)
    if bad.any():
        raise ValueError(
            f"control{where} has non-finite values (NaN or inf) in {int(bad.sum())} of "
            f"{len(arr)} frames, the first at frame {int(np.argmax(bad))}; fill or cut them "
            "(e.g. np.nan_to_num, or keep only the finite frames) and save it again"
        )
    return arr.astype(np.float32)


def load_control(
    path_or_name: str | os.PathLike,
    seconds: float | None = None,
    fps: float = DEFAULT_FPS,
    *,
    skeleton="bandai",
    root_sigma_s: float = ROOT_SIGMA_S,
) -> np.ndarray:
    """A (T, 3) control in data units (m/frame, m/frame, rad/frame) from a preset name
    (needs ``seconds``), a ``.npy`` file holding a (T, 3) array, or a ``.bvh`` take (its own
    control track at ``fps``, exactly as :func:`motionflows.data.clip_from_bvh` computes it;
    ``skeleton`` maps its joints, ``root_sigma_s`` is the root smoothing in seconds: give the
    model's own, ``config.data.root_sigma_s``).

    With a file and ``seconds`` given, the control is cut or repeated-last-frame padded to
    ``round(seconds * fps)`` frames.

    >>> load_control("walk", seconds=2.0).shape
    (40, 3)
    """
    text = str(path_or_name)
    if canonical_preset(text) is not None:
        if seconds is None:
            raise ValueError(f"preset {text!r} needs seconds=")
        return preset(text, seconds, fps)
    p = Path(text)
    if p.suffix.lower() not in (".npy", ".bvh"):
        raise ValueError(
            f"{text!r} is neither a control preset ({', '.join(PRESETS)}) nor a .npy or .bvh file"
        )
    if not p.exists():
        raise ValueError(f"control file {p} not found")
    if p.suffix.lower() == ".bvh":
        arr = clip_from_bvh(p, fps=fps, skeleton=skeleton, root_sigma_s=root_sigma_s).control
    else:
        try:
            arr = np.load(p, allow_pickle=False)
        except Exception as err:  # numpy's first sentence only: its next offers pickle
            raise ValueError(
                f"cannot read control file {p} as a numeric NumPy array "
                f"({str(err).split('. ')[0]}); write a (T, 3) float array with "
                "numpy.save(path, control)"
            ) from None
    arr = validate_control(arr, path=str(p))
    if seconds is not None:
        n = max(1, int(round(seconds * fps)))
        if len(arr) >= n:
            arr = arr[:n]
        else:
            arr = np.concatenate([arr, np.repeat(arr[-1:], n - len(arr), 0)])
    return arr
