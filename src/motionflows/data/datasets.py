"""Datasets: sources -> clips (cached) -> split by take -> augmented windows -> batches.

``load_dataset(name, **options)`` with ``name`` in ``SOURCES`` (the sources and their
options: :mod:`motionflows.data.sources`; the clip cache: :mod:`motionflows.data.clip_cache`).

Splits are by take (file/clip), never by window: ``split_by="take"`` sorts the takes of
each content group by a hash of their names and gives ``val_frac`` / ``test_frac`` of them
to val / test (at least one each when a group has >= 3 takes); ``split_by="performer"``
holds out whole performers for test (``test_performers``, default the last one in sorted
order) and val (``val_performers``; default: a take split of the remaining performers).
``styles`` keeps only the takes of those styles (metadata ``style``) in every split.
``train_fraction`` keeps that share of the training takes (for learning curves over data
size; validation and test keep every take): see :func:`_train_share`.
Augmentation (``mirror``, ``reverse``, ``tempo``: :mod:`motionflows.data.augment`) is
applied to the training takes only, and ``short_repeat`` repeats each padded training window
(:func:`repeat_padded`); the standardiser is fitted on the augmented training windows.
"""

from __future__ import annotations

import hashlib
import warnings
from collections.abc import Iterator

import numpy as np

from motionflows.data.augment import augment_clips
from motionflows.data.clip_cache import PIPELINE_VERSION, cache_dir
from motionflows.data.features import ROOT_SIGMA_S, Clip
from motionflows.data.names import DEFAULT_FPS, DEFAULT_WINDOW
from motionflows.data.pipeline import (
    Standardizer,
    WindowSet,
    batch_indices,
    batches_per_epoch,
    make_windows,
)
from motionflows.data.sources import (
    BANDAI_DEFAULT,
    BANDAI_EXTRA,
    MANIFEST,
    SOURCES,
    bandai_manifest,
    check_checksums,
    default_bandai_dir,
    default_bandai_dirs,
    git_blob_sha1,
    load_clips,
)
from motionflows.errors import MotionDataError

__all__ = [  # the source names stay importable from here (they lived in this module)
    "BANDAI_DEFAULT",
    "BANDAI_EXTRA",
    "MANIFEST",
    "PIPELINE_VERSION",
    "SOURCES",
    "SPLITS",
    "MotionDataset",
    "bandai_manifest",
    "cache_dir",
    "check_checksums",
    "default_bandai_dir",
    "default_bandai_dirs",
    "git_blob_sha1",
    "load_clips",
    "load_dataset",
]

SPLITS = ("train", "val", "test")


def _hash_order(name: str) -> str:
    """The sort key that orders takes for the split by take and for ``train_fraction``: a
    hash of the take's name (stable, unrelated to recording order)."""
    return hashlib.sha1(name.encode()).hexdigest()


def _names(performers) -> list[str]:
    """A list of performer names from None, one name, or an iterable of names."""
    if not performers:
        return []
    return [performers] if isinstance(performers, str) else [str(p) for p in performers]


