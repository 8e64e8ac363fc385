"""``blockloc map changes | update | rollback`` and the version history of ``map info``
(lifelong maps, issue 43; core in :mod:`blockloc.maps.changes`)."""

from __future__ import annotations

import logging
import sys
from pathlib import Path

log = logging.getLogger("blockloc")

#: Free space an update needs at least (its rebuilt blocks and place index; with --out, a copy of
#: the store besides), as map build's floor.
UPDATE_MIN_BYTES = 16 * 2**20


def _detect(store, opened, stride: int):
    """One opened run's detection (:func:`blockloc.app.lifelong.open_run`), with its progress bar."""
    from blockloc.app.lifelong import detect_run_changes
    from blockloc.commands.common import progress

    with progress(f"changes {opened.run.path.name}") as cb:
        return detect_run_changes(store, opened, stride=stride, progress=cb)


def changes_command(map_path: str, run_dir: Path, seq: str | None, out: Path | None, data_root: str | None,
                    stride: int) -> None:
    from blockloc.app.lifelong import open_block_store, open_run, write_changes
    from blockloc.fileio import check_output_parent

    out = Path(out) if out is not None else Path(run_dir) / "changes.json"
    check_output_parent(out, "--out")  # before any work
    from blockloc.outdir import check_file_replaceable

    check_file_replaceable(out, "--out", _is_changes_report, "the change reports")
    store = open_block_store(map_path, "--map")
    found = _detect(store, open_run(store, Path(run_dir), seq=seq, data_root=data_root), stride)
    doc = write_changes(found.result, store, out, run_dir, map=str(map_path), run=str(run_dir),
                        sequence=found.sequence_name)
    print_changes(doc, out)


def _is_changes_report(path: Path) -> bool:
    """A ``changes.json`` blockloc wrote (a JSON object with its report's fields)."""
    import json

    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError, UnicodeDecodeError):
        return False
    return isinstance(doc, dict) and doc.get("format") == "blockloc-changes"


def print_changes(doc: dict, out: Path) -> None:
    """What a detection found (its ``changes.json`` document), one line per changed block, and
    where it went."""
    t = doc["totals"]
    print(f"{doc['scans_used']} scans used, {doc['scans_rejected']} dropped by the consistency gate "
          f"({doc['frames_trusted']} trusted frames)", file=sys.stderr)
    for b in doc["blocks"]:
        if b["removed_voxels"] or b["added_voxels"]:
            print(f"block {b['block']}: removed {b['removed_m3']} m3 ({b['removed_points']} points), "
                  f"added {b['added_m3']} m3, dynamic {b['dynamic_voxels']} voxels, confidence "
                  f"{b['confidence']}{'' if b['confirmed'] else ' (below the block threshold)'}")
    print(f"removed {t['removed_voxels']}, added {t['added_voxels']}, dynamic {t['dynamic_voxels']} voxels "
          f"of {doc['params']['voxel_m']} m")
    print(f"wrote {out}")
    for name, what in doc.get("drawn", {}).items():
        print(f"drew the changes into {name}: "
              f"{what if isinstance(what, str) else ', '.join(f'{k} {v}' for k, v in what.items())}")


def update_command(map_path: str, runs: list[Path], seqs: list[str] | None, out: Path | None,
                   data_root: str | None, stride: int, strong_scans: int, min_runs: int) -> None:
    from blockloc.app.lifelong import open_block_store, open_run, update_map
    from blockloc.errors import MapError

    seqs = list(seqs or [])
    if seqs and len(seqs) != len(runs):
        raise MapError(f"--seq given {len(seqs)} times for {len(runs)} --run: give it once per --run, or never")
    if out is not None and Path(out).exists():
        raise MapError(f"--out {out}: already exists (choose a new directory)")
    store = open_block_store(map_path, "map")
    if store.files.is_remote:
        raise MapError(f"{map_path}: map update writes a local store; copy it first")
    # before any work: the store (or --out) writable, room for the rebuilt blocks, no other run on it
    from blockloc.outdir import claim_output

    claim_output(Path(out) if out is not None else Path(map_path), "--out" if out is not None else "MAP",
                 need_bytes=max(UPDATE_MIN_BYTES, store.total_bytes if out is not None else 0))
    # every run read and checked against its sequence before the first detection
    opened = [open_run(store, Path(run_dir), seq=seqs[k] if seqs else None, data_root=data_root)
              for k, run_dir in enumerate(runs)]
    detected = []
    for run_dir, one in zip(runs, opened):
        found = _detect(store, one, stride)
        print(f"{run_dir}: {found.result.scans_used} scans used, {found.result.scans_rejected} dropped by the "
              "consistency gate", file=sys.stderr)
        detected.append(found)
    rec = update_map(map_path, detected, runs=[str(r) for r in runs], out=out, strong_scans=strong_scans,
                     min_runs=min_runs)
    for b in rec["changed_blocks"]:
        c = rec["blocks"][b]
        print(f"block {b}: removed {c['removed_voxels']} voxels ({c['points_removed']} points), added "
              f"{c['added_voxels']} voxels; {c['points_added']} points added (in added voxels and seen behind "
              f"removed ones), {c['points_before']} -> {c['points_after']} points")
    for h in rec["held_back"]:
        print(f"held back: block {h['block']}: {h['reason']}")
    print(f"version {rec['version']} of {rec['path']}: {len(rec['changed_blocks'])} blocks rebuilt, "
          f"{len(rec['held_back'])} held back")


def rollback_command(map_path: str, to: int) -> None:
    from blockloc.app.lifelong import open_block_store
    from blockloc.maps.changes.versions import rollback

    from blockloc.outdir import claim_output

    open_block_store(map_path, "map")
    claim_output(Path(map_path), "MAP")  # writable, and no other run (an update) on it
    rec = rollback(map_path, to)
    print(f"{map_path}: version {rec['version']} is current")


def history_records(map_path: str) -> list[dict]:
    """The version history of a local manifest store (:func:`~blockloc.maps.changes.versions.history`);
    [] for a URL or a directory without a manifest."""
    from blockloc.maps.changes.versions import history

    if "://" in str(map_path) or not (Path(map_path) / "manifest.json").is_file():
        return []
    return history(map_path)


def history_lines(map_path: str) -> list[str]:
    """``map info``'s version history lines (none for a store never updated)."""
    hist = history_records(map_path)
    if len(hist) < 2:
        return []
    out = ["versions:"]
    for h in hist:
        out.append(f"  {'*' if h.get('current') else ' '} v{h['version']}"
                   f"{'' if h.get('parent') is None else ' (parent v' + str(h['parent']) + ')'}"
                   f" {h.get('created') or ''} {h.get('note') or ''}; blocks {', '.join(h.get('changed_blocks') or []) or '-'};"
                   f" runs {', '.join(h.get('runs') or []) or '-'}")
    return out
