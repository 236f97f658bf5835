"""Bandai downloader against a local HTTP server serving ../shared/data."""

from __future__ import annotations

import functools
import http.server
import threading
from pathlib import Path

import pytest

from motionflows.data.datasets import bandai_manifest
from motionflows.data.download import BASE_URL, COMMIT, download_bandai, git_blob_sha1
from motionflows.errors import MotionDataError

SHARED = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"


def test_git_blob_sha1_known_value():
    # `git hash-object` of "hello\n"
    assert git_blob_sha1(b"hello\n") == "ce013625030ba8dba906f756967f9e9ca394464a"
    assert COMMIT in BASE_URL and BASE_URL.startswith("https://raw.githubusercontent.com/")


FOLDERS = ("bandai_locomotion_dev", "bandai_locomotion_extra")


def test_packaged_manifest_matches_shared_copy():
    rows = bandai_manifest()
    assert len(rows) == 249 + 496 and {"file", "source_path", "git_blob_sha1"} <= set(rows[0])
    shared = [SHARED / f / "manifest.csv" for f in FOLDERS]
    if all(p.exists() for p in shared):  # the dev rows, then the extra takes' rows
        assert bandai_manifest(shared[0]) + bandai_manifest(shared[1]) == rows


@pytest.fixture()
def server(tmp_path_factory):
    """A flat mirror (every file at the top) of the dev and extra folders."""
    if not all((SHARED / f).is_dir() for f in FOLDERS):
        pytest.skip("../shared/data not present")
    mirror = tmp_path_factory.mktemp("mirror") / "bandai_locomotion_dev"
    mirror.mkdir()
    for folder in FOLDERS:
        for bvh in (SHARED / folder).glob("*.bvh"):
            (mirror / bvh.name).symlink_to(bvh.resolve())
    handler = functools.partial(_Quiet, directory=str(mirror.parent))
    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{httpd.server_address[1]}/bandai_locomotion_dev/"
    httpd.shutdown()
    httpd.server_close()


class _Quiet(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args):
        pass


FILES = ["dataset-1_dash_giant_001.bvh", "dataset-1_run_masculinity_001.bvh"]


def test_download_verify_skip_and_repair(server, tmp_path):
    events = []
    result = download_bandai(tmp_path, base_url=server, files=FILES, progress=events.append)
    assert result["downloaded"] == 2 and result["skipped"] == 0
    for name in FILES:
        assert (tmp_path / name).read_bytes() == (
            SHARED / "bandai_locomotion_dev" / name
        ).read_bytes()
    assert (tmp_path / "manifest.csv").exists()
    assert [e["index"] for e in events] == [1, 2]
    again = download_bandai(tmp_path, base_url=server, files=FILES, progress=False)
    assert again["skipped"] == 2 and again["downloaded"] == 0
    # a corrupted file is detected and fetched again
    (tmp_path / FILES[0]).write_bytes(b"garbage")
    fixed = download_bandai(tmp_path, base_url=server, files=FILES, progress=False)
    assert fixed["downloaded"] == 1
    assert git_blob_sha1((tmp_path / FILES[0]).read_bytes()) == next(
        r["git_blob_sha1"] for r in bandai_manifest() if r["file"] == FILES[0]
    )


def test_download_reports_bad_checksum_and_missing(server, tmp_path):
    fake = tmp_path / "mirror" / "bandai_locomotion_dev"
    fake.mkdir(parents=True)
    (fake / FILES[0]).write_bytes(b"not the real file")
    handler = functools.partial(_Quiet, directory=str(tmp_path / "mirror"))
    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=httpd.serve_forever, daemon=True).start()
    try:
        url = f"http://127.0.0.1:{httpd.server_address[1]}/bandai_locomotion_dev/"
        with pytest.raises(MotionDataError, match="checksum mismatch|HTTP 404"):
            download_bandai(tmp_path / "out", base_url=url, files=FILES, progress=False, retries=0)
        assert not (tmp_path / "out" / FILES[0]).exists()
    finally:
        httpd.shutdown()
        httpd.server_close()


def test_cli_download_from_mirror_then_skips(server, tmp_path, monkeypatch, capsys):
    from motionflows.cli import main

    monkeypatch.setenv("MOTIONFLOWS_BANDAI_URL", server)  # the CLI's mirror setting
    assert main(["data", "download", "bandai", "--dest", str(tmp_path)]) == 0
    rows = bandai_manifest()
    for row in rows:
        data = (tmp_path / row["file"]).read_bytes()
        assert git_blob_sha1(data) == row["git_blob_sha1"]
    capsys.readouterr()
    assert main(["data", "download", "bandai", "--dest", str(tmp_path), "--url", server]) == 0
    assert f"0 downloaded, {len(rows)} already present" in capsys.readouterr().err