def _split_names(
    clips: list[Clip],
    split_by: str,
    val_frac: float,
    test_frac: float,
    val_performers=None,
    test_performers=None,
) -> dict[str, list[str]]:
    def by_take(names_groups: dict[str, list[str]]) -> dict[str, list[str]]:
        out = {s: [] for s in SPLITS}
        for group in sorted(names_groups):
            names = sorted(names_groups[group], key=_hash_order)
            n = len(names)
            n_test = int(round(n * test_frac))
            n_val = int(round(n * val_frac))
            if n >= 3:
                n_test = max(n_test, 1 if test_frac > 0 else 0)
                n_val = max(n_val, 1 if val_frac > 0 else 0)
            out["test"] += names[:n_test]
            out["val"] += names[n_test : n_test + n_val]
            out["train"] += names[n_test + n_val :]
        return out

    def groups(cs):
        g: dict[str, list[str]] = {}
        for c in cs:
            g.setdefault(str(c.meta.get("content", "")), []).append(c.name)
        return g

    if split_by == "take":
        return by_take(groups(clips))
    if split_by != "performer":
        raise ValueError(f"split_by must be 'take' or 'performer', got {split_by!r}")
    performers = sorted({str(c.meta.get("performer", "unknown")) for c in clips})
    if len(performers) < 2:
        raise MotionDataError(
            f"split_by='performer' needs at least 2 performers, found {performers}; use "
            "split_by='take'"
        )
    test_p = _names(test_performers) or [performers[-1]]
    val_p = _names(val_performers)
    unknown = sorted(set(test_p + val_p) - set(performers))
    if unknown:
        raise ValueError(f"unknown performer(s) {unknown}; the data have {performers}")
    both = sorted(set(test_p) & set(val_p))
    if both:
        raise ValueError(
            f"performer(s) {both} both for validation and for test: the model would be "
            f"selected on its test takes; give val_performers others than the test ones "
            f"({test_p})"
        )
    rest = [c for c in clips if c.meta.get("performer") not in set(test_p + val_p)]
    if not rest:
        raise ValueError("no performer is left for training; hold out fewer performers")
    out = {"test": [c.name for c in clips if c.meta.get("performer") in test_p]}
    if val_p:
        out["val"] = [c.name for c in clips if c.meta.get("performer") in val_p]
        out["train"] = [c.name for c in rest]
    else:
        inner = by_take(groups(rest))
        out["val"] = inner["val"] + inner["test"]
        out["train"] = inner["train"]
    return out


