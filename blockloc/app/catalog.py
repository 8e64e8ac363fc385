"""The catalogue: what a ``--seq`` value names, the preset that fits it and its default map.

Parsed once, here, for every command, the benchmarks and the node.

:meth:`SequenceRef.parse` turns the text into a reference that knows its loader
(:meth:`SequenceRef.open`), the config preset that fits it (``preset``), where the map for it is
expected when ``--map`` is not given (:meth:`default_map_path`) and the command that builds that
map (:meth:`build_hint`). Names:

- ``nclt_1``..``nclt_5``: NCLT sessions 2012-01-15, 2012-01-22, 2012-02-02, 2012-04-29,
  2012-05-11. The official downloads ``<date>_vel.tar.gz`` and ``<date>_sen.tar.gz`` both unpack
  into a ``<date>/`` directory; unpack them under ``<data_root>/nclt/`` (or ``<data_root>/``)
  and put ``groundtruth_<date>.csv`` in ``<date>/``, beside it, or in ``ground_truth/``.
- ``m2dgr_1``, ``m2dgr_2``: M2DGR ``street_01.bag`` / ``street_02.bag`` under
  ``<data_root>/m2dgr/`` (or ``<data_root>/``), ground truth ``street_0N.txt`` (TUM) beside the
  bag or in ``ground_truth/``; topics ``/velodyne_points`` and ``/handsfree/imu``.
- ``sim:<preset>/<session>[@<seed>]``: a simulated session streamed on the fly, seed 1 by default.
- a path: an NCLT-layout session directory (has ``velodyne_sync/``; written by ``blockloc sim``
  when ``sim.json`` lies beside it), a ROS1 ``.bag`` file, a ROS2 bag directory (has
  ``metadata.yaml``), or a folder of point clouds with a trajectory (``scans/*.pcd|bin|ply`` plus
  ``poses.tum`` or ``poses.txt``: :mod:`blockloc.datasets.scanfolder`).

Any sequence may be given its trajectory from a file (``poses=``, the commands' ``--poses``):
the poses become its ground truth and mapping poses (:func:`blockloc.datasets.with_poses.
with_trajectory`).

The data root is the ``data_root`` argument, else the dataset settings' ``data_root``, else
``$BLOCKLOC_DATA``, else ``./data``.

:func:`open_sequence` opens a value in one call; :func:`config_for_sequence` loads the config for
it (``--config`` when given, else the preset that fits the sequence).
"""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from blockloc.cache import cache_root, fingerprint
from blockloc.config import Config, DatasetConfig, load_config
from blockloc.datasets.base import RangeLimited, Sequence
from blockloc.datasets.with_poses import with_trajectory
from blockloc.errors import DatasetError, MapError

NCLT_NAMES = {f"nclt_{i + 1}": d for i, d in enumerate(
    ("2012-01-15", "2012-01-22", "2012-02-02", "2012-04-29", "2012-05-11"))}
M2DGR_NAMES = {"m2dgr_1": "street_01", "m2dgr_2": "street_02"}

#: M2DGR: body = the Handsfree A9 IMU frame (x forward, y left, z up). The VLP-32C sits at
#: (0.27255, -0.00053, 0.17954) m in it with identity rotation: the lidar-IMU extrinsic the
#: M2DGR authors ship in their LIO configurations (extrinsic_T / extrinsic_R).
M2DGR_T_BODY_LIDAR = np.array([[1.0, 0.0, 0.0, 0.27255],
                               [0.0, 1.0, 0.0, -0.00053],
                               [0.0, 0.0, 1.0, 0.17954],
                               [0.0, 0.0, 0.0, 1.0]])
M2DGR_T_BODY_IMU = np.eye(4)
M2DGR_LIDAR_TOPIC = "/velodyne_points"
M2DGR_IMU_TOPIC = "/handsfree/imu"

_SIM_RE = re.compile(r"^sim:(?P<preset>[A-Za-z0-9_\-]+)/(?P<session>[A-Za-z0-9_\-]+)(@(?P<seed>\d+))?$")
#: the changed world's later days (``loc_m3``, ``loc_m12``, ``map_m12``: ``blockloc.sim.changes``)
_SIM_LATER_DAY_RE = re.compile(r"^[A-Za-z0-9]+_m\d+$")
MAP_KINDS = ("block", "grid")

