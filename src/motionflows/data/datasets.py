"""Datasets: sources -> clips (cached) -> split by take -> augmented windows -> batches.

``load_dataset(name, **options)`` with ``name`` in ``SOURCES``:

* ``"synthetic"``: :func:`motionflows.data.synthetic.generate` (``n_clips``, ``seconds``,
  ``seed``); no download.
* ``"bandai"``: the Bandai-Namco locomotion BVH files in a folder: ``path``, else
  ``$MOTIONFLOWS_BANDAI_DIR``, else ``../shared/data/bandai_locomotion_dev`` (relative to the
  working directory or to the repository). Metadata (content, style, performer proxy) come
  from the packaged manifest or, for files not in it, from the file name.
* ``"bvh"``: every ``*.bvh`` under ``path`` (recursive) read with mapping ``skeleton``.

Splits are by take (file/clip), never by window: ``split_by="take"`` sorts the takes of
each content group by a hash of their names and gives ``val_frac`` / ``test_frac`` of them
to val / test (at least one each when a group has >= 3 takes); ``split_by="performer"``
holds out whole performers for test (``test_performers``, default the last one in sorted
order) and val (``val_performers``; default: a take split of the remaining performers).
Augmentation (``mirror``, ``reverse``) is applied to the training takes only; the
standardiser is fitted on the augmented training windows.

Clips are cached as .npz in ``cache_dir`` (default ``$MOTIONFLOWS_CACHE`` or
``~/.cache/motionflows``), keyed by a hash of the input files (name, size, mtime) or the
generator arguments, the frame rate, the skeleton mapping and the pipeline version.
"""

from __future__ import annotations

import csv
import functools
import hashlib
import json
import os
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from motionflows.data.augment import augment_clips
from motionflows.data.features import Clip, clip_from_bvh
from motionflows.data.names import DEFAULT_FPS, DEFAULT_WINDOW
from motionflows.data.pipeline import (
    Standardizer,
    WindowSet,
    batch_indices,
    batches_per_epoch,
    make_windows,
)
from motionflows.data.skeleton import SkeletonMapping, get_skeleton
from motionflows.errors import MotionDataError

SOURCES = ("synthetic", "bandai", "bvh")
SPLITS = ("train", "val", "test")
PIPELINE_VERSION = "1"
BANDAI_DEFAULT = Path("..") / "shared" / "data" / "bandai_locomotion_dev"
BANDAI_EXTRA = Path("..") / "shared" / "data" / "bandai_locomotion_extra"
MANIFEST = Path(__file__).with_name("bandai_manifest.csv")
_DOWNLOAD_HINT = (
    "get the data with `motionflows data download bandai --dest DIR` (needs internet) and "
    "pass path=DIR, or set MOTIONFLOWS_BANDAI_DIR=DIR"
)


def bandai_manifest(path: str | os.PathLike | None = None) -> list[dict]:
    """Rows of the Bandai manifest (file, source_path, git_blob_sha1, bytes, ...)."""
    with open(path or MANIFEST, newline="") as fh:
        return list(csv.DictReader(fh))


def default_bandai_dirs() -> list[Path]:
    """The default Bandai folders: ``$MOTIONFLOWS_BANDAI_DIR`` (one folder, or several
    separated by ``os.pathsep``) if set, else the dev folder
    ``../shared/data/bandai_locomotion_dev`` and, when it is there too, the extra takes
    ``../shared/data/bandai_locomotion_extra`` (relative to the working directory or to the
    repository). Empty when none exists."""
    env = os.environ.get("MOTIONFLOWS_BANDAI_DIR")
    if env:
        return [Path(p) for p in env.split(os.pathsep) if p and Path(p).is_dir()]
    for base in (Path.cwd(), Path(__file__).resolve().parents[3]):
        if (base / BANDAI_DEFAULT).is_dir():
            return [base / BANDAI_DEFAULT] + [
                base / d for d in (BANDAI_EXTRA,) if (base / d).is_dir()
            ]
    return []


