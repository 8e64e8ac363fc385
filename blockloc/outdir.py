"""Output folders: whose they are, whether they may be replaced, and whether a run can write them.

Ownership. Every directory blockloc writes whole (a map store, a simulated dataset, a session
written by ``write_session``) or fills (a results folder, ``eval --plot``'s folder) carries a
marker file, :data:`MARKER_NAME`, holding a JSON object with blockloc's own key
(``"blockloc_output": 1``), the ``kind`` of output and, for a directory written whole, the list
of ``files`` (relative POSIX paths) blockloc put there. A directory is blockloc's of a kind only
when the marker's *content* says so; the file name alone proves nothing, and no file name another
program uses (``manifest.json``, ``metrics.json``) is taken for proof.

Folders written before the marker existed are proven by their kind's own format instead
(:func:`_legacy_files`): a map store by a manifest with blockloc's ``version`` / ``kind`` /
``entries`` (each entry with ``file`` and ``sha256``), a results folder by a ``metrics.json``
object with ``frames`` / ``processed`` / ``estimated``, a simulated dataset by a ``sim.json``
object with ``preset`` / ``seed`` / ``sessions``, a session by ``blockloc_session.json`` with its
extrinsics. What such a folder may hold is then what that format lists.

A directory is replaced only when it is absent, empty, or blockloc's of the kind the command
writes and holding no file blockloc did not write (:func:`check_replaceable`: a foreign file is
named in the error, nothing is deleted).

Pre-checks before any work (:func:`claim_output`): the folder can be written (a probe file is
created and removed: permission bits say nothing to root or to a read-only mount), the file
system has the free space the run needs, and no other blockloc process uses the folder (a lock
file ``.NAME.blockloc-lock`` beside it names the holder's PID; taken over when that process is
gone).
"""

from __future__ import annotations

import json
import logging
import os
import shutil
from pathlib import Path

from blockloc.errors import BlocklocError

log = logging.getLogger(__name__)

#: The marker file of a directory blockloc made.
MARKER_NAME = ".blockloc-output.json"
#: The key (and its value) that makes a marker blockloc's.
MARKER_KEY, MARKER_VERSION = "blockloc_output", 1

#: Kinds of output.
MAP_STORE, SIM_DATASET, RESULTS, SESSION, PLOTS = ("map store", "simulated dataset", "results folder",
                                                   "session", "plot folder")
DYNAMIC_MAP = "dynamicmap export"  # ``blockloc export dynamicmap``: the DynamicMap Benchmark layout
KINDS = (MAP_STORE, SIM_DATASET, RESULTS, SESSION, PLOTS, DYNAMIC_MAP)

#: Files a results folder holds (a run writes them in place, so its marker lists no files).
RESULT_NAMES = frozenset({"poses.tum", "diagnostics.csv", "config.yaml", "poses_kitti.txt",
                          "poses_kitti.times.txt", "metrics.json", "trajectories.png", "errors.png",
                          "error_breakdown.png", "report.html", "run.mcap", "foxglove_layout.json",
                          "live.json", ".reserve", "changes.json"})
#: Files ``eval --plot`` writes.
PLOT_NAMES = frozenset({"trajectories.png", "errors.png", "error_breakdown.png"})
_KIND_NAMES = {RESULTS: RESULT_NAMES, PLOTS: PLOT_NAMES}


# ----------------------------------------------------------------------------- ownership
def write_marker(directory: str | Path, kind: str, files: list[str] | None = None) -> Path:
    """Write ``directory``'s marker: blockloc made it, as ``kind``. ``files``: the relative paths it
    holds (None: list the directory now, for one written whole; a kind filled in place (results,
    plots) lists none: its file names are the kind's)."""
    directory = Path(directory)
    if files is None and kind not in _KIND_NAMES:
        files = sorted(p.relative_to(directory).as_posix() for p in directory.rglob("*")
                       if not p.is_dir() and p.name != MARKER_NAME)
    doc = {MARKER_KEY: MARKER_VERSION, "kind": kind, "files": files}
    path = directory / MARKER_NAME
    tmp = directory / f".{MARKER_NAME}.{os.getpid()}.tmp"
    tmp.write_text(json.dumps(doc, indent=1) + "\n")
    os.replace(tmp, path)
    return path