#: Loaders of ``--seq`` paths, tried in this order: kind -> module with ``detect(path) -> bool``,
#: ``open_path(path, options) -> Sequence`` and ``PRESET`` (config preset or None); one that
#: reads ``options["poses"]`` itself sets ``TAKES_POSES = True`` (else the sequence is wrapped by
#: ``with_trajectory``). A new loader is one module plus one line here.
PATH_LOADERS = {
    "nclt_dir": "blockloc.datasets.nclt",
    "rosbag": "blockloc.datasets.rosbag",
    "scan_folder": "blockloc.datasets.scanfolder",
}
_PATH_KINDS = ("an NCLT-layout session directory (with velodyne_sync/), a ROS1 .bag file, a ROS2 bag "
               "directory (with metadata.yaml) or a folder of point clouds (.pcd/.bin/.ply, itself or "
               "in scans/)")


def _loader(kind: str):
    import importlib

    return importlib.import_module(PATH_LOADERS[kind])


def known_names() -> list[str]:
    """Dataset names besides paths and ``sim:`` names."""
    return list(NCLT_NAMES) + list(M2DGR_NAMES)


def resolve_data_root(data_root: str | Path | None = None, dataset_cfg: Any = None) -> Path:
    """The data root: argument, then ``dataset_cfg.data_root``, then $BLOCKLOC_DATA, then ./data."""
    for cand in (data_root, getattr(dataset_cfg, "data_root", None), os.environ.get("BLOCKLOC_DATA")):
        if cand:
            return Path(cand).expanduser()
    return Path("data")


def map_kind_for_backend(backend: str) -> str:
    """The map kind a tracking backend reads: block maps for ``block``, grid maps otherwise."""
    return "block" if backend == "block" else "grid"


def _is_map_store(path: Path) -> bool:
    """A directory blockloc's map build (or the block maps paper's release layout) wrote: what
    :func:`blockloc.maps.store.open_map` opens, recognised without checking it whole."""
    from blockloc.maps.store import CENTROID_CLOUD, KINDS, MANIFEST_NAME

    if not path.is_dir():
        return False
    if (path / CENTROID_CLOUD).is_file():
        return True
    try:
        doc = json.loads((path / MANIFEST_NAME).read_text())
    except (OSError, ValueError, UnicodeDecodeError):
        return False
    return isinstance(doc, dict) and doc.get("kind") in KINDS and isinstance(doc.get("entries"), list)


