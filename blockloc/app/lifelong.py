"""Lifelong maps' recipes (issue 43): what ``blockloc map changes | update | rollback`` do, with
the run's sequence opened by name and the config read here (the core, which reads neither, is
:mod:`blockloc.maps.changes`).

- :func:`open_run`: a run folder, its sequence (``--seq`` or the name the run's ``metrics.json``
  records) and the config that fits it, checked against each other and against the map before
  any work (:func:`check_run_map`: a run tracked in another map is refused);
- :func:`detect_run_changes`: a map store + a run folder (or an opened run) -> what changed;
- :func:`update_map`: several runs' detections -> a new version of the store, its place index
  rebuilt with the ``global_init`` settings of the first run's config and its sequence's gravity;
- :func:`write_changes`: ``changes.json``, and the changes drawn into the run folder's
  ``run.mcap`` and ``report.html`` (:mod:`blockloc.viz.changes_view`) when that folder is
  blockloc's results folder (a file blockloc did not make is never rewritten).

No printing, no progress bars (the commands draw them): a long step takes ``progress``.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from blockloc.app.assemble import place_index_params
from blockloc.app.catalog import config_for_sequence, open_sequence
from blockloc.config import Config
from blockloc.errors import BlocklocError, DatasetError, MapError
from blockloc.maps.changes.pipeline import ChangeResult, detect_changes
from blockloc.maps.changes.runs import RunError, RunPoses, read_run
from blockloc.maps.changes.update import apply_update, plan_update
from blockloc.maps.mounting import with_map_mounting
from blockloc.maps.store import MapStore, open_map

log = logging.getLogger("blockloc")


@dataclass
class RunChanges:
    """One run's detection: the result, the sequence name it was made from, the opened sequence
    and the config that fits it."""

    result: ChangeResult
    sequence_name: str
    sequence: object
    config: Config


def open_block_store(map_path: str | Path, option: str = "--map") -> MapStore:
    """The block map store at ``map_path``; MapError naming it unless it is one with a manifest."""
    store = open_map(map_path)
    if store.kind != "block" or store.legacy:
        raise MapError(f"{option} {map_path}: expected a block map store with a manifest (blockloc map build "
                       f"--kind block), got a {'released-layout block' if store.legacy else store.kind} map")
    return store


def open_run_sequence(run: RunPoses, seq: str | None, data_root: str | None):
    """The sequence a run was made from (``seq``, else the name its metrics.json records), with
    the trajectory the run gave it (``--poses``: the scans' stamps may come from it), its name and
    the config that fits it: (Sequence, name, Config)."""
    name = seq or run.sequence
    if not name:
        raise RunError(f"--run {run.path}: its metrics.json names no sequence (an interrupted run?); give --seq")
    if run.poses is not None and not Path(run.poses).is_file():
        raise RunError(f"--run {run.path}: the trajectory it was tracked with (--poses {run.poses}) is not there "
                       "any more (expected it where the run's metrics.json records it)")
    try:
        cfg = config_for_sequence(name)
        return open_sequence(name, data_root=data_root, dataset_cfg=cfg.dataset, poses=run.poses), name, cfg
    except DatasetError as exc:
        if seq is not None:  # the user's own --seq: its error as it is
            raise
        # the one metrics.json names: a live run, a moved or renamed recording
        raise RunError(f"--run {run.path}: the sequence its metrics.json names ({name!r}) cannot be opened "
                       f"here ({exc}); give its scans with --seq") from None


@dataclass
class OpenedRun:
    """A run folder read (its trusted frames), the sequence it was made from opened (placed with
    the mounting the run tracked with), its name and the config that fits it."""

    run: RunPoses
    sequence_name: str
    sequence: object
    config: Config


def open_run(store: MapStore, run_dir: str | Path, *, seq: str | None = None,
             data_root: str | None = None) -> OpenedRun:
    """The run folder ``run_dir`` and its sequence, checked before any work: RunError when the run
    was tracked in another map than ``store`` (:func:`check_run_map`), or naming ``--seq`` (or the
    sequence the run records) when it has fewer scans than the run went through (the run's frame
    indices would run past its end)."""
    run = read_run(run_dir)
    check_run_map(run, store)
    sequence, name, cfg = open_run_sequence(run, seq, data_root)
    if len(sequence) < run.num_frames:
        where = f"--seq {seq}" if seq is not None else f"--run {run.path}: its sequence {name}"
        raise RunError(f"{where}: {len(sequence)} scans, fewer than the {run.num_frames} frames the run "
                       f"{run.path} tracked (expected the sequence it was tracked on)")
    # the scans placed with the mounting the run tracked with (track's default: the map's, issue 41)
    sequence = with_map_mounting(sequence, store, cfg.map.use_map_mounting)
    return OpenedRun(run, name, sequence, cfg)


def check_run_map(run: RunPoses, store: MapStore) -> None:
    """RunError unless ``run`` was tracked in ``store`` (its poses are in that map's frame, its
    statuses say how its scans fit that map: against another, its frames would carve and add
    wrongly). The same map is the same identity (:func:`~blockloc.maps.changes.versions.map_identity`:
    a moved, copied or updated map still matches its runs). A run without an identity (from before
    runs recorded it) is compared by the path it records (relative: from the current directory):
    another map there is refused; when that cannot tell (the path gone, a store without a
    manifest), a warning and the run is taken as tracked in ``store``."""
    from blockloc.maps.changes.versions import map_identity

    given = map_identity(store)
    if run.map_id is not None and given is not None:
        if run.map_id != given:
            again = " as built before (it was built again since)" if _same_map_path(run.map, store) else ""
            raise RunError(f"--run {run.path}: tracked in {run.map or 'another map'}{again}, not {store.path} "
                           "(expected a run tracked in this map, or in a copy or another version of it)")
        return
    if run.map is None:
        log.warning("%s: its metrics.json does not say which map it was tracked in; taken as tracked in %s",
                    run.path, store.path)
        return
    if _same_map_path(run.map, store):
        return
    recorded = _open_recorded_map(run.map)
    theirs = map_identity(recorded) if recorded is not None else None
    if theirs is not None and given is not None:
        if theirs != given:
            raise RunError(f"--run {run.path}: tracked in {run.map}, not {store.path} (expected a run tracked in "
                           "this map, or in a copy or another version of it)")
        return
    log.warning("%s: tracked in %s, which cannot be compared with %s here (a run from before runs recorded "
                "their map's identity); taken as tracked in %s", run.path, run.map, store.path, store.path)


def _same_map_path(recorded: str | None, store: MapStore) -> bool:
    """Whether the map path a run records names ``store``'s directory (or URL)."""
    if recorded is None:
        return False
    if store.files.is_remote or "://" in recorded:
        return recorded.rstrip("/") == str(store.path).rstrip("/")
    try:
        return Path(recorded).resolve() == Path(store.path).resolve()
    except (OSError, RuntimeError):
        return False


def _open_recorded_map(recorded: str) -> MapStore | None:
    """The local store at the path a run records, or None (a URL is not fetched to compare; a
    path that is gone or holds no store)."""
    if "://" in recorded or not Path(recorded).is_dir():
        return None
    try:
        return open_map(recorded)
    except (OSError, BlocklocError):
        return None


def detect_run_changes(store: MapStore, run_dir: str | Path | OpenedRun, *, seq: str | None = None,
                       data_root: str | None = None, stride: int = 1,
                       progress: Callable[[int, int], None] | None = None) -> RunChanges:
    """What changed in ``store`` according to the trusted frames of the run folder ``run_dir``
    (opened here with ``seq`` and ``data_root``, or already by :func:`open_run`)."""
    opened = run_dir if isinstance(run_dir, OpenedRun) else open_run(store, run_dir, seq=seq, data_root=data_root)
    run = opened.run
    if not len(run):
        log.warning("%s: no trusted frame (status ok after 10 ok frames): nothing to learn from it", run.path)
    res = detect_changes(store, opened.sequence, run, stride=stride, progress=progress)
    return RunChanges(res, opened.sequence_name, opened.sequence, opened.config)


def place_index_builder(gravity_map, cfg: Config) -> Callable[[MapStore], bytes]:
    """The function :func:`~blockloc.maps.changes.update.apply_update` calls to rebuild a new
    version's place index: the ``global_init`` settings of ``cfg``, gravity (3,) in the map frame."""
    from blockloc.global_init.place_index import build_place_index

    params = place_index_params(cfg.global_init)
    return lambda store: build_place_index(store, gravity_map, params).to_bytes()


def update_map(map_path: str | Path, detected: list[RunChanges], *, runs: list[str], out: str | Path | None = None,
               strong_scans: int = 15, min_runs: int = 2) -> dict:
    """Apply what the runs' detections confirm as a new version of the local block store at
    ``map_path`` (or of a copy at ``out``); the version record (``version``, ``path``,
    ``changed_blocks``, ``blocks``, ``held_back``)."""
    if not detected:
        raise MapError("map update: no run to update from")
    plan = plan_update([d.result for d in detected], strong_scans=strong_scans, min_runs=min_runs)
    first = detected[0]
    return apply_update(map_path, plan, [d.result for d in detected], runs=list(runs), out=out,
                        place_index=place_index_builder(first.sequence.info.gravity_map, first.config))


def check_detectable(store: MapStore, where: str) -> None:
    """MapError naming the map ``where`` unless ``store`` is a block store with a manifest (the
    detector needs blocks and their keyframes): ``track --detect-changes`` checks it before tracking."""
    if store.kind != "block" or store.legacy:
        raise MapError(f"--map {where}: --detect-changes "
                       f"needs a block map store with a manifest (blockloc map build --kind block), got a "
                       f"{'released-layout block' if store.legacy else store.kind} map")


def write_changes(result: ChangeResult, store: MapStore, out: str | Path, run_dir: str | Path | None,
                  **facts) -> dict:
    """Write ``changes.json`` to ``out`` (atomically), then draw the changes into ``run_dir``'s
    ``run.mcap`` and ``report.html`` where they exist and the folder is blockloc's results
    folder. Returns the document, with ``drawn``: {file name: what was added} (a file that could
    not be drawn into is logged and left as it was: the changes.json stands)."""
    from blockloc.fileio import atomic_write_text
    from blockloc.maps.changes.layers import block_voxels
    from blockloc.outdir import RESULTS, owner
    from blockloc.viz.events import VizError

    doc = result.to_json(**facts)
    atomic_write_text(out, json.dumps(doc, indent=1) + "\n")
    drawn: dict = {}
    if run_dir is None:
        return {**doc, "drawn": drawn}
    run_dir = Path(run_dir)
    mine = owner(run_dir)
    if mine is None or mine[0] != RESULTS:
        log.warning("%s: not a results folder blockloc made; its run.mcap and report.html are left as they are",
                    run_dir)
        return {**doc, "drawn": drawn}
    from blockloc.viz.changes_view import add_changes_to_recording, add_changes_to_report
    from blockloc.viz.layout import RECORDING_NAME, REPORT_NAME

    by_block = block_voxels(result)
    try:
        if (run_dir / RECORDING_NAME).is_file():
            drawn[RECORDING_NAME] = add_changes_to_recording(run_dir / RECORDING_NAME, by_block,
                                                             result.voxels.voxel_m)
        if (run_dir / REPORT_NAME).is_file():
            from blockloc.maps.summary import map_points_xy

            add_changes_to_report(run_dir / REPORT_NAME, doc, map_points_xy(store), by_block)
            drawn[REPORT_NAME] = "changes section"
    except VizError as exc:
        log.error("%s", exc)
    return {**doc, "drawn": drawn}