class MotionDataset:
    """Windows of one source split by take, plus the standardiser and batching.

    Attributes:
      train, val, test: :class:`WindowSet` (train augmented; val/test as recorded).
      standardizer: :class:`Standardizer` fitted on the augmented training windows.
      clips: the un-augmented clips by split (dict of lists).
      info: dict with source, fps, window, hop, takes / windows per split, frames used...
    """

    def __init__(
        self,
        splits: dict[str, WindowSet],
        standardizer: Standardizer,
        info: dict,
        clips: dict[str, list[Clip]] | None = None,
    ):
        self._splits = splits
        self.standardizer = standardizer
        self.info = info
        self.clips = clips or {}
        self._std_cache: dict[str, tuple[np.ndarray, np.ndarray]] = {}

    train = property(lambda self: self._splits["train"])
    val = property(lambda self: self._splits["val"])
    test = property(lambda self: self._splits["test"])

    def with_standardizer(self, standardizer: Standardizer) -> MotionDataset:
        """The same windows with another standardiser (e.g. a run's, fitted on its own
        augmented training windows): the frames stay, their standardised units change."""
        return MotionDataset(self._splits, standardizer, self.info, self.clips)

    def split(self, name: str) -> WindowSet:
        if name not in self._splits:
            raise ValueError(f"unknown split {name!r}; valid: {', '.join(SPLITS)}")
        return self._splits[name]

    def __repr__(self) -> str:
        sizes = ", ".join(f"{s}={len(self._splits[s])}" for s in SPLITS)
        return f"MotionDataset({self.info.get('source')}: windows {sizes})"

    def summary(self) -> str:
        """One line: the source and split rule, each split's takes and windows, the training
        augmentation and, with ``train_fraction`` < 1, how many training takes it kept."""
        info = self.info
        takes = {s: info.get("takes", {}).get(s, len(self.clips.get(s, ()))) for s in SPLITS}
        train = f"train {takes['train']} takes"
        available = info.get("train_takes_available", takes["train"])
        if available != takes["train"]:
            share = f"train_fraction {info.get('train_fraction', 1.0):g}"
            train = f"train {takes['train']} of {available} takes ({share})"
        aug = info.get("augment", {})
        kinds = [k for k, on in (("mirrored", "mirror"), ("reversed", "reverse")) if aug.get(on)]
        if aug.get("tempo", 1.0) != 1.0:
            kinds.append(f"tempo {aug['tempo']:g} {aug.get('tempo_replay', 'both')}")
        if aug.get("foot_lock"):
            kinds.append("feet locked")
        if aug.get("short_repeat", 1) != 1:
            kinds.append(f"short takes x{aug['short_repeat']}")
        train += f" -> {len(self.train)} windows ({', '.join(kinds) or 'as recorded'})"
        held = "; ".join(f"{s} {takes[s]} takes ({len(self.split(s))} windows)" for s in SPLITS[1:])
        return f"{info.get('source')}, split by {info.get('split_by')}: {train}; {held}"

    def with_test(self, windows: WindowSet, **info) -> MotionDataset:
        """A copy whose test split is ``windows`` (e.g. takes of an unseen performer); the
        standardiser and the other splits are kept, ``info`` entries are added. The per-split
        counts describe the new test windows (takes, windows, padded windows); those the
        windows cannot tell (frames per take, performers) and the old test clips are
        dropped rather than kept stale."""
        splits = dict(self._splits, test=windows)
        new = {
            "takes": len(set(np.asarray(windows.take).tolist())),
            "windows": len(windows),
            "padded_windows": int((~windows.valid).any(axis=1).sum()),
        }
        merged = {**self.info, **info}
        for key, counts in self.info.items():
            if isinstance(counts, dict) and "test" in counts and set(counts) <= set(SPLITS):
                rest = {s: n for s, n in counts.items() if s != "test"}
                merged[key] = {**rest, "test": new[key]} if key in new else rest
        clips = {s: c for s, c in self.clips.items() if s != "test"}
        return MotionDataset(splits, self.standardizer, merged, clips)

    def arrays(self, split: str, *, standardized: bool = True) -> dict[str, np.ndarray]:
        """All windows of a split: {"pose": (N, T, 63), "control": (N, T, 3), "valid"}."""
        ws = self.split(split)
        if not standardized:
            return {"pose": ws.pose, "control": ws.control, "valid": ws.valid}
        if split not in self._std_cache:
            s = self.standardizer
            self._std_cache[split] = (
                s.normalize_pose(ws.pose).astype(np.float32),
                s.normalize_control(ws.control).astype(np.float32),
            )
        pose, control = self._std_cache[split]
        return {"pose": pose, "control": control, "valid": ws.valid}

    def batches_per_epoch(self, split: str, batch_size: int, *, drop_last=None) -> int:
        drop = (split == "train") if drop_last is None else drop_last
        return batches_per_epoch(len(self.split(split)), batch_size, drop_last=drop)

    def batch(
        self,
        split: str,
        batch_size: int,
        *,
        seed: int = 0,
        index: int,
        standardized: bool = True,
        shuffle: bool = True,
        drop_last: bool | None = None,
    ) -> dict[str, np.ndarray]:
        """Batch number ``index`` of a seeded stream: {"pose": (B, T, 63), "control"
        (B, T, 3), "valid" (B, T) bool, False on a padded take's frozen tail}.

        Deterministic in (seed, index): epoch = index // batches_per_epoch and the order is
        a permutation drawn from (seed, epoch, split). ``drop_last`` defaults to True for
        "train" (every batch has B windows) and False otherwise.
        """
        drop = (split == "train") if drop_last is None else drop_last
        data = self.arrays(split, standardized=standardized)
        idx = batch_indices(
            len(data["pose"]),
            batch_size,
            seed=seed,
            index=index,
            shuffle=shuffle,
            drop_last=drop,
            salt=SPLITS.index(split),
        )
        return {
            "pose": data["pose"][idx],
            "control": data["control"][idx],
            "valid": data["valid"][idx],
        }

    def batches(
        self,
        split: str,
        batch_size: int,
        *,
        seed: int = 0,
        start: int = 0,
        shuffle: bool = True,
        drop_last: bool = True,
        epochs: int | None = None,
        standardized: bool = True,
    ) -> Iterator[dict[str, np.ndarray]]:
        """Iterate :meth:`batch` from index ``start``; ``epochs=None`` runs forever."""
        per_epoch = self.batches_per_epoch(split, batch_size, drop_last=drop_last)
        stop = None if epochs is None else epochs * per_epoch
        i = start
        while stop is None or i < stop:
            yield self.batch(
                split,
                batch_size,
                seed=seed,
                index=i,
                standardized=standardized,
                shuffle=shuffle,
                drop_last=drop_last,
            )
            i += 1