@dataclass(frozen=True)
class SequenceRef:
    """A parsed ``--seq`` value.

    kind: ``sim`` | ``nclt`` | ``m2dgr`` (names), or a key of ``PATH_LOADERS`` (``nclt_dir`` |
    ``rosbag`` | ``scan_folder``) for paths.
    text: the value as given. sim: (preset, session, seed) for ``sim``. path: the file or
    directory for path kinds. preset: the config preset that fits (``sim`` | ``nclt`` | ``m2dgr``
    | None).
    """

    text: str
    kind: str
    preset: str | None = None
    path: Path | None = None
    sim: tuple[str, str, int] | None = None

    # ------------------------------------------------------------------ parsing
    @classmethod
    def parse(cls, text: str | os.PathLike) -> "SequenceRef":
        """Parse a name or path; DatasetError (one line, what was expected) when it names nothing."""
        name = str(text)
        m = _SIM_RE.match(name)
        if m:
            return cls(name, "sim", "sim", sim=(m["preset"], m["session"], int(m["seed"] or 1)))
        if name.startswith("sim:"):
            raise DatasetError(f"sequence {name!r}: expected sim:<preset>/<session>[@<seed>], "
                               "e.g. sim:small/loc@1")
        if name in NCLT_NAMES:
            return cls(name, "nclt", "nclt")
        if name in M2DGR_NAMES:
            return cls(name, "m2dgr", "m2dgr")
        path = Path(name).expanduser()
        if _is_map_store(path):  # its PCD blocks would read as a scan folder without stamps
            raise DatasetError(f"{path}: a map store, not a sequence (give it with --map; --seq takes the scans: "
                               f"{_PATH_KINDS})")
        for kind in PATH_LOADERS:
            loader = _loader(kind)
            if loader.detect(path):
                # a session written by `blockloc sim` (sim.json beside it) is simulated data
                preset = "sim" if (path.parent / "sim.json").is_file() else loader.PRESET
                return cls(name, kind, preset, path=path)
        if path.exists():
            raise DatasetError(f"{path}: not a sequence; expected {_PATH_KINDS}")
        if "/" in name or os.sep in name or name.endswith(".bag"):
            raise DatasetError(f"{path}: no such file or directory (expected {_PATH_KINDS})")
        raise DatasetError(f"unknown sequence {name!r}: expected a path or one of "
                           f"{', '.join(known_names())}, sim:<preset>/<session>[@<seed>]")

    # ------------------------------------------------------------------ opening
    def open(self, *, data_root: str | Path | None = None, dataset_cfg: Any = None,
             lidar_topic: str | None = None, imu_topic: str | None = None, poses=None,
             poses_frame: str | None = None, want_imu: bool = True):
        """The Sequence this names. dataset_cfg: the dataset settings (range limits, hits use,
        topics, data root; read by attribute); explicit arguments override it. poses: a
        trajectory file (TUM, KITTI, NCLT csv) or Trajectory giving its ground truth and mapping
        poses (T_map_body); poses_frame: that trajectory's frame name. want_imu: False when the
        run ignores the IMU (``tracking.use_imu`` false): a loader does not warn about a missing
        IMU file then."""
        dc = DatasetConfig()  # what a setting missing from dataset_cfg defaults to (declared once, there)
        options = dict(min_range_m=float(getattr(dataset_cfg, "min_range_m", dc.min_range_m)),
                       max_range_m=float(getattr(dataset_cfg, "max_range_m", dc.max_range_m)),
                       use_hits_times=bool(getattr(dataset_cfg, "use_hits_times", dc.use_hits_times)),
                       lidar_topic=lidar_topic or getattr(dataset_cfg, "lidar_topic", None),
                       imu_topic=imu_topic or getattr(dataset_cfg, "imu_topic", None),
                       want_imu=bool(want_imu))
        if self.kind in PATH_LOADERS:
            loader = _loader(self.kind)
            seq = loader.open_path(self.path, {**options, "poses": poses, "poses_frame": poses_frame})
            if getattr(loader, "TAKES_POSES", False):  # it used ``poses`` itself
                return seq
        else:
            seq = self._open_named(data_root, dataset_cfg, lidar_topic, imu_topic, options)
        if poses is None:
            return seq
        return with_trajectory(seq, poses, frame_name=poses_frame)

    def _open_named(self, data_root, dataset_cfg, lidar_topic, imu_topic, options):
        ranges = {k: options[k] for k in ("min_range_m", "max_range_m")}
        if self.kind == "sim":  # the simulator, only for sim: names
            if _SIM_LATER_DAY_RE.match(self.sim[1]):  # a day of the changing world (it says which exist)
                from blockloc.sim.changes import open_session as open_sim
            else:
                from blockloc.sim.stream import open_sim_sequence as open_sim

            return RangeLimited(open_sim(*self.sim), ranges["min_range_m"], ranges["max_range_m"])
        if self.kind == "nclt":
            from blockloc.datasets.nclt import NcltSequence

            root = resolve_data_root(data_root, dataset_cfg)
            date = NCLT_NAMES[self.text]
            cands = [root / "nclt" / date, root / "NCLT" / date, root / date]
            for c in cands:
                if (c / "velodyne_sync").is_dir():
                    return NcltSequence(c, use_hits_times=options["use_hits_times"], date=date, name=self.text,
                                        want_imu=options["want_imu"], **ranges)
            raise DatasetError(
                f"{self.text}: NCLT session {date} not found: expected {cands[0]}/velodyne_sync/ "
                f"(unpack {date}_vel.tar.gz and {date}_sen.tar.gz from the NCLT site into {root / 'nclt'}, "
                f"put groundtruth_{date}.csv in {cands[0]}; data root from --data-root or BLOCKLOC_DATA)")
        return self._open_m2dgr(data_root, dataset_cfg, lidar_topic, imu_topic, ranges)

    def _open_m2dgr(self, data_root, dataset_cfg, lidar_topic, imu_topic, ranges):
        from blockloc.datasets.rosbag import RosbagSequence

        root = resolve_data_root(data_root, dataset_cfg)
        stem = M2DGR_NAMES[self.text]
        cands = [root / "m2dgr" / f"{stem}.bag", root / "M2DGR" / f"{stem}.bag", root / f"{stem}.bag"]
        bag = next((c for c in cands if c.is_file()), None)
        if bag is None:
            raise DatasetError(f"{self.text}: M2DGR {stem}.bag not found: expected {cands[0]} "
                               f"(download {stem}.bag and its ground truth {stem}.txt from the "
                               f"M2DGR site into {root / 'm2dgr'})")
        gt = next((g for g in (bag.with_suffix(".txt"), bag.parent / "ground_truth" / f"{stem}.txt")
                   if g.is_file()), None)
        return RosbagSequence(bag, lidar_topic=lidar_topic or M2DGR_LIDAR_TOPIC,
                              imu_topic=imu_topic or M2DGR_IMU_TOPIC,
                              T_body_lidar=M2DGR_T_BODY_LIDAR, T_body_imu=M2DGR_T_BODY_IMU,
                              gravity_map=(0.0, 0.0, -9.81), ground_truth_path=gt, name=self.text,
                              **ranges)

    # ------------------------------------------------------------------ its map
    def mapping_source(self) -> str | None:
        """The ``--seq`` a map for this sequence is built from (another session of the same
        place), or None when there is no convention."""
        if self.kind == "sim":
            preset, _, seed = self.sim
            return f"sim:{preset}/map@{seed}"
        if self.kind == "nclt":
            return "nclt_1" if self.text != "nclt_1" else "nclt_3"
        if self.path is not None and self.preset == "sim" and (self.path.parent / "map").exists():
            return str(self.path.parent / "map")
        return None

    def default_map_path(self, kind: str, *, data_root: str | Path | None = None,
                         dataset_cfg: Any = None, map_params: tuple = ()) -> Path:
        """Where the ``kind`` (block | grid) map for this sequence is expected without --map.

        sim: the cache entry ``blockloc demo`` and the tests build, keyed by the simulator's and
        the map builder's code and ``map_params``. nclt_N: ``<data_root>/maps/nclt_<kind>``.
        A session written by ``blockloc sim``: ``<out>/<kind>_map``. Otherwise MapError (give --map).
        """
        if kind not in MAP_KINDS:
            raise MapError(f"map kind {kind!r}: expected one of {', '.join(MAP_KINDS)}")
        if self.kind == "sim":
            preset, _, seed = self.sim
            world = fingerprint("blockloc.sim", "blockloc.datasets.nclt", params=(preset, seed))
            key = fingerprint("blockloc.maps", "blockloc.datasets", params=(world, kind, tuple(map_params)))
            return cache_root() / "maps" / f"{preset}_{seed}_{kind}-{key}"
        if self.kind == "nclt":
            return resolve_data_root(data_root, dataset_cfg) / "maps" / f"nclt_{kind}"
        if self.path is not None and self.mapping_source() is not None:
            return self.path.parent / f"{kind}_map"
        raise MapError(f"no default map for sequence {self.text!r}: give --map MAP (build one with "
                       f"'blockloc map build --seq <mapping session> --kind {kind} --out MAP')")

    def build_hint(self, kind: str, out: Path) -> str:
        """The one-line command that builds the map expected at ``out``."""
        src = self.mapping_source() or "<mapping session>"
        return f"blockloc map build --seq {src} --kind {kind} --out {out}"