def read_marker(directory: str | Path) -> dict | None:
    """The marker of ``directory`` when it is blockloc's (its content checked), else None."""
    try:
        doc = json.loads((Path(directory) / MARKER_NAME).read_text())
    except (OSError, ValueError, UnicodeDecodeError):
        return None
    if not isinstance(doc, dict) or doc.get(MARKER_KEY) != MARKER_VERSION or doc.get("kind") not in KINDS:
        return None
    files = doc.get("files")
    if files is not None and not (isinstance(files, list) and all(isinstance(f, str) for f in files)):
        return None
    return doc


def _json_object(path: Path) -> dict | None:
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError, UnicodeDecodeError):
        return None
    return doc if isinstance(doc, dict) else None


def _legacy_files(directory: Path) -> tuple[str, set[str] | None] | None:
    """(kind, the files that kind's format lists, or None: any name of the kind's) for a folder
    written before markers, proven blockloc's by its format; None when nothing proves it."""
    m = _json_object(directory / "manifest.json")
    if m is not None and isinstance(m.get("version"), int) and m.get("kind") in ("block", "grid") \
            and isinstance(m.get("entries"), list) \
            and all(isinstance(e, dict) and isinstance(e.get("file"), str) and "sha256" in e for e in m["entries"]):
        extras = m.get("extras") if isinstance(m.get("extras"), dict) else {}
        names = {"manifest.json", "CentroidCloud.pcd", "pointcloud_map_metadata.yaml"}
        names |= {e["file"] for e in m["entries"]}
        names |= {x.get("file") for x in extras.values() if isinstance(x, dict) and isinstance(x.get("file"), str)}
        return MAP_STORE, names
    r = _json_object(directory / "metrics.json")
    if r is not None and all(k in r for k in ("frames", "processed", "estimated")):
        return RESULTS, None
    s = _json_object(directory / "sim.json")
    if s is not None and "preset" in s and "seed" in s and isinstance(s.get("sessions"), dict):
        # its sessions' trees are blockloc's (each session is checked no further)
        sessions = list(s["sessions"])
        names = {"sim.json"}
        for p in directory.rglob("*"):
            rel = p.relative_to(directory).as_posix()
            top = rel.split("/")[0]
            if any(top == n or top.startswith((f"{n}.", f"{n}_")) for n in sessions):
                names.add(rel)
        return SIM_DATASET, names
    d = _json_object(directory / "blockloc_session.json")
    if d is not None and all(k in d for k in ("T_body_lidar", "T_body_imu", "gravity_map")):
        names = {p.relative_to(directory).as_posix() for p in directory.rglob("*")
                 if p.relative_to(directory).parts[0] == "velodyne_sync"}
        names |= {"blockloc_session.json", "ms25.csv", "velodyne_hits.bin"}
        names |= {p.name for p in directory.glob("groundtruth_*.csv")} | {p.name for p in directory.glob("slam_poses_*.csv")}
        return SESSION, names
    return None


def owner(directory: str | Path) -> tuple[str, set[str] | None] | None:
    """(kind, the files blockloc wrote there or None: any of the kind's names) when ``directory``
    is blockloc's output (marker, else a format that proves it), else None."""
    directory = Path(directory)
    if not directory.is_dir() or directory.is_symlink():
        return None
    doc = read_marker(directory)
    legacy = _legacy_files(directory)
    if doc is not None:
        files = doc.get("files")
        if files is None:
            return doc["kind"], None
        files = set(files) | {MARKER_NAME}
        if legacy is not None and legacy[0] == doc["kind"] and legacy[1] is not None:
            files |= legacy[1]  # files its format lists that came later (a store's extras: map index)
        return doc["kind"], files
    return legacy


def _is_temp_of(name: str, names) -> bool:
    """A temp file blockloc's atomic writes leave after a kill (``.NAME.XXXX.tmp``, ``NAME.partial``)."""
    base = name.rsplit("/", 1)[-1]
    return (base.endswith(".partial") and base[: -len(".partial")] in names) or (
        base.startswith(".") and base.endswith(".tmp") and any(base.startswith(f".{n}.") for n in names))


def foreign_files(directory: str | Path, kind: str, files: set[str] | None) -> list[str]:
    """Files in ``directory`` (relative paths, sorted) that blockloc did not write there."""
    directory = Path(directory)
    names = set(files) if files is not None else set(_KIND_NAMES.get(kind, ())) | {MARKER_NAME}
    # a folder filled in place (results) may hold blockloc's own plot folders (`eval --plot RUN/eval`):
    # their files are blockloc's when the sub-folder is, and holds nothing else
    own_subdirs = set()
    if files is None:
        for sub in directory.iterdir():
            o = owner(sub) if sub.is_dir() and not sub.is_symlink() else None
            if o is not None and o[0] in (PLOTS, RESULTS) and not foreign_files(sub, o[0], o[1]):
                own_subdirs.add(sub.name)
    out = []
    for p in sorted(directory.rglob("*")):
        if p.is_dir() and not p.is_symlink():
            continue
        rel = p.relative_to(directory).as_posix()
        if files is None and "/" in rel:
            if rel.split("/", 1)[0] not in own_subdirs:
                out.append(rel)
        elif rel not in names and not _is_temp_of(rel if files is not None else p.name, names):
            out.append(rel)
    return out