def _check_options(name: str, window: int, hop: int, val_frac: float, test_frac: float) -> None:
    """Raise ``ValueError`` on an unknown source, a bad window/hop or bad split fractions."""
    if name not in SOURCES:
        raise ValueError(f"unknown dataset {name!r}; valid: {', '.join(SOURCES)}")
    if int(window) < 2 or int(hop) < 1:
        raise ValueError(f"window must be >= 2 and hop >= 1, got {window}, {hop}")
    if not (0 <= val_frac < 1 and 0 <= test_frac < 1 and val_frac + test_frac < 1):
        raise ValueError("val_frac and test_frac must be in [0, 1) with a sum below 1")


def _assign_takes(
    clips: list[Clip],
    source_info: dict,
    split_by: str,
    val_frac: float,
    test_frac: float,
    val_performers=None,
    test_performers=None,
) -> dict[str, list[Clip]]:
    """The clips of each split, sorted by name (see :func:`_split_names`); raise on
    duplicate take names or an empty val or test split."""
    names = [c.name for c in clips]
    if len(set(names)) != len(names):
        raise MotionDataError("take names are not unique; rename the duplicate files")
    assignment = _split_names(clips, split_by, val_frac, test_frac, val_performers, test_performers)
    empty = [s for s in ("val", "test") if not assignment[s]]
    if empty:
        where = f" in {source_info['path']}" if source_info.get("path") else ""
        raise MotionDataError(
            f"the {' and '.join(empty)} split(s) got no take: found {len(clips)} take(s){where}, "
            "and a split by take needs at least 3 takes per content group (one each for "
            "train, val and test); add takes"
        )
    by_name = {c.name: c for c in clips}
    return {s: [by_name[n] for n in sorted(assignment[s])] for s in SPLITS}


def _split_windows(
    split_clips: dict[str, list[Clip]],
    window: int,
    hop: int,
    mirror: bool,
    reverse: bool,
    short: str,
    min_frames: int | None,
    tempo: float = 1.0,
    root_sigma_s: float = ROOT_SIGMA_S,
    tempo_replay: str = "both",
    foot_lock: bool = False,
    short_repeat: int = 1,
) -> tuple[dict[str, WindowSet], dict[str, dict]]:
    """The windows and window statistics of each split (training takes augmented first,
    padded training windows repeated ``short_repeat`` times); raise if the training split
    has no window."""
    splits, stats = {}, {}
    for s in SPLITS:
        cs = split_clips[s]
        if s == "train":
            cs = augment_clips(
                cs,
                mirror=mirror,
                reverse=reverse,
                tempo=tempo,
                tempo_replay=tempo_replay,
                root_sigma_s=root_sigma_s,
                foot_lock=foot_lock,
            )
        splits[s], stats[s] = make_windows(
            cs, int(window), int(hop), short=short, min_frames=min_frames
        )
        if s == "train":
            splits[s] = repeat_padded(splits[s], short_repeat)
    if len(splits["train"]) == 0:
        raise MotionDataError(
            f"no training windows: the takes are shorter than window={window} frames; use a "
            "smaller window or short='pad'"
        )
    return splits, stats


