"""Sources of motion clips: the synthetic generator, the Bandai-Namco BVH folders (with
their manifests and checksums) and any folder of BVH files; ``load_clips(name, **options)``
reads one (through the clip cache).

* ``"synthetic"``: :func:`motionflows.data.synthetic.generate` (``n_clips``, ``seconds``,
  ``seed``); no download.
* ``"bandai"``: the Bandai-Namco locomotion BVH files in a folder: ``path``, else
  ``$MOTIONFLOWS_BANDAI_DIR``, else ``../shared/data/bandai_locomotion_dev`` and
  ``../shared/data/bandai_locomotion_extra`` (relative to the working directory or to the
  repository). Metadata (content, style, performer proxy) come from the packaged manifest or,
  for files not in it, from the file name; files are checked against the manifests' git blob
  SHA-1s when the cache is built.
* ``"bvh"``: every ``*.bvh`` under ``path`` (recursive) read with mapping ``skeleton``.
"""

from __future__ import annotations

import csv
import functools
import hashlib
import os
import warnings
from collections.abc import Callable
from pathlib import Path

from motionflows.data.clip_cache import _cached, _code_version, _hash
from motionflows.data.features import ROOT_SIGMA_S, Clip, clip_from_bvh
from motionflows.data.names import DEFAULT_FPS
from motionflows.data.skeleton import SkeletonMapping, get_skeleton
from motionflows.errors import MotionDataError

SOURCES = ("synthetic", "bandai", "bvh")
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


def _bvh_clips(files, fps, skeleton, meta_fn, manifest, root_sigma_s) -> list[Clip]:
    check_checksums(files, manifest or {})  # once, when the cache is built
    return [
        clip_from_bvh(f, fps, skeleton, meta=meta_fn(f.stem), root_sigma_s=root_sigma_s)
        for f in files
    ]


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
    n_clips: int, seconds: float, seed: int, fps: float, root_sigma_s: float
) -> tuple[dict, Callable[[], list[Clip]]]:
    """The cache key and the builder of the ``synthetic`` source's clips."""
    from motionflows.data import synthetic

    key = {"source": "synthetic", "n_clips": int(n_clips), "seconds": float(seconds),
           "seed": int(seed), "fps": fps, "root_sigma_s": root_sigma_s,
           "v": _code_version()}  # fmt: skip
    return key, lambda: synthetic.generate(
        n_clips, seconds, seed, fps=fps, root_sigma_s=root_sigma_s
    )


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
    root_sigma_s: float,
) -> dict:
    """The cache key of BVH clips: the files (name, size, mtime), the folder(s), the frame
    rate, the root smoothing, the skeleton mapping, the code version and a hash of the
    takes' metadata."""
    return {"source": name, "files": _file_key(files),
            "folder": [str(d.resolve()) for d in folders] if len(folders) > 1
            else str(folders[0].resolve()),
            "fps": fps, "root_sigma_s": root_sigma_s, "skeleton": mapping.to_dict(),
            "v": _code_version(),
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
    root_sigma_s: float = ROOT_SIGMA_S,
    **_ignored,
) -> tuple[list[Clip], dict]:
    """The clips of a source (cached), and info about where they came from. ``root_sigma_s``
    is the root's smoothing in seconds (:data:`motionflows.data.features.ROOT_SIGMA_S`)."""
    if name not in SOURCES:
        raise ValueError(f"unknown dataset {name!r}; valid: {', '.join(SOURCES)}")
    fps, root_sigma_s = float(fps), float(root_sigma_s)
    if name == "synthetic":
        key, build = _synthetic_source(n_clips, seconds, seed, fps, root_sigma_s)
        clips, cfile = _cached(key, build, cache=cache, directory=cache_dir)
        return clips, {"cache_file": cfile}
    if name == "bandai":
        folders, mapping, meta_fn, checksums = _bandai_source(path)
    else:
        folders, mapping, meta_fn, checksums = _bvh_source(path, skeleton)
    # _bvh_files and _cached warn with stacklevel=3 (the caller of this function): call them here
    files = sorted((f for d in folders for f in _bvh_files(d)), key=lambda f: f.name)
    files = _with_contents(files, contents, meta_fn, folders[0])
    key = _bvh_key(name, files, folders, fps, mapping, meta_fn, root_sigma_s)
    clips, cfile = _cached(
        key,
        lambda: _bvh_clips(files, fps, mapping, meta_fn, checksums, root_sigma_s),
        cache=cache,
        directory=cache_dir,
    )
    return clips, {"cache_file": cfile, "path": os.pathsep.join(str(d) for d in folders)}