def is_blockloc_output(path: str | Path, kinds: tuple[str, ...] = KINDS) -> bool:
    """True for an empty directory or one blockloc made as one of ``kinds``."""
    path = Path(path)
    if not path.is_dir() or path.is_symlink():
        return False
    if not any(path.iterdir()):
        return True
    o = owner(path)
    return o is not None and o[0] in kinds


def check_replaceable(path: str | Path, option: str = "--out", kinds: tuple[str, ...] = KINDS,
                      kind: str | None = None) -> None:
    """Before any work that replaces ``path`` (or writes into it): BlocklocError, one line naming
    ``option`` and ``path``, unless it is absent, an empty directory, or a directory blockloc made
    as one of ``kinds`` (``kind``: what they are called, e.g. "a map store") holding no file
    blockloc did not write (those are named)."""
    path = Path(path)
    if path.is_symlink() or (path.exists() and not path.is_dir()):
        raise BlocklocError(f"{option} {path}: exists and is not a directory; blockloc replaces only "
                            "directories it made (choose another path)")
    if path.is_dir() and any(path.iterdir()):
        o = owner(path)
        if o is None:
            raise BlocklocError(f"{option} {path}: a directory blockloc did not make (no {MARKER_NAME} of "
                                "blockloc's); not replacing it (choose another path or empty it)")
        if o[0] not in kinds:
            raise BlocklocError(f"{option} {path}: not {kind or ' / '.join(kinds)} (it is blockloc's {o[0]}); "
                                "not replacing it (choose another path)")
        foreign = foreign_files(path, o[0], o[1])
        if foreign:
            shown = ", ".join(foreign[:5]) + (f" and {len(foreign) - 5} more" if len(foreign) > 5 else "")
            raise BlocklocError(f"{option} {path}: holds files blockloc did not write ({shown}); not replacing "
                                "it (move them out or choose another path)")
    check_output_parent(path, option)


def check_file_replaceable(path: str | Path, option: str, ours, what: str) -> None:
    """Before any work that writes the single file ``path`` (``map plot --out``, ``map changes
    --out``): BlocklocError, one line naming ``option``, when a file is there that ``ours(path)``
    does not recognise as blockloc's ``what`` (a user's figure or notes are never replaced)."""
    path = Path(path)
    if path.is_file() and not ours(path):
        raise BlocklocError(f"{option} {path}: a file blockloc did not write (not one of {what} it writes); "
                            "not replacing it (choose another path, or remove it)")


# ----------------------------------------------------------------------------- pre-checks
def check_output_parent(path: str | Path, option: str = "--out") -> None:
    """BlocklocError unless every existing ancestor of ``path`` is a directory (so that
    ``mkdir(parents=True)`` can make the rest)."""
    for parent in Path(path).absolute().parents:
        if parent.exists():
            if not parent.is_dir():
                raise BlocklocError(f"{option} {path}: {parent} is a file, not a directory")
            return


def _existing_ancestor(path: Path) -> Path:
    p = path.absolute()
    while not p.exists():
        p = p.parent
    return p


def check_writable(path: str | Path, option: str = "--out") -> None:
    """BlocklocError naming ``option`` unless files can be created where ``path`` is (in it when it
    is a directory, else in its nearest existing ancestor): a probe file is made and removed."""
    import tempfile

    where = _existing_ancestor(Path(path))
    if not where.is_dir():  # a file to be replaced: its directory is where the new one is made
        where = where.parent
    try:
        fd, probe = tempfile.mkstemp(prefix=".blockloc-probe-", dir=where)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise BlocklocError(f"{option} {path}: cannot write in {where} ({exc.strerror or exc})") from None


def check_free_space(path: str | Path, need_bytes: int, option: str = "--out") -> None:
    """BlocklocError naming ``option`` when the file system of ``path`` has less than
    ``need_bytes`` free (an estimate of what the run writes)."""
    where = _existing_ancestor(Path(path))
    free = shutil.disk_usage(where).free
    if free < need_bytes:
        raise BlocklocError(f"{option} {path}: {free / 2**20:.1f} MiB free on its file system, the run "
                            f"needs about {need_bytes / 2**20:.1f} MiB (free space or choose another {option})")