def default_bandai_dir() -> Path | None:
    """The first default Bandai folder (see :func:`default_bandai_dirs`), or None."""
    dirs = default_bandai_dirs()
    return dirs[0] if dirs else None


def git_blob_sha1(data: bytes) -> str:
    """The git blob id of ``data``: sha1 of ``b"blob <len>\\0" + data``."""
    h = hashlib.sha1(b"blob %d\0" % len(data))
    h.update(data)
    return h.hexdigest()


def check_checksums(files: list[Path], manifest: dict[str, dict]) -> None:
    """Raise ``MotionDataError`` naming the first file whose git blob SHA-1 differs from its
    manifest row (files without a row, or a row without a checksum, are not checked)."""
    for f in files:
        want = (manifest.get(f.name) or {}).get("git_blob_sha1")
        if want and git_blob_sha1(f.read_bytes()) != want:
            raise MotionDataError(
                "does not match its manifest checksum (the file is damaged or was edited); "
                "fetch it again with `motionflows data download bandai --dest DIR`",
                path=str(f),
            )


def cache_dir(path: str | os.PathLike | None = None) -> Path:
    if path is not None:
        return Path(path)
    env = os.environ.get("MOTIONFLOWS_CACHE")
    return Path(env) if env else Path.home() / ".cache" / "motionflows"


def _code_version() -> str:
    """PIPELINE_VERSION plus a hash of the feature code, so cached clips follow code edits."""
    here = Path(__file__).parent
    h = hashlib.sha1(PIPELINE_VERSION.encode())
    for name in ("bvh.py", "skeleton.py", "features.py", "synthetic.py"):
        h.update((here / name).read_bytes())
    return h.hexdigest()[:12]


def _hash(obj) -> str:
    return hashlib.sha1(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:16]


def _save_clips(path: Path, clips: list[Clip]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(f".tmp{os.getpid()}.npz")
    np.savez(
        tmp,
        pose=np.concatenate([c.pose for c in clips]),
        control=np.concatenate([c.control for c in clips]),
        lengths=np.array([len(c) for c in clips], np.int64),
        fps=np.array([c.fps for c in clips]),
        names=np.array([c.name for c in clips]),
        meta=np.array(json.dumps([c.meta for c in clips])),
    )
    os.replace(tmp, path)


def _load_clips(path: Path) -> list[Clip]:
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in ("pose", "control", "lengths", "fps", "names", "meta")}
    ends = np.cumsum(arrays["lengths"])
    starts = ends - arrays["lengths"]
    metas = json.loads(str(arrays["meta"]))
    pose, control = arrays["pose"], arrays["control"]
    return [
        Clip(pose[s:e], control[s:e], float(f), str(n), m)
        for s, e, f, n, m in zip(starts, ends, arrays["fps"], arrays["names"], metas, strict=True)
    ]


def _cached(key: dict, build, *, cache: bool, directory) -> tuple[list[Clip], str | None]:
    if not cache:
        return build(), None
    path = cache_dir(directory) / f"clips_{key['source']}_{_hash(key)}.npz"
    if path.exists():
        try:
            return _load_clips(path), str(path)
        except Exception:  # a corrupt cache entry is rebuilt
            path.unlink(missing_ok=True)
    clips = build()
    try:
        _save_clips(path, clips)
    except OSError as err:
        warnings.warn(f"could not write the data cache {path}: {err}", stacklevel=3)
        return clips, None
    return clips, str(path)


def _folder_manifest(folder: Path) -> dict[str, dict]:
    """Rows of ``folder/manifest.csv`` by file name (columns ``file`` and optionally
    ``content``, ``style``, ``performer_proxy`` or ``performer``, ``dataset``, ``take``)."""
    path = folder / "manifest.csv"
    if not path.is_file():
        return {}
    try:
        rows = bandai_manifest(path)
    except (OSError, csv.Error, UnicodeDecodeError) as err:
        raise MotionDataError(f"cannot read the manifest ({err})", path=str(path)) from None
    return {r["file"]: r for r in rows if r.get("file")}


