"""`blockloc map serve`: read-only, no path traversal, ETag/Last-Modified/304, HEAD, Range, CLI."""

from __future__ import annotations

import http.client
import os
import signal
import subprocess
import sys
import time

import pytest

from blockloc.errors import MapError
from blockloc.maps.server import MapServer, _resolve, check_root

from .conftest import write_grid_store


def _request(srv, method, raw_path, headers=None):
    """(status, headers, body) of one request with the path sent exactly as given."""
    conn = http.client.HTTPConnection("127.0.0.1", srv.port, timeout=5)
    try:
        conn.putrequest(method, raw_path, skip_accept_encoding=True)
        for k, v in (headers or {}).items():
            conn.putheader(k, v)
        conn.endheaders()
        r = conn.getresponse()
        return r.status, {k.lower(): v for k, v in r.getheaders()}, r.read()
    finally:
        conn.close()


@pytest.fixture(scope="module")
def jail(tmp_path_factory):
    """A served root with symlinks in and out of it, and a secret file outside it."""
    base = tmp_path_factory.mktemp("jail")
    outside = base / "outside"
    outside.mkdir()
    (outside / "secret.txt").write_text("TOP-SECRET\n")
    root = base / "root"
    write_grid_store(root / "campus", n_tiles=2)
    (root / "campus" / "escape.pcd").symlink_to(outside / "secret.txt")
    (root / "campus" / "escape_dir").symlink_to(outside)
    (root / "campus" / "alias.json").symlink_to(root / "campus" / "manifest.json")
    (root / "campus" / ".hidden.tmp").write_text("partial\n")
    with MapServer(root) as srv:
        yield root, srv


@pytest.mark.parametrize("raw_path", [
    "/../outside/secret.txt",
    "/campus/../../outside/secret.txt",
    "/campus/%2e%2e/%2e%2e/outside/secret.txt",
    "/campus/%2E%2E%2F%2E%2E%2Foutside%2Fsecret.txt",
    "/%2e%2e%2foutside%2fsecret.txt",
    "/campus/..%5c..%5coutside%5csecret.txt",
    "/campus/%252e%252e/%252e%252e/outside/secret.txt",
    "//outside/secret.txt",
    "/campus/escape.pcd",
    "/campus/escape_dir/secret.txt",
    "/campus/escape_dir/",
    "/campus/.hidden.tmp",
    "/campus/%00manifest.json",
    "/campus/%ff%fe",
])
def test_path_traversal_is_refused(jail, raw_path):
    root, srv = jail
    status, _, body = _request(srv, "GET", raw_path)
    assert status in (403, 404), raw_path
    assert b"TOP-SECRET" not in body


def test_symlink_escape_is_403_and_inside_link_is_served(jail):
    root, srv = jail
    assert _request(srv, "GET", "/campus/escape.pcd")[0] == 403
    status, _, body = _request(srv, "GET", "/campus/alias.json")
    assert status == 200 and body == (root / "campus" / "manifest.json").read_bytes()
    status, _, listing = _request(srv, "GET", "/campus/")
    assert status == 200 and b"manifest.json" in listing
    assert b"escape" not in listing and b".hidden" not in listing


def test_resolve_unit(tmp_path):
    root = tmp_path.resolve()
    assert _resolve(root, "/a/b.pcd") == (200, root / "a" / "b.pcd")
    assert _resolve(root, "/a/%2e%2e/b")[0] == 404
    assert _resolve(root, "/a/b?x=/../..") == (200, root / "a" / "b")
    assert _resolve(root, "/")[1] == root


def test_read_only_methods(jail):
    root, srv = jail
    before = (root / "campus" / "manifest.json").read_bytes()
    for method in ("PUT", "POST", "DELETE", "PATCH"):
        assert _request(srv, method, "/campus/manifest.json")[0] == 405
    assert (root / "campus" / "manifest.json").read_bytes() == before


