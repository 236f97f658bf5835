"""Download the Bandai-Namco locomotion files listed in the packaged manifest.

Source: GitHub ``BandaiNamcoResearchInc/Bandai-Namco-Research-Motiondataset`` at the pinned
commit ``74ead3ba1ae4696404e6086233779f60de8bf9ef`` (licence CC BY-NC 4.0: non-commercial
use, with attribution "Bandai-Namco-Research-Motiondataset, (c) 2022 Bandai Namco Research
Inc., CC BY-NC 4.0"). Each file is fetched from ``base_url + source_path`` (falling back to
``base_url + file`` for flat mirrors), checked against its git blob SHA-1
(``sha1(b"blob <size>\\0" + content)``) and saved flat as ``dest/<file>``, the layout of
``../shared/data/bandai_locomotion_dev`` that ``load_dataset("bandai", path=dest)`` reads.
Files already present and valid are skipped; a copy of the manifest is written beside them.
"""

from __future__ import annotations

import os
import shutil
import sys
import time
import urllib.error
import urllib.request
from collections.abc import Callable
from pathlib import Path

from motionflows.data.sources import MANIFEST, bandai_manifest, git_blob_sha1
from motionflows.errors import MotionDataError

COMMIT = "74ead3ba1ae4696404e6086233779f60de8bf9ef"
REPOSITORY = "BandaiNamcoResearchInc/Bandai-Namco-Research-Motiondataset"
BASE_URL = f"https://raw.githubusercontent.com/{REPOSITORY}/{COMMIT}/"
ATTRIBUTION = (
    "Bandai-Namco-Research-Motiondataset, (c) 2022 Bandai Namco Research Inc., "
    "CC BY-NC 4.0 (non-commercial use only)"
)


def file_is_valid(path: Path, sha1: str, size: int | None = None) -> bool:
    if not path.is_file():
        return False
    if size is not None and path.stat().st_size != size:
        return False
    return git_blob_sha1(path.read_bytes()) == sha1


def _print_progress(event: dict) -> None:
    print(
        f"[{event['index']}/{event['total']}] {event['file']}: {event['status']}",
        file=sys.stderr,
        flush=True,
    )


class _TooLarge(Exception):
    """A response longer than the manifest's size for the file."""


def _fetch(url: str, timeout: float, limit: int) -> bytes:
    """The body of ``url``, reading at most ``limit`` bytes (``_TooLarge`` beyond that)."""
    with urllib.request.urlopen(url, timeout=timeout) as response:  # noqa: S310 (http/https)
        length = response.headers.get("Content-Length")
        if length is not None and length.isdigit() and int(length) > limit:
            raise _TooLarge(f"{url} announces {int(length)} bytes, expected {limit}")
        data = response.read(limit + 1)
    if len(data) > limit:
        raise _TooLarge(f"{url} sent more than the expected {limit} bytes")
    return data


def _safe_name(name: str) -> bool:
    """A manifest file name that stays inside ``dest``: one plain path component."""
    return (
        bool(name)
        and name not in (".", "..")
        and "/" not in name
        and "\\" not in name
        and "\0" not in name
        and not Path(name).is_absolute()
        and Path(name).name == name
    )


def _manifest_rows(manifest: str | os.PathLike | None) -> list[dict]:
    """The manifest's rows with ``bytes`` as an int; raise on an unsafe file name or a row
    without a valid size."""
    rows = bandai_manifest(manifest)
    unsafe = [r.get("file") for r in rows if not _safe_name(r.get("file") or "")]
    if unsafe:
        raise MotionDataError(
            f"the manifest lists file name(s) {unsafe[:3]} that would be written outside "
            "the destination folder; use the packaged manifest",
            path=str(manifest or MANIFEST),
        )
    for r in rows:
        try:
            r["bytes"] = int(r["bytes"])
        except (KeyError, TypeError, ValueError):
            raise MotionDataError(
                f"manifest entry {r.get('file')!r} has no valid 'bytes' size",
                path=str(manifest or MANIFEST),
            ) from None
    return rows


def _select(rows: list[dict], files: list[str] | None, contents: list[str] | None) -> list[dict]:
    """The rows named in ``files`` (".bvh" optional; ValueError on unknown names) and of
    the given ``contents``; None keeps all."""
    if files is not None:
        wanted = {f if f.endswith(".bvh") else f + ".bvh" for f in files}
        unknown = sorted(wanted - {r["file"] for r in rows})
        if unknown:
            raise ValueError(f"not in the manifest: {unknown[:5]}")
        rows = [r for r in rows if r["file"] in wanted]
    if contents is not None:
        rows = [r for r in rows if r["content"] in set(contents)]
    return rows