def process_alive(pid: int) -> bool:
    """True when a process ``pid`` exists (this one included; another user's counts)."""
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process
        return True
    return True


def _process_is_blockloc(pid: int) -> bool:
    """True when ``pid`` runs (and, where /proc tells, runs blockloc: a reused PID is not a holder)."""
    if not process_alive(pid):
        return False
    if pid == os.getpid():
        return True
    try:
        cmd = Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return True
    return b"blockloc" in cmd


class OutputLock:
    """The lock of one output path: the file ``.NAME.blockloc-lock`` beside it, holding
    ``pid N``. :meth:`acquire` raises BlocklocError naming the holder when another live blockloc
    process holds it and takes it over from a process that is gone."""

    def __init__(self, path: str | Path, option: str = "--out") -> None:
        self.path = Path(path)
        self.option = option
        self.file = self.path.absolute().parent / f".{self.path.name}.blockloc-lock"
        self.held = False

    def holder(self) -> int | None:
        try:
            return int(self.file.read_text().split()[1])
        except (OSError, ValueError, IndexError):
            return None

    def acquire(self) -> "OutputLock":
        self.file.parent.mkdir(parents=True, exist_ok=True)
        remove_dead_locks(self.file.parent)
        text = f"pid {os.getpid()}\n"
        for _ in range(3):
            try:
                fd = os.open(self.file, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
            except FileExistsError:
                pid = self.holder()
                if pid is not None and pid != os.getpid() and _process_is_blockloc(pid):
                    raise BlocklocError(f"{self.option} {self.path}: in use by another blockloc run (process {pid}); "
                                        "wait for it to end or choose another path") from None
                # the holder is gone (killed: nothing removed its lock), or it is this process
                log.info("%s: taking over the lock of process %s", self.file, pid)
                self.file.unlink(missing_ok=True)
                continue
            with os.fdopen(fd, "w") as fh:
                fh.write(text)
            self.held = True
            return self
        raise BlocklocError(f"{self.option} {self.path}: cannot take its lock {self.file}")

    def release(self) -> None:
        if self.held and self.holder() == os.getpid():
            self.file.unlink(missing_ok=True)
        self.held = False

    def __enter__(self) -> "OutputLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


def remove_dead_locks(parent: str | Path) -> list[Path]:
    """Remove the ``.NAME.blockloc-lock`` files in ``parent`` whose process is gone (a run killed
    with SIGKILL could not remove its own); returns what was removed."""
    removed = []
    for f in Path(parent).glob(".*.blockloc-lock"):
        try:
            pid = int(f.read_text().split()[1])
        except (OSError, ValueError, IndexError):
            continue
        if not _process_is_blockloc(pid):
            f.unlink(missing_ok=True)
            removed.append(f)
    return removed


#: Locks taken by :func:`claim_output`, released by :func:`release_outputs` (the CLI's exit).
_HELD: list[OutputLock] = []


def claim_output(path: str | Path, option: str = "--out", *, need_bytes: int = 0,
                 kinds: tuple[str, ...] | None = None, kind: str | None = None) -> OutputLock:
    """Every pre-check of an output before any work: replaceable (when ``kinds`` is given),
    writable, ``need_bytes`` free, not in use by another blockloc run (its lock is taken and held
    until :func:`release_outputs` or the process's end)."""
    import atexit

    if kinds is not None:
        check_replaceable(path, option, kinds, kind)
    check_writable(path, option)
    if need_bytes:
        check_free_space(path, need_bytes, option)
    lock = OutputLock(path, option).acquire()
    if not _HELD:
        atexit.register(release_outputs)
    _HELD.append(lock)
    return lock


def release_outputs() -> None:
    """Release every lock :func:`claim_output` took."""
    while _HELD:
        _HELD.pop().release()


def is_blockloc_link(link: str | Path, kind: str = RESULTS) -> bool:
    """True when ``link`` is a symlink blockloc may repoint: it points (relatively, to a name
    beside it) at a directory blockloc made as ``kind``. A user's link elsewhere, a dangling link
    or anything else is left alone."""
    link = Path(link)
    if not link.is_symlink():
        return False
    target = os.readlink(link)
    if "/" in target.rstrip("/"):
        return False
    o = owner(link.parent / target)
    return o is not None and o[0] == kind
