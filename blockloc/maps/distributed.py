"""Map builds on a Dask cluster: the build plan's tasks (:mod:`blockloc.maps.build_plan`) run as
Dask tasks.

``open_executor("local:4")`` starts a ``LocalCluster`` of 4 worker processes (one thread each:
the tasks are numpy-bound) and closes it afterwards; ``open_executor("tcp://host:8786")``
connects to a running scheduler (``dask scheduler`` + ``dask worker``, dask-jobqueue, Kubernetes)
and leaves it running; ``open_executor(None)`` is the serial build in this process.

Workers must import the same blockloc (same version, same ``PYTHONPATH``) and reach the build's
output: a local path shared by every worker (one machine, or a shared file system), or an
object-store URL (``s3://...``, credentials in the workers' environment). Dask reruns the tasks
of a worker that dies (up to ``distributed.scheduler.allowed-failures`` times per task); the
plan's tasks are idempotent, so the build still writes the same bytes.
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import time
from typing import Iterator

from blockloc.errors import MapError

log = logging.getLogger(__name__)

_LOCAL = re.compile(r"^local:(\d+)$")


class DaskExecutor:
    """Submits plan tasks to a ``distributed.Client`` (the executor interface of the plan)."""

    def __init__(self, client, description: str) -> None:
        self.client = client
        self.description = description
        self._workers: list[str] | None = None  # worker addresses, read at the first located task

    @property
    def dashboard_link(self) -> str | None:
        """The Dask dashboard's URL (None without one; it needs the bokeh package)."""
        if not _has_bokeh():
            return None
        try:
            return self.client.dashboard_link
        except Exception:  # the scheduler runs without a dashboard
            return None

    def submit(self, fn, *args, key: str | None = None, priority: int = 0, locality: float | None = None):
        """locality in [0, 1) (optional): a soft preference for the worker owning that share of the
        build, so that neighbouring runs of a drive share one worker's scene windows instead of
        every worker building every window; Dask may still run the task elsewhere."""
        # pure=False: every build gets fresh tasks (keys carry the build's id)
        if locality is None:
            return self.client.submit(fn, *args, key=key, priority=priority, pure=False)
        if self._workers is None:
            self._workers = sorted(self.client.scheduler_info().get("workers", {}))
        if not self._workers:
            return self.client.submit(fn, *args, key=key, priority=priority, pure=False)
        w = self._workers[min(int(locality * len(self._workers)), len(self._workers) - 1)]
        return self.client.submit(fn, *args, key=key, priority=priority, pure=False, workers=[w],
                                  allow_other_workers=True)

    def on_each_worker(self, fn, args_of, *, key: str) -> list:
        """Submit ``fn(*args_of(i, n))`` once to each of the ``n`` workers now connected (worker
        ``i`` pinned): e.g. open on each worker the drive it will read first, instead of on its
        first task."""
        workers = sorted(self.client.scheduler_info().get("workers", {}))
        return [self.client.submit(fn, *args_of(i, len(workers)), key=f"{key}-{i}", workers=[w],
                                   allow_other_workers=False, priority=100, pure=False)
                for i, w in enumerate(workers)]

    def cancel(self, futures, wait_s: float = 60.0) -> None:
        """Cancel the build's tasks and wait (up to ``wait_s``) until none of them still runs, so
        that none writes into a build directory being removed."""
        from distributed import Future

        futs = [f for f in futures if isinstance(f, Future)]
        if not futs:
            return
        keys = {f.key for f in futs}
        try:
            self.client.cancel(futs)
            deadline = time.monotonic() + wait_s
            while time.monotonic() < deadline:
                running = {k for ks in self.client.processing().values() for k in ks}
                if not running & keys:
                    return
                time.sleep(0.2)
            log.warning("%d build task(s) still running after cancel", len(running & keys))
        except Exception as exc:  # the scheduler went away: nothing left to cancel
            log.debug("cancel: %s", exc)

    def worker_info(self) -> dict[str, dict]:
        """Worker address -> {pid, peak_rss_mb, cpu_s}: each worker process's own figures."""
        return self.client.run(_worker_info)


def _worker_info() -> dict:
    import os

    import psutil

    from blockloc.resources import peak_rss_mb

    t = psutil.Process().cpu_times()
    return {"pid": os.getpid(), "peak_rss_mb": peak_rss_mb(), "cpu_s": t.user + t.system}