def open_sequence(name_or_path: str | Path, *, data_root: str | Path | None = None,
                  dataset_cfg: Any = None, lidar_topic: str | None = None,
                  imu_topic: str | None = None, poses=None, poses_frame: str | None = None) -> Sequence:
    """Open a sequence by name or path.

    dataset_cfg: the dataset settings (range limits, hits use, topics, data root); explicit
    arguments override it. poses: a trajectory file (or Trajectory) that gives the sequence its
    ground truth and mapping poses. Raises DatasetError with one line naming the expected path
    when data are missing, or listing the known names for an unknown name.
    """
    return SequenceRef.parse(name_or_path).open(data_root=data_root, dataset_cfg=dataset_cfg,
                                                lidar_topic=lidar_topic, imu_topic=imu_topic,
                                                poses=poses, poses_frame=poses_frame)


def preset_for_sequence(seq: str) -> str | None:
    """The preset that fits a ``--seq`` value (:attr:`SequenceRef.preset`): 'sim' for simulated
    sessions, 'nclt' for NCLT, 'm2dgr' for M2DGR, None otherwise (also for a value that names
    nothing: opening it will say why)."""
    try:
        return SequenceRef.parse(seq).preset
    except DatasetError:
        return None


def config_for_sequence(seq: str | None, config: str | Path | None = None,
                        overrides: dict | None = None, overrides_source: str = "overrides") -> Config:
    """``config`` (a file or preset name) when given, else the preset that fits ``seq``, else the
    defaults; then ``overrides`` (nested mapping SECTION -> KEY -> value)."""
    return load_config(config, overrides=overrides, overrides_source=overrides_source,
                       preset=None if config or not seq else preset_for_sequence(seq))


def map_params(map_cfg, kind: str) -> tuple:
    """The map-building settings a cached map depends on (part of its cache key)."""
    size = map_cfg.block_size_m if kind == "block" else map_cfg.tile_size_m
    return (size, map_cfg.keyframe_distance_m, map_cfg.keyframe_angle_deg, map_cfg.voxel_size_m,
            bool(map_cfg.calibrate_mounting), float(map_cfg.mounting_translation_tolerance_m),
            bool(map_cfg.refine_poses)) + (("remove_dynamic",) if map_cfg.remove_dynamic else ())  # off: keys as before