def repeat_padded(windows: WindowSet, times: int) -> WindowSet:
    """``windows`` with each padded window (``valid`` not all True: a take shorter than
    the window) ``times`` times, the copies after the windows as cut.

    A frame of a take of n >= W frames is in about W / hop of its windows (8 for 80-frame
    windows at hop 10), a shorter take's in its one padded window, so with ``times`` = 1
    the short takes (on Bandai, the runs of most styles) weigh that much less per frame in
    training; ``times`` > 1 evens that out. ``times`` = 1 returns ``windows`` itself."""
    times = int(times)
    if times < 1:
        raise ValueError(f"short_repeat must be >= 1, got {times}")
    padded = np.flatnonzero(~np.asarray(windows.valid).all(axis=1))
    if times == 1 or len(padded) == 0:
        return windows
    extra = np.tile(padded, times - 1)
    every = np.concatenate([np.arange(len(windows)), extra])
    return WindowSet(
        pose=windows.pose[every],
        control=windows.control[every],
        take=windows.take[every],
        start=windows.start[every],
        valid=windows.valid[every],
    )


def _style_name(clip: Clip) -> str | None:
    """The take's style name (Bandai's ``style`` metadata), None where it has none
    (synthetic takes carry their style's parameters there, not a name)."""
    style = clip.meta.get("style")
    return style if isinstance(style, str) else None


def _with_styles(clips: list[Clip], styles) -> list[Clip]:
    """The clips whose metadata ``style`` (a name, as the Bandai takes have) is in
    ``styles``; None or empty keeps all. Raise, naming the styles there are, if one is
    unknown."""
    if not styles:
        return clips
    styles = (styles,) if isinstance(styles, str) else tuple(styles)
    have = sorted({s for c in clips if (s := _style_name(c)) is not None})
    unknown = sorted(set(styles) - set(have))
    if unknown:
        there = f"the styles of these takes are {have}" if have else "these takes name none"
        raise MotionDataError(
            f"data.styles: no take has style {unknown}; {there}. Give styles from that list, "
            "or none to keep every take"
        )
    return [c for c in clips if _style_name(c) in set(styles)]


def _train_share(clips: list[Clip], fraction: float) -> list[Clip]:
    """The first ``max(1, round(fraction * n))`` of each (performer, content, style name)
    group's n training takes in the hash order of their names (as the split by take orders them).

    Stratified, so a share keeps every performer and style in proportion; nested, so the
    takes of a smaller fraction are among those of a larger one. Returned sorted by name.
    """
    fraction = float(fraction)
    if not 0.0 < fraction <= 1.0:
        raise ValueError(f"train_fraction must be in (0, 1], got {fraction!r}")
    if fraction == 1.0:
        return clips
    groups: dict[tuple, list[Clip]] = {}
    for c in clips:
        key = (str(c.meta.get("performer", "")), str(c.meta.get("content", "")), _style_name(c))
        groups.setdefault(key, []).append(c)
    kept = []
    for members in groups.values():
        members = sorted(members, key=lambda c: _hash_order(c.name))
        kept += members[: max(1, int(round(fraction * len(members))))]
    return sorted(kept, key=lambda c: c.name)


