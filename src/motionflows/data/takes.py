"""Takes a model never saw: BVH folders or files read at a run's frame rate and window.

Scoring, sampling and benchmarking a trained run on other data must use the run's own
standardiser, window length and frame rate, never refitted ones: this module only reads
and cuts, and leaves standardising to the caller.

``data`` specs (the ``--data`` grammar of the CLI): ``bvh:DIR`` (every ``*.bvh`` under DIR,
read with ``skeleton``), ``bandai:DIR`` (the same with the Bandai mapping and manifest
metadata), ``bandai`` (the default Bandai folders), a folder (as ``bvh:DIR``) or a single
``.bvh`` file.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from motionflows.data.features import ROOT_SIGMA_S, Clip, clip_from_bvh
from motionflows.data.pipeline import WindowSet, make_windows
from motionflows.errors import MotionDataError


@dataclasses.dataclass
class Takes:
    """Complete windows of a set of takes, in metres, and what was left out.

    Attributes:
      windows: every complete window (no padding) of every usable take, (N, T, 63) pose
        and (N, T, 3) control, in data units; ``windows.take`` names the take of each.
      clips: the takes read (all of them, usable or not).
      skipped: ``"name (F frames < T)"`` for each take too short for one window.
      label: a short name for reports (the folder's or file's name).
      source: the spec the takes came from.
    """

    windows: WindowSet
    clips: list[Clip]
    skipped: list[str]
    label: str
    source: str


def parse_spec(spec: str) -> tuple[str, Path | None]:
    """``spec`` -> (source, path): source ``"bvh"`` or ``"bandai"``; path a folder, a
    ``.bvh`` file, or None for the default Bandai folders. Raises ``MotionDataError``."""
    text = str(spec)
    source, path = "bvh", text
    if ":" in text and text.split(":", 1)[0] in ("bvh", "bandai"):
        source, path = text.split(":", 1)
    elif text == "bandai":
        return "bandai", None
    if not path:
        raise MotionDataError(f"--data {spec!r}: give a folder or file after the colon")
    p = Path(path)
    if not p.exists():
        raise MotionDataError(
            f"--data {spec!r}: {p} does not exist; give a folder of .bvh takes or one .bvh file"
        )
    if p.is_file() and p.suffix.lower() != ".bvh":
        raise MotionDataError(f"--data {spec!r}: {p} is a file but not a .bvh file")
    return source, p


def read_takes(
    spec: str, *, fps: float, skeleton: str = "bandai", root_sigma_s: float = ROOT_SIGMA_S
) -> tuple[list[Clip], str]:
    """The clips of every take of ``spec`` at ``fps`` (see the module docstring), the root
    smoothed over ``root_sigma_s`` seconds, and a label."""
    from motionflows.data.sources import load_clips

    source, path = parse_spec(spec)
    if path is not None and path.is_file():
        clip = clip_from_bvh(path, fps=fps, skeleton=skeleton, root_sigma_s=root_sigma_s)
        return [clip], path.stem
    if source == "bandai":
        clips, info = load_clips("bandai", path=path, fps=fps, root_sigma_s=root_sigma_s)
        label = Path(info.get("path", "bandai")).name if path is not None else "bandai"
        return clips, label
    clips, _ = load_clips("bvh", path=path, skeleton=skeleton, fps=fps, root_sigma_s=root_sigma_s)
    return clips, path.name


def load_takes(
    spec: str,
    *,
    fps: float,
    window: int,
    hop: int,
    skeleton: str = "bandai",
    root_sigma_s: float = ROOT_SIGMA_S,
) -> Takes:
    """Every complete ``window``-frame window (start every ``hop`` frames) of every take of
    ``spec`` read at ``fps`` with the root smoothed over ``root_sigma_s`` seconds (give the
    run's own, ``config.data.root_sigma_s``). Takes shorter than one window are listed in
    ``skipped``; a spec with no usable take raises ``MotionDataError``."""
    clips, label = read_takes(spec, fps=fps, skeleton=skeleton, root_sigma_s=root_sigma_s)
    long_enough = [c for c in clips if len(c) >= window]
    skipped = [f"{c.name} ({len(c)} frames < {window})" for c in clips if len(c) < window]
    if not long_enough:
        raise MotionDataError(
            f"--data {spec}: no take has the {window} frames ({window / fps:g} s at {fps:g} fps) "
            f"of one window ({len(clips)} take(s) read, all shorter); give longer takes"
        )
    windows, _ = make_windows(long_enough, window, hop, short="drop")
    return Takes(windows=windows, clips=clips, skipped=skipped, label=label, source=str(spec))
