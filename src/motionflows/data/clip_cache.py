"""The clip cache: a source's clips as one .npz per (files or generator arguments, frame
rate, skeleton mapping, code version) key.

Clips live in ``cache_dir`` (default ``$MOTIONFLOWS_CACHE`` or ``~/.cache/motionflows``) as
``clips_<source>_<hash of the key>.npz``; a corrupt entry is rebuilt, a cache that cannot be
written is skipped with a warning. The key's ``"v"`` is :func:`_code_version`, so cached clips
follow edits of the feature code.
"""

from __future__ import annotations

import hashlib
import json
import os
import warnings
from pathlib import Path

import numpy as np

from motionflows.data.features import Clip

PIPELINE_VERSION = "1"


def cache_dir(path: str | os.PathLike | None = None) -> Path:
    """The cache folder: ``path``, else ``$MOTIONFLOWS_CACHE``, else ~/.cache/motionflows."""
    if path is not None:
        return Path(path)
    env = os.environ.get("MOTIONFLOWS_CACHE")
    return Path(env) if env else Path.home() / ".cache" / "motionflows"


def _code_version() -> str:
    """PIPELINE_VERSION plus a hash of the feature code, so cached clips follow code edits."""
    here = Path(__file__).parent
    h = hashlib.sha1(PIPELINE_VERSION.encode())
    for name in ("bvh.py", "skeleton.py", "features.py", "synthetic.py", "names.py"):
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
    """``build()``'s clips through the cache under ``key`` (and the cache file, or None)."""
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