def _bvh_files(folder: Path) -> list[Path]:
    """Every ``*.bvh`` under ``folder`` (symlinks followed once; a link that loops back or
    points nowhere is skipped with a warning naming it)."""
    files, skipped, seen = [], [], set()
    for root, dirs, names in os.walk(folder, followlinks=True):
        real = os.path.realpath(root)
        if real in seen:  # a symlink back into a folder already walked
            skipped.append(f"{root} (a symlink loop, or a second link to one folder)")
            dirs[:] = []
            continue
        seen.add(real)
        for name in names:
            p = Path(root) / name
            if p.suffix.lower() != ".bvh":
                continue
            if p.is_file():
                files.append(p)
            elif p.is_symlink():
                skipped.append(f"{p} (a symlink loop or a link to nothing)")
    if skipped:
        warnings.warn(
            f"skipped {len(skipped)} path(s) under {folder}: {', '.join(skipped[:3])}; remove "
            "or fix the links",
            stacklevel=3,
        )
    files.sort()
    if not files:
        raise MotionDataError(f"no .bvh files in {folder}; " + _DOWNLOAD_HINT, path=str(folder))
    return files


def _file_key(files: list[Path]) -> list:
    return [(f.name, f.stat().st_size, f.stat().st_mtime_ns) for f in files]


def _bandai_meta(name: str, manifest: dict[str, dict]) -> dict:
    row = manifest.get(name + ".bvh")
    if row is not None and row.get("content"):
        return {
            "source": "bandai",
            "dataset": row.get("dataset", ""),
            "content": row["content"],
            "style": row.get("style", ""),
            "take": row.get("take", ""),
            "performer": row.get("performer_proxy") or row.get("performer") or "unknown",
        }  # fmt: skip
    parts = name.split("_")
    meta = {"source": "bandai", "performer": "unknown"}
    if len(parts) >= 4:
        meta.update(dataset=parts[0], content=parts[1], style=parts[2], take=parts[3])
        group = {"dataset-1": "D1-X"}.get(parts[0])
        if group is None and parts[2] in ("active", "elderly", "exhausted"):
            group = "D2-A"
        elif group is None and parts[2] in ("masculine", "normal"):
            group = "D2-C"
        meta["performer"] = group or f"{parts[0]}-other"
    return meta


def _bvh_clips(files, fps, skeleton, source, meta_fn, manifest=None) -> list[Clip]:
    check_checksums(files, manifest or {})  # once, when the cache is built
    return [clip_from_bvh(f, fps, skeleton, meta=meta_fn(f.stem)) for f in files]


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
            names = sorted(names_groups[group], key=lambda n: hashlib.sha1(n.encode()).hexdigest())
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
    test_p = list(test_performers) if test_performers else [performers[-1]]
    val_p = list(val_performers) if val_performers else []
    unknown = sorted(set(test_p + val_p) - set(performers))
    if unknown:
        raise ValueError(f"unknown performer(s) {unknown}; the data have {performers}")
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

    def split(self, name: str) -> WindowSet:
        if name not in self._splits:
            raise ValueError(f"unknown split {name!r}; valid: {', '.join(SPLITS)}")
        return self._splits[name]

    def __repr__(self) -> str:
        sizes = ", ".join(f"{s}={len(self._splits[s])}" for s in SPLITS)
        return f"MotionDataset({self.info.get('source')}: windows {sizes})"

    def with_test(self, windows: WindowSet, **info) -> MotionDataset:
        """A copy whose test split is ``windows`` (e.g. takes of an unseen performer); the
        standardiser and the other splits are kept, ``info`` entries are added."""
        splits = dict(self._splits, test=windows)
        return MotionDataset(splits, self.standardizer, {**self.info, **info}, self.clips)

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
        """Batch number ``index`` of a seeded stream: {"pose": (B, T, 63), "control"}.

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
        return {"pose": data["pose"][idx], "control": data["control"][idx]}

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


def _bvh_meta(name: str, manifest: dict[str, dict]) -> dict:
    """Metadata of a take of the ``bvh`` source from its row in the folder's manifest."""
    row = manifest.get(name + ".bvh", {})
    return {
        "source": "bvh",
        "performer": row.get("performer_proxy") or row.get("performer") or "unknown",
        "content": row.get("content", ""),
        "style": row.get("style", ""),
    }