def _warn_dropped(dropped: list[str], window: int, short: str, min_frames: int | None) -> None:
    """Warn, at the caller of :func:`load_dataset`, about clips too short to be used."""
    if not dropped:
        return
    if short == "pad":
        floor = max(2, int(window) // 4) if min_frames is None else int(min_frames)
        why = f"shorter than min_frames={floor} (short='pad' pads takes of at least that)"
        fix = "pass a smaller min_frames or window to keep them"
    else:
        why = f"shorter than the window {window} (short='drop')"
        fix = "use short='pad' or a smaller window to keep them"
    warnings.warn(
        f"{len(dropped)} clip(s) (augmented copies included) were dropped as {why}: "
        f"{dropped[:5]}; {fix}",
        stacklevel=3,
    )


def _split_info(
    split_clips: dict[str, list[Clip]],
    splits: dict[str, WindowSet],
    stats: dict[str, dict],
    dropped: list[str],
) -> dict:
    """Per-split counts for ``MotionDataset.info``: takes, windows, frames, padded windows,
    the dropped takes and the performers."""
    return {
        "takes": {s: len(split_clips[s]) for s in SPLITS},
        "windows": {s: len(splits[s]) for s in SPLITS},
        "frames_total": {s: stats[s]["frames_total"] for s in SPLITS},
        "frames_used": {s: stats[s]["frames_used"] for s in SPLITS},
        "padded_windows": {s: stats[s]["padded_windows"] for s in SPLITS},
        "dropped_takes": dropped,
        "performers": {
            s: sorted({str(c.meta.get("performer")) for c in split_clips[s]}) for s in SPLITS
        },
    }


def load_dataset(
    name: str = "synthetic",
    *,
    path=None,
    skeleton="bandai",
    fps: float = DEFAULT_FPS,
    window: int = DEFAULT_WINDOW,
    hop: int = 10,
    split_by: str = "take",
    mirror: bool = True,
    reverse: bool = False,
    n_clips: int = 120,
    seconds: float = 12.0,
    seed: int = 0,
    val_frac: float = 0.1,
    test_frac: float = 0.1,
    val_performers=None,
    test_performers=None,
    short: str = "pad",
    min_frames: int | None = None,
    contents=None,
    cache: bool = True,
    cache_dir=None,
    root_sigma_s: float = ROOT_SIGMA_S,
    tempo: float = 1.0,
    tempo_replay: str = "both",
    styles=None,
    train_fraction: float = 1.0,
    foot_lock: bool = False,
    short_repeat: int = 1,
    **extra,
) -> MotionDataset:
    """Load a motion dataset (see the module docstring for sources and options).

    >>> ds = load_dataset("synthetic")                 # no download
    >>> ds = load_dataset("bandai", window=80, hop=10)  # ../shared/data/... or path=
    """
    if extra:
        warnings.warn(f"load_dataset ignores unknown option(s) {sorted(extra)}", stacklevel=2)
    _check_options(name, window, hop, val_frac, test_frac)
    clips, source_info = load_clips(
        name,
        path=path,
        skeleton=skeleton,
        fps=fps,
        n_clips=n_clips,
        seconds=seconds,
        seed=seed,
        contents=contents,
        cache=cache,
        cache_dir=cache_dir,
        root_sigma_s=root_sigma_s,
    )
    clips = _with_styles(clips, styles)
    split_clips = _assign_takes(
        clips, source_info, split_by, val_frac, test_frac, val_performers, test_performers
    )
    available = len(split_clips["train"])
    split_clips["train"] = _train_share(split_clips["train"], train_fraction)
    splits, stats = _split_windows(
        split_clips,
        window,
        hop,
        mirror,
        reverse,
        short,
        min_frames,
        tempo,
        root_sigma_s,
        tempo_replay,
        foot_lock,
        short_repeat,
    )
    dropped = [d for s in SPLITS for d in stats[s]["dropped_clips"]]
    _warn_dropped(dropped, window, short, min_frames)
    train = splits["train"]
    standardizer = Standardizer.fit(train.pose, train.control, valid=train.valid)
    info = {
        "source": name,
        "fps": float(fps),
        "root_sigma_s": float(root_sigma_s),
        "window": int(window),
        "hop": int(hop),
        "split_by": split_by,
        "styles": sorted(styles) if styles else None,
        "train_fraction": float(train_fraction),
        "train_takes_available": available,
        "augment": {
            "mirror": bool(mirror),
            "reverse": bool(reverse),
            "tempo": float(tempo),
            "tempo_replay": tempo_replay,
            "foot_lock": bool(foot_lock),
            "short_repeat": int(short_repeat),
        },
        **_split_info(split_clips, splits, stats, dropped),
        "seconds": sum(len(c) for c in clips) / float(fps),
        **source_info,
    }
    if name == "synthetic":
        info.update(n_clips=int(n_clips), clip_seconds=float(seconds), seed=int(seed))
    return MotionDataset(splits, standardizer, info, split_clips)
