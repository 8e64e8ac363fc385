"""Fixtures of the fault-injection suite: tiny inputs (built once per test session) and a runner
that calls the ``blockloc`` entry point the way a shell does."""

from __future__ import annotations

import contextlib
import io
import os
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

from . import tiny

REPO = Path(__file__).resolve().parents[2]


@dataclass
class Outcome:
    """What one ``blockloc`` invocation did: exit code, stdout, stderr."""

    code: int
    out: str
    err: str

    @property
    def err_lines(self) -> list[str]:
        """stderr without progress lines (a bar's redraws, ``label: done/total``)."""
        import re

        # a progress bar redraws with \r and leaves its line open: a message may follow on it
        return [ln for ln in re.split(r"[\r\n]+|(?=error: )", self.err) if ln.strip() and not _is_progress(ln)]


def _is_progress(line: str) -> bool:
    import re

    return bool(re.match(r"^[\w .-]+: +(\d+%\|.*|\d+/(\d+|\?)( \(\d+%\))?(, working for \d+ s)?"
                         r"|session \w+, \d+ frames)$", line.strip()))


def cli_in_process(*args: str) -> Outcome:
    """Run ``blockloc ARGS`` in this process through ``blockloc.cli.main`` (argument and
    validation errors: no process start-up per case). An exception escaping ``main`` is a
    traceback the user would have seen: it fails the test."""
    import signal

    from blockloc import cli

    out, err = io.StringIO(), io.StringIO()
    argv = sys.argv
    sys.argv = ["blockloc", *map(str, args)]
    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}  # main() installs its own
    code = 0
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            cli.main()
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    finally:
        sys.argv = argv
        cli._state["debug"] = False
        for s, h in handlers.items():
            signal.signal(s, h)
    return Outcome(code, out.getvalue(), err.getvalue())


_CACHE: list[Path] = []


def blockloc_env(cache: Path | None = None) -> dict:
    """The environment of a ``blockloc`` subprocess: this checkout first on the path, and a
    cache of its own (global-init pyramids of a store are cached by checksum: a case that
    removes a block must find it missing, not cached)."""
    import tempfile

    if not _CACHE:
        _CACHE.append(Path(tempfile.mkdtemp(prefix="blockloc-faults-cache-")))
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]),
               COLUMNS="120", BLOCKLOC_CACHE=str(cache or _CACHE[0]))
    env.pop("FORCE_COLOR", None)
    return env


@pytest.fixture(scope="session", autouse=True)
def _remove_cache():
    yield
    import shutil

    for d in _CACHE:
        shutil.rmtree(d, ignore_errors=True)


def cli_process(*args: str, cwd: Path | None = None, timeout: float = 600, cache: Path | None = None) -> Outcome:
    """Run ``python -m blockloc.cli ARGS`` in a subprocess (stdout/stderr piped); ``cache``: a
    cache directory of its own (default: the session's)."""
    r = subprocess.run([sys.executable, "-m", "blockloc.cli", *map(str, args)], capture_output=True, text=True,
                       cwd=cwd, env=blockloc_env(cache), timeout=timeout)
    return Outcome(r.returncode, r.stdout, r.stderr)


def cli_start(*args: str, cwd: Path | None = None) -> subprocess.Popen:
    """Start ``python -m blockloc.cli ARGS`` (for signals); stdout/stderr piped."""
    return subprocess.Popen([sys.executable, "-m", "blockloc.cli", *map(str, args)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=cwd, env=blockloc_env())


class Running:
    """A ``blockloc`` subprocess whose stderr is read as it comes (progress bars end no line),
    to send it a signal at a chosen moment of its work."""

    def __init__(self, *args: str, cwd: Path | None = None) -> None:
        import threading

        self.proc = subprocess.Popen([sys.executable, "-m", "blockloc.cli", *map(str, args)],
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=cwd, env=blockloc_env())
        self._err = bytearray()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        while chunk := os.read(self.proc.stderr.fileno(), 4096):
            self._err += chunk

    @property
    def err(self) -> str:
        return self._err.decode(errors="replace")

    def wait_for(self, ready, timeout: float = 300.0) -> None:
        """Poll ``ready()`` until true; fails the test if the process ends or time runs out first."""
        import time

        t0 = time.monotonic()
        while not ready():
            if self.proc.poll() is not None:
                pytest.fail(f"ended (exit {self.proc.returncode}) before the moment to signal it: {self.err[-500:]}")
            if time.monotonic() - t0 > timeout:
                self.proc.kill()
                pytest.fail(f"not ready after {timeout} s: {self.err[-500:]}")
            time.sleep(0.05)

    def signal(self, signum: int, timeout: float = 300.0) -> Outcome:
        """Send ``signum``, wait for the end; the outcome (stdout read at the end)."""
        self.proc.send_signal(signum)
        out = self.proc.stdout.read().decode(errors="replace")
        self.proc.wait(timeout)
        self._reader.join(10)
        self.proc.stdout.close()
        self.proc.stderr.close()
        return Outcome(self.proc.returncode, out, self.err)


@pytest.fixture(scope="session")
def tiny_world(tmp_path_factory):
    """A tiny NCLT-layout session (40 scans, 20 m), a longer one (120 scans, 60 m) and the block
    map of the longer one (7 blocks of 8 m), the config file the runs use, and the short session
    as a scan folder. Read-only for the tests: copy what a case corrupts."""
    root = tmp_path_factory.mktemp("tiny")
    session = tiny.write_tiny_session(root / "sess")
    long = tiny.write_tiny_session(root / "long", n_frames=120)
    return {
        "root": root, "session": session, "long": long,
        "map": tiny.build_tiny_map(long, root / "map"),
        "config": tiny.write_config(root / "cfg.yaml"),
        "folder": tiny.write_tiny_scan_folder(root / "folder", session),
    }


@contextlib.contextmanager
def small_fs(where: Path, size: str = "1m", *, fill_from: Path | None = None, read_only: bool = False):
    """A tmpfs of ``size`` mounted at ``where`` (``fill_from``'s tree copied in; ``read_only``:
    remounted read-only after). Needs root and mount(8): skips with the reason otherwise, and
    fails under CI=true (CI runs as root: a skip there would hide the case)."""
    import shutil

    where.mkdir(parents=True, exist_ok=True)
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(where)],
                       capture_output=True, text=True) if shutil.which("mount") else None
    if r is None or r.returncode != 0:
        reason = f"cannot mount a tmpfs at {where} ({r.stderr.strip() if r else 'no mount(8)'}): needs root"
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(reason)
        pytest.skip(reason)
    try:
        if fill_from is not None:
            shutil.copytree(fill_from, where, dirs_exist_ok=True)
        if read_only:
            subprocess.run(["mount", "-o", "remount,ro", str(where)], check=True)
        yield where
    finally:
        subprocess.run(["umount", "-l", str(where)], check=False)


@contextlib.contextmanager
def live_holder():
    """A live process whose command line names blockloc (a run holding an output's lock)."""
    p = subprocess.Popen([sys.executable, "-c", "import time; print(1, flush=True); time.sleep(120)", "blockloc"],
                         stdout=subprocess.PIPE)
    try:
        p.stdout.readline()  # exec done: /proc shows its own command line
        yield p.pid
    finally:
        p.kill()
        p.wait()
        p.stdout.close()