def _synthetic_source(
    n_clips: int, seconds: float, seed: int, fps: float
) -> tuple[dict, Callable[[], list[Clip]]]:
    """The cache key and the builder of the ``synthetic`` source's clips."""
    from motionflows.data import synthetic

    key = {"source": "synthetic", "n_clips": int(n_clips), "seconds": float(seconds),
           "seed": int(seed), "fps": fps, "v": _code_version()}  # fmt: skip
    return key, lambda: synthetic.generate(n_clips, seconds, seed, fps=fps)


def _bandai_source(path) -> tuple[list[Path], SkeletonMapping, Callable[[str], dict], dict]:
    """The ``bandai`` source: its folders (``path`` or the defaults), the Bandai skeleton
    mapping, the metadata function of a take name and the manifest rows to check the files
    against (the packaged manifest updated by each folder's ``manifest.csv``)."""
    folders = [Path(path)] if path else default_bandai_dirs()
    if not folders or not all(f.is_dir() for f in folders):
        env = os.environ.get("MOTIONFLOWS_BANDAI_DIR")
        where = (
            str(folders[0])
            if folders
            else (f"$MOTIONFLOWS_BANDAI_DIR={env}" if env else str(BANDAI_DEFAULT))
        )
        raise MotionDataError(f"Bandai data folder not found: {where}; " + _DOWNLOAD_HINT)
    mapping = get_skeleton("bandai")
    manifest = {r["file"]: r for r in bandai_manifest()}
    for f in folders:
        manifest.update(_folder_manifest(f))
    return folders, mapping, functools.partial(_bandai_meta, manifest=manifest), manifest


def _bvh_source(path, skeleton) -> tuple[list[Path], SkeletonMapping, Callable[[str], dict], dict]:
    """The ``bvh`` source: its one folder ``path``, the skeleton mapping, the metadata
    function of a take name (from the folder's ``manifest.csv``) and no checksums."""
    if path is None:
        raise ValueError("load_dataset('bvh') needs path=<folder of .bvh files>")
    folder = Path(path)
    if folder.is_file():
        raise MotionDataError(
            "is a file, but the bvh source reads a folder of .bvh files (at least 3 takes "
            "for the train/val/test split); put the file in a folder and pass bvh:DIR "
            "(to look at one file, use `motionflows render FILE`)",
            path=str(folder),
        )
    if not folder.is_dir():
        raise MotionDataError("BVH folder not found", path=str(folder))
    mapping = get_skeleton(skeleton)
    local = _folder_manifest(folder)
    return [folder], mapping, functools.partial(_bvh_meta, manifest=local), {}


def _with_contents(
    files: list[Path], contents, meta_fn: Callable[[str], dict], folder: Path
) -> list[Path]:
    """The files whose metadata ``content`` is in ``contents`` (a name or several; None
    or empty keeps all); raise if none is left."""
    if not contents:
        return files
    wanted = {contents} if isinstance(contents, str) else set(contents)
    files = [f for f in files if meta_fn(f.stem).get("content") in wanted]
    if not files:
        raise MotionDataError(f"no files with content in {sorted(wanted)}", path=str(folder))
    return files