def _try_urls(
    row: dict, base_url: str, timeout: float, size: int
) -> tuple[bytes | None, str, bool, int]:
    """One try of the row's URLs (``source_path``, then the flat ``file``): (data, problem,
    unreachable, 404 count). ``data`` is None unless a body of at most ``size`` bytes
    matched the checksum; ``unreachable`` says the last URL tried could not be reached."""
    problem, not_found = "", 0
    for url in (base_url + row["source_path"], base_url + row["file"]):
        try:
            data = _fetch(url, timeout, size)
        except urllib.error.HTTPError as err:
            problem = f"HTTP {err.code} for {url}"
            if err.code == 404:
                not_found += 1
                continue
            return None, problem, False, not_found
        except _TooLarge as err:
            problem = str(err)
            continue
        except (urllib.error.URLError, OSError, TimeoutError) as err:
            reason = getattr(err, "reason", err)
            return None, f"cannot reach {url}: {reason}", True, not_found
        if git_blob_sha1(data) != row["git_blob_sha1"]:
            problem = f"checksum mismatch for {url} (expected git blob {row['git_blob_sha1']})"
            continue
        return data, problem, False, not_found
    return None, problem, False, not_found


def _fetch_row(
    row: dict, base_url: str, timeout: float, retries: int, size: int
) -> tuple[bytes | None, str, bool]:
    """The verified bytes of one manifest row, or None after ``retries`` further tries
    (sleeping 0.5, 1, 2, 2.. s between them; no retry once every URL gave 404), with the
    last problem and whether the server was unreachable."""
    data, problem, unreachable = None, "", False
    for attempt in range(retries + 1):
        data, problem, unreachable, not_found = _try_urls(row, base_url, timeout, size)
        if data is not None or not_found == 2:
            break
        if attempt < retries:
            time.sleep(min(0.5 * 2.0**attempt, 2.0))
    return data, problem, unreachable


def _save(target: Path, data: bytes) -> None:
    """Write ``data`` to ``target`` atomically (through a ``.part`` file)."""
    tmp = target.with_suffix(target.suffix + ".part")
    tmp.write_bytes(data)
    os.replace(tmp, target)


def _finish(
    out: Path, manifest: Path, total: int, failures: list[str], summary: dict, progress
) -> None:
    """Copy the manifest the files were checked against beside them, then raise on
    ``failures`` or, with ``progress=True``, print the summary line with the attribution."""
    shutil.copyfile(manifest, out / "manifest.csv")
    if failures:
        raise MotionDataError(
            f"{len(failures)} of {total} file(s) failed: {failures[:3]}; check the network "
            "or --url and run the same command again (valid files are kept and skipped)",
            path=str(out),
        )
    if progress is True:
        print(
            f"{summary['downloaded']} downloaded, {summary['skipped']} already present in "
            f"{out}. Data: {ATTRIBUTION}.",
            file=sys.stderr,
        )


def download_bandai(
    dest: str | os.PathLike,
    *,
    base_url: str = BASE_URL,
    progress: bool | Callable[[dict], None] = True,
    files: list[str] | None = None,
    contents: list[str] | None = None,
    timeout: float = 10.0,
    retries: int = 2,
    manifest: str | os.PathLike | None = None,
) -> dict:
    """Fetch the manifest's files into ``dest`` and verify them.

    Args:
      dest: target folder (created).
      base_url: where the repository's files live (default: GitHub raw at the pinned commit).
      progress: True prints one line per file to stderr; a callable gets a dict
        (index, total, file, status, bytes); False is silent.
      files: only these file names (default all); contents: only these contents (walk, run..).
      timeout: seconds per request; retries: further tries per file. A server that cannot
        be reached at all stops the whole download after the first file's tries.
      manifest: the manifest CSV (default: the packaged one); every ``file`` entry must be
        a plain file name (nothing is written outside ``dest``).
    Returns:
      {"dest", "downloaded", "skipped", "total", "bytes"}.
    Raises:
      MotionDataError: a file could not be fetched or failed its checksum (after retries);
        files fetched before stay, verified, and are skipped on the next call.
    """
    report = _print_progress if progress is True else (progress or (lambda event: None))
    if not base_url.endswith("/"):
        base_url += "/"
    rows = _select(_manifest_rows(manifest), files, contents)
    out = Path(dest)
    if out.exists() and not out.is_dir():
        raise MotionDataError("is a file, not a folder; give --dest a folder path", path=str(out))
    out.mkdir(parents=True, exist_ok=True)
    summary = {"dest": str(out), "downloaded": 0, "skipped": 0, "total": len(rows), "bytes": 0}
    failures = []
    for i, row in enumerate(rows, 1):
        target = out / row["file"]
        size = int(row["bytes"])
        event = {"index": i, "total": len(rows), "file": row["file"], "bytes": size}
        if file_is_valid(target, row["git_blob_sha1"], size):
            summary["skipped"] += 1
            report(dict(event, status="present, checksum ok (skipped)"))
            continue
        data, problem, unreachable = _fetch_row(row, base_url, timeout, retries, size)
        if data is None and unreachable:
            raise MotionDataError(
                f"{problem} (after {retries + 1} tries, {timeout:g} s timeout each); check the "
                f"network or --url and run the same command again ({summary['downloaded']} "
                "file(s) fetched before are kept and skipped next time)",
                path=str(out),
            )
        if data is None:
            failures.append(f"{row['file']}: {problem}")
            report(dict(event, status=f"FAILED ({problem})"))
            continue
        _save(target, data)
        summary["downloaded"] += 1
        summary["bytes"] += len(data)
        report(dict(event, status="downloaded, checksum ok"))
    _finish(out, Path(manifest or MANIFEST), len(rows), failures, summary, progress)
    return summary