_SPAWN_ENV = "distributed.nanny.pre-spawn-environ"
#: Worker settings of the clusters blockloc starts: no statistical profiler (it samples the task
#: thread's stack every 10 ms for the dashboard's profile page; the task stream stays).
WORKER_CONFIG = {"distributed.worker.profile.enabled": False}


def _spawn_environ() -> dict:
    """The environment Dask's nanny gives its workers, without ``MALLOC_TRIM_THRESHOLD_``, and
    with one thread per ray cast (:func:`_worker_environ`).

    Dask sets it to return freed memory to the system early; setting it also switches off
    glibc's adaptive mmap threshold, so every large numpy temporary of a scan is mmapped and
    page-faulted afresh: a ray-cast and deskewed keyframe cost 60% more CPU (system time) in such
    a worker than in a plain process (campus scans, measured). Workers started by ``dask worker``
    get it from their nanny too: start them with ``--no-nanny`` (as :class:`ProcessCluster`
    does), or with a Dask config whose ``distributed.nanny.pre-spawn-environ`` lacks it."""
    import dask

    env = {k: v for k, v in (dask.config.get(_SPAWN_ENV, None) or {}).items()
           if k != "MALLOC_TRIM_THRESHOLD_"}
    return {**env, **_worker_environ(os.environ)}


def _worker_environ(parent) -> dict:
    """Variables for the single-threaded worker processes blockloc starts: the simulator casts
    rays in one thread (``blockloc.threads.RAYCAST_THREADS_ENV``; open3d's default, every core,
    ran ~9% of a worker's scan CPU in threads its task timer does not see, contending with the
    other workers, and cost ~3% more CPU in all), unless ``parent`` (the environment they
    inherit) sets it."""
    from blockloc.threads import RAYCAST_THREADS_ENV

    return {} if RAYCAST_THREADS_ENV in parent else {RAYCAST_THREADS_ENV: "1"}


def _has_bokeh() -> bool:
    import importlib.util

    return importlib.util.find_spec("bokeh") is not None


@contextlib.contextmanager
def _quiet_distributed() -> Iterator[None]:
    """distributed logs every start and stop at INFO (and a worker it has to kill at close on a
    busy machine at WARNING); keep that out of the command's output unless debugging."""
    logger = logging.getLogger("distributed")
    old = logger.level
    if not log.isEnabledFor(logging.DEBUG):
        logger.setLevel(logging.ERROR)
    try:
        yield
    finally:
        logger.setLevel(old)


@contextlib.contextmanager
def open_executor(cluster: str | None, *, startup_timeout_s: float = 60.0) -> Iterator:
    """An executor for the build plan: None or '' -> serial in this process; ``local:N`` -> a
    LocalCluster of N single-threaded worker processes, closed on exit; ``tcp://HOST:PORT`` (or
    any scheduler address Dask accepts) -> that scheduler's workers, left running.

    The executor has ``description`` and ``dashboard_link`` (None without a dashboard).
    MapError (one line) for a bad spec or an unreachable scheduler.
    """
    if not cluster:
        from blockloc.maps.build_plan import InlineExecutor

        yield InlineExecutor()
        return
    spec = str(cluster).strip()
    m = _LOCAL.match(spec)
    if m is None and "://" not in spec:
        raise MapError(f"--cluster {spec!r}: expected local:N (N worker processes here) or a "
                       "scheduler address tcp://HOST:PORT")
    try:
        import dask
        from distributed import Client, LocalCluster
    except ImportError:
        raise MapError("--cluster needs dask[distributed] (pip install 'dask[distributed]')") from None
    if m is not None:
        n = int(m.group(1))
        if n < 1:
            raise MapError(f"--cluster {spec!r}: expected at least one worker")
        # quiet for the cluster's whole life: its scheduler and nannies run in this process and
        # log every client, worker and close at INFO
        with _quiet_distributed():
            with dask.config.set({_SPAWN_ENV: _spawn_environ(), **WORKER_CONFIG}):
                lc = LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                  dashboard_address=":0",  # a free port: the machine may be shared
                                  silence_logs=logging.CRITICAL)  # task errors reach the client
            with lc, Client(lc) as client:
                yield DaskExecutor(client, f"local cluster of {n} worker process(es)")
        return
    try:
        client = Client(spec, timeout=f"{startup_timeout_s}s")
    except (OSError, TimeoutError) as exc:
        raise MapError(f"--cluster {spec}: cannot reach the Dask scheduler ({exc})") from None
    try:
        n = len(client.scheduler_info().get("workers", {}))
        if n == 0:
            log.warning("%s: the scheduler has no worker yet; tasks wait for one", spec)
        yield DaskExecutor(client, f"Dask scheduler {spec} ({n} worker(s))")
    finally:
        client.close()