def test_etag_last_modified_conditional_head_range(jail):
    root, srv = jail
    path = "/campus/manifest.json"
    data = (root / "campus" / "manifest.json").read_bytes()
    status, h, body = _request(srv, "GET", path)
    assert status == 200 and body == data and h["content-length"] == str(len(data))
    etag, last_modified = h["etag"], h["last-modified"]
    assert etag and last_modified and h["cache-control"] == "no-cache"
    status, h304, body = _request(srv, "GET", path, {"If-None-Match": etag})
    assert status == 304 and body == b"" and h304["etag"] == etag
    status, _, _ = _request(srv, "GET", path, {"If-Modified-Since": last_modified})
    assert status == 304
    assert _request(srv, "GET", path, {"If-None-Match": '"something-else"'})[0] == 200
    status, hh, body = _request(srv, "HEAD", path)
    assert status == 200 and body == b"" and hh["content-length"] == str(len(data)) and hh["etag"] == etag
    status, hr, body = _request(srv, "GET", path, {"Range": "bytes=10-19"})
    assert status == 206 and body == data[10:20] and hr["content-range"] == f"bytes 10-19/{len(data)}"
    # a changed file gets a new ETag, and the old one no longer matches
    f = root / "campus" / "pointcloud_map_metadata.yaml"
    e1 = _request(srv, "HEAD", "/campus/pointcloud_map_metadata.yaml")[1]["etag"]
    st = f.stat()
    os.utime(f, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    status, h2, _ = _request(srv, "GET", "/campus/pointcloud_map_metadata.yaml", {"If-None-Match": e1})
    assert status == 200 and h2["etag"] != e1


def test_check_root(tmp_path):
    with pytest.raises(MapError, match="no such map directory"):
        check_root(tmp_path / "nope")
    (tmp_path / "f.pcd").write_bytes(b"x")
    with pytest.raises(MapError, match="not a directory"):
        check_root(tmp_path / "f.pcd")
    with pytest.raises(MapError, match="nor a directory of map stores"):
        check_root(tmp_path)
    write_grid_store(tmp_path / "a", n_tiles=1)
    assert check_root(tmp_path)[1] == ["a"]
    assert check_root(tmp_path / "a")[1] == [""]


def test_port_in_use_is_a_clear_error(jail):
    root, srv = jail
    other = MapServer(root, port=srv.port)
    try:
        with pytest.raises(MapError, match=f"127.0.0.1:{srv.port}: cannot serve"):
            other.start()
    finally:
        other.stop()
    assert _request(srv, "HEAD", "/campus/manifest.json")[0] == 200  # the first one still serves


@pytest.mark.parametrize("sig, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_cli_serve_subprocess_and_clean_shutdown(tmp_path, sig, code):
    """Served until Ctrl-C / SIGTERM, then stopped as every blockloc command is: exit 130 / 143,
    one line (it exited 0 before: a script could not tell a stop from a finish)."""
    write_grid_store(tmp_path / "campus", n_tiles=1)
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    proc = subprocess.Popen([sys.executable, "-m", "blockloc.cli", "map", "serve",
                             str(tmp_path / "campus"), "--port", "0"],
                            stderr=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env)
    try:
        line = proc.stderr.readline()  # "serving http://127.0.0.1:PORT/"
        assert line.startswith("serving http://127.0.0.1:"), line
        assert proc.stderr.readline().startswith("press Ctrl-C")
        port = int(line.split(":")[2].split("/")[0])
        conn = http.client.HTTPConnection("127.0.0.1", port, timeout=5)
        conn.request("GET", "/manifest.json")
        r = conn.getresponse()
        assert r.status == 200 and b'"kind": "grid"' in r.read()
        conn.close()
        proc.send_signal(sig)
        assert proc.wait(timeout=10) == code
        rest = proc.stderr.read()
        assert rest.strip().splitlines()[-1] == "map server stopped" and "Traceback" not in rest, rest
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)
    bad = subprocess.run([sys.executable, "-m", "blockloc.cli", "map", "serve", str(tmp_path / "nope")],
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and bad.stderr.strip() == f"error: {tmp_path / 'nope'}: no such map directory"
