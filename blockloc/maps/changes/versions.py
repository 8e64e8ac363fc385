"""Map versions: every update of a store is a new version; any version can be made current again.

Layout (inside a local manifest store)::

    manifest.json          the current version (what every reader opens; its ``lifelong`` key
                           says which version it is)
    versions/v0001.json    the manifest of each version, with ``lifelong``: version, parent,
    versions/v0002.json    created, runs, changed_blocks, held_back, note
    000.pcd 000.v2.pcd ... block files: a changed block gets a new file name per version; a file
                           once written is never rewritten nor removed (an older manifest, a
                           reader mid-way, a rollback still need it)

A version is written completely (its block files, then ``versions/vNNNN.json``) before
``manifest.json`` is replaced by it in one atomic rename: a reader sees the old version or the new
one, never a mix. ``rollback`` replaces ``manifest.json`` by an older version's the same way.
A store without ``versions/`` is version 1 (its history starts when it is first updated).

A store's identity (:func:`map_identity`) is that of its version 1, as built: the same through
its updates and rollbacks, and wherever it is moved or copied to; a run records the identity of
the map it was tracked in (its ``metrics.json``'s ``map_id``).
"""

from __future__ import annotations

import hashlib
import json
import logging
import re
import time
from pathlib import Path

from blockloc.errors import BlocklocError, MapError
from blockloc.fileio import atomic_write_bytes

log = logging.getLogger(__name__)

VERSIONS_DIR = "versions"
_VERSION_FILE = re.compile(r"^v(\d{4,})\.json$")


def _read_manifest(root: Path) -> dict:
    where = root / "manifest.json"
    try:
        return json.loads(where.read_text())
    except (OSError, ValueError) as exc:
        raise MapError(f"{where}: cannot read the manifest ({exc}); expected a local map store") from None


def version_path(root: Path, version: int) -> Path:
    return Path(root) / VERSIONS_DIR / f"v{int(version):04d}.json"


def current_version(root: str | Path) -> int:
    """The version ``manifest.json`` holds (1 for a store never updated)."""
    return int((_read_manifest(Path(root)).get("lifelong") or {}).get("version", 1))


def history(root: str | Path) -> list[dict]:
    """Every version of the store at ``root``, oldest first: its ``lifelong`` record (version,
    parent, created, runs, changed_blocks, held_back, note) plus ``current`` (bool)."""
    root = Path(root)
    cur = current_version(root)
    out = []
    vdir = root / VERSIONS_DIR
    if vdir.is_dir():
        for p in sorted(vdir.iterdir()):
            if _VERSION_FILE.match(p.name):
                try:
                    rec = dict(json.loads(p.read_text()).get("lifelong") or {})
                except (OSError, ValueError) as exc:
                    raise MapError(f"{p}: unreadable version record ({exc})") from None
                rec["current"] = rec.get("version") == cur
                out.append(rec)
    if not out:
        out.append({"version": 1, "parent": None, "note": "as built", "runs": [], "changed_blocks": [],
                    "current": True})
    return out


#: The manifest keys that make a store's identity: what its build wrote (the extras, such as a
#: place index added later, and the lifelong record are left out).
IDENTITY_KEYS = ("kind", "frame", "parameters", "created", "entries")


def map_identity(store) -> str | None:
    """The identity of a manifest store (a :class:`~blockloc.maps.store.MapStore`, local or
    remote): 16 hex digits of the sha256 of its version 1's :data:`IDENTITY_KEYS` (from
    ``versions/v0001.json`` once it was updated, else from ``manifest.json``). None for a store
    in the released layout (no manifest), or updated but without its version 1 at hand (a served
    store's history is not read: no request beyond its manifest)."""
    if getattr(store, "legacy", False):
        return None
    files = store.files
    try:
        first = None if files.is_remote else version_path(Path(files.root), 1)
        if first is not None and first.is_file():
            doc = json.loads(first.read_bytes())
        else:
            doc = json.loads(files.read_bytes("manifest.json"))
            if int((doc.get("lifelong") or {}).get("version", 1)) != 1:
                return None  # an updated store whose history is gone
    except (OSError, ValueError, TypeError, AttributeError, BlocklocError):
        return None
    built = {k: doc.get(k) for k in IDENTITY_KEYS}
    return hashlib.sha256(json.dumps(built, sort_keys=True).encode()).hexdigest()[:16]


def _now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%S%z")


def ensure_history(root: str | Path) -> None:
    """Record the store's current manifest as version 1 when it has no history yet."""
    root = Path(root)
    if version_path(root, 1).exists() or (root / VERSIONS_DIR).is_dir() and any((root / VERSIONS_DIR).iterdir()):
        return
    doc = _read_manifest(root)
    doc["lifelong"] = {"version": 1, "parent": None, "created": doc.get("created"), "note": "as built",
                       "runs": [], "changed_blocks": [], "held_back": []}
    (root / VERSIONS_DIR).mkdir(exist_ok=True)
    atomic_write_bytes(version_path(root, 1), json.dumps(doc, indent=1).encode())


def next_version(root: str | Path) -> int:
    return max(int(h["version"]) for h in history(root)) + 1


def commit_version(root: str | Path, doc: dict, record: dict) -> int:
    """Make ``doc`` (a manifest whose files are all in ``root`` already) the next version and the
    current one. record: runs, changed_blocks, held_back, note. Returns the version number."""
    root = Path(root)
    ensure_history(root)
    parent = current_version(root)
    version = next_version(root)
    doc = dict(doc)
    doc["lifelong"] = {"version": version, "parent": parent, "created": _now(), **record}
    data = json.dumps(doc, indent=1).encode()
    atomic_write_bytes(version_path(root, version), data)  # the version exists first...
    atomic_write_bytes(root / "manifest.json", data)  # ...then the pointer moves, in one rename
    log.info("%s: version %d (parent %d) is current", root, version, parent)
    return version


def rollback(root: str | Path, to: int) -> dict:
    """Make version ``to`` current again (atomic replace of ``manifest.json``); returns its
    record. Nothing is deleted: the newer versions stay in the history and can be made current."""
    root = Path(root)
    ensure_history(root)
    path = version_path(root, to)
    if not path.is_file():
        have = ", ".join(str(h["version"]) for h in history(root))
        raise MapError(f"--to {to}: {root} has no version {to} (versions: {have})")
    data = path.read_bytes()
    try:
        doc = json.loads(data)
    except ValueError as exc:
        raise MapError(f"{path}: unreadable version ({exc})") from None
    missing = [e["file"] for e in doc.get("entries", []) if not (root / e["file"]).is_file()]
    if missing:
        raise MapError(f"--to {to}: files of version {to} are missing in {root}: {', '.join(missing[:5])}")
    atomic_write_bytes(root / "manifest.json", data)
    log.info("%s: rolled back to version %d", root, to)
    return doc["lifelong"]