class ProcessCluster:
    """A Dask cluster of separate processes on this machine, started with the ``dask scheduler``
    and ``dask worker`` command lines (``python -m dask ...``, this interpreter), each worker
    single-threaded and without a nanny, so that every worker is one process with a known PID.
    For tests and benchmarks: ``stop()`` ends each process by its PID.

    workdir: where the scheduler file and the processes' logs go. env: their environment
    (default: this process's, so they import the same blockloc).
    """

    def __init__(self, n_workers: int, workdir, *, host: str = "127.0.0.1", env: dict | None = None,
                 timeout_s: float = 120.0) -> None:
        import json
        import os
        import subprocess
        import sys
        from pathlib import Path

        env = dict(os.environ if env is None else env)
        env.setdefault("DASK_DISTRIBUTED__WORKER__PROFILE__ENABLED", "False")  # WORKER_CONFIG
        env.update(_worker_environ(env))
        self.workdir = Path(workdir)
        self.workdir.mkdir(parents=True, exist_ok=True)
        self.scheduler_file = self.workdir / "scheduler.json"
        self.scheduler_file.unlink(missing_ok=True)
        self.host = host
        self._env = env
        self._timeout_s = timeout_s
        self._logs: list = []
        self.workers: list[subprocess.Popen] = []
        self.scheduler = self._spawn("scheduler", [sys.executable, "-m", "dask", "scheduler",
                                                   "--host", host, "--port", "0", "--no-dashboard",
                                                   "--scheduler-file", str(self.scheduler_file)])
        try:
            deadline = time.monotonic() + timeout_s
            while True:
                if self.scheduler.poll() is not None:
                    raise MapError(f"dask scheduler exited ({self.scheduler.returncode}); see "
                                   f"{self.workdir / 'scheduler.log'}")
                try:
                    self.address = json.loads(self.scheduler_file.read_text())["address"]
                    break
                except (OSError, ValueError, KeyError):
                    if time.monotonic() > deadline:
                        raise MapError("dask scheduler did not start in time") from None
                    time.sleep(0.2)
            for _ in range(n_workers):
                self.add_worker()
            self.wait_for_workers(n_workers)
        except BaseException:
            self.stop()
            raise

    def _spawn(self, name: str, cmd: list[str]):
        import subprocess

        log_file = open(self.workdir / f"{name}.log", "ab")
        self._logs.append(log_file)
        return subprocess.Popen(cmd, stdout=log_file, stderr=subprocess.STDOUT, env=self._env,
                                cwd=self.workdir)

    def add_worker(self):
        """Start one more worker process; returns its Popen."""
        import sys

        i = len(self.workers)
        p = self._spawn(f"worker-{i}", [sys.executable, "-m", "dask", "worker",
                                        "--scheduler-file", str(self.scheduler_file),
                                        "--nthreads", "1", "--no-nanny", "--no-dashboard",
                                        "--host", self.host, "--name", f"worker-{i}"])
        self.workers.append(p)
        return p

    def wait_for_workers(self, n: int) -> None:
        from distributed import Client

        with Client(self.address, timeout=f"{self._timeout_s}s") as client:
            client.wait_for_workers(n, timeout=self._timeout_s)

    @property
    def worker_pids(self) -> list[int]:
        return [p.pid for p in self.workers if p.poll() is None]

    def stop(self) -> None:
        """Terminate every process by its PID (kill what does not exit within 5 s)."""
        import subprocess

        for p in self.workers + [self.scheduler]:
            if p.poll() is None:
                p.terminate()
        for p in self.workers + [self.scheduler]:
            try:
                p.wait(5)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(10)
        for f in self._logs:
            f.close()

    def __enter__(self) -> "ProcessCluster":
        return self

    def __exit__(self, *exc) -> None:
        self.stop()