def _bvh_key(
    name: str,
    files: list[Path],
    folders: list[Path],
    fps: float,
    mapping: SkeletonMapping,
    meta_fn: Callable[[str], dict],
) -> dict:
    """The cache key of BVH clips: the files (name, size, mtime), the folder(s), the frame
    rate, the skeleton mapping, the code version and a hash of the takes' metadata."""
    return {"source": name, "files": _file_key(files),
            "folder": [str(d.resolve()) for d in folders] if len(folders) > 1
            else str(folders[0].resolve()),
            "fps": fps, "skeleton": mapping.to_dict(), "v": _code_version(),
            "meta": _hash([meta_fn(f.stem) for f in files])}  # fmt: skip


def load_clips(
    name: str,
    *,
    path=None,
    skeleton="bandai",
    fps: float = DEFAULT_FPS,
    n_clips: int = 120,
    seconds: float = 12.0,
    seed: int = 0,
    contents=None,
    cache: bool = True,
    cache_dir=None,
    **_ignored,
) -> tuple[list[Clip], dict]:
    """The clips of a source (cached), and info about where they came from."""
    if name not in SOURCES:
        raise ValueError(f"unknown dataset {name!r}; valid: {', '.join(SOURCES)}")
    fps = float(fps)
    if name == "synthetic":
        key, build = _synthetic_source(n_clips, seconds, seed, fps)
        clips, cfile = _cached(key, build, cache=cache, directory=cache_dir)
        return clips, {"cache_file": cfile}
    if name == "bandai":
        folders, mapping, meta_fn, checksums = _bandai_source(path)
    else:
        folders, mapping, meta_fn, checksums = _bvh_source(path, skeleton)
    # _bvh_files and _cached warn with stacklevel=3 (the caller of this function): call them here
    files = sorted((f for d in folders for f in _bvh_files(d)), key=lambda f: f.name)
    files = _with_contents(files, contents, meta_fn, folders[0])
    key = _bvh_key(name, files, folders, fps, mapping, meta_fn)
    clips, cfile = _cached(
        key,
        lambda: _bvh_clips(files, fps, mapping, name, meta_fn, checksums),
        cache=cache,
        directory=cache_dir,
    )
    return clips, {"cache_file": cfile, "path": os.pathsep.join(str(d) for d in folders)}


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
) -> tuple[dict[str, WindowSet], dict[str, dict]]:
    """The windows and window statistics of each split (training takes augmented first);
    raise if the training split has no window."""
    splits, stats = {}, {}
    for s in SPLITS:
        cs = split_clips[s]
        if s == "train":
            cs = augment_clips(cs, mirror=mirror, reverse=reverse)
        splits[s], stats[s] = make_windows(
            cs, int(window), int(hop), short=short, min_frames=min_frames
        )
    if len(splits["train"]) == 0:
        raise MotionDataError(
            f"no training windows: the takes are shorter than window={window} frames; use a "
            "smaller window or short='pad'"
        )
    return splits, stats


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
    )
    split_clips = _assign_takes(
        clips, source_info, split_by, val_frac, test_frac, val_performers, test_performers
    )
    splits, stats = _split_windows(split_clips, window, hop, mirror, reverse, short, min_frames)
    dropped = [d for s in SPLITS for d in stats[s]["dropped_clips"]]
    _warn_dropped(dropped, window, short, min_frames)
    train = splits["train"]
    standardizer = Standardizer.fit(train.pose, train.control, valid=train.valid)
    info = {
        "source": name,
        "fps": float(fps),
        "window": int(window),
        "hop": int(hop),
        "split_by": split_by,
        "augment": {"mirror": bool(mirror), "reverse": bool(reverse)},
        **_split_info(split_clips, splits, stats, dropped),
        "seconds": sum(len(c) for c in clips) / float(fps),
        **source_info,
    }
    if name == "synthetic":
        info.update(n_clips=int(n_clips), clip_seconds=float(seconds), seed=int(seed))
    return MotionDataset(splits, standardizer, info, split_clips)
