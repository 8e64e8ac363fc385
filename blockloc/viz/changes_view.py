"""What changed since the map was made, drawn where a run is looked at (issue 43): a layer in the
run's MCAP recording and a section in its ``report.html``.

Both take plain arrays: ``by_block`` is block id -> class (``removed``, ``added``, ``dynamic``) ->
(K, 3) voxel centres, map frame, metres (:func:`blockloc.maps.changes.layers.block_voxels`).

Recording (:func:`add_changes_to_recording`): the file is rewritten whole (MCAP has no append)
into a temp file beside it and renamed over it, every record of the original kept, plus

- ``/changes/removed``, ``/changes/added``, ``/changes/dynamic`` (sensor_msgs/PointCloud2, x y z
  float32, ``map`` frame): one cloud per class, the voxel centres of every block (a voxel in two
  overlapping blocks' maps once per block);
- ``/changes/blocks`` (visualization_msgs/MarkerArray): per block, one CUBE_LIST per class
  (namespace ``changes/<class>``, voxel-sized cubes: red removed, green added, orange dynamic)
  and a text label with the block's counts, so each block can be toggled in Foxglove.

Every message is stamped with the recording's first message time, so the layer is visible from
the start of playback. A recording that already has the topics (detection run again) has them
replaced. Report (:func:`add_changes_to_report`): a ``<section id="changes">`` before the
metrics, a top view of the map with the changed voxels over it and the per-block table; an
earlier changes section is replaced.
"""

from __future__ import annotations

import base64
import html
import io
import logging
import re
from pathlib import Path

import numpy as np

from blockloc.fileio import atomic_path, atomic_write_text
from blockloc.viz.events import VizError

log = logging.getLogger(__name__)

CLASSES = ("removed", "added", "dynamic")
TOPIC_PREFIX = "/changes/"
MARKERS_TOPIC = "/changes/blocks"
COLOURS = {"removed": (0.84, 0.15, 0.16, 0.9), "added": (0.17, 0.63, 0.17, 0.9), "dynamic": (1.0, 0.5, 0.05, 0.6)}
_CUBE_LIST, _TEXT = 6, 9  # visualization_msgs/Marker types


def cloud_topics() -> dict[str, str]:
    """topic -> class of the changes' point clouds."""
    return {f"{TOPIC_PREFIX}{c}": c for c in CLASSES}


def _messages(by_block: dict, voxel_m: float, t_ns: int) -> dict[str, bytes]:
    """topic -> the CDR bytes of its one message."""
    from blockloc.viz.ros_codec import FRAME_MAP, MSG_MARKERS, RosBuilder

    rb = RosBuilder()
    out = {}
    for topic, cls in cloud_topics().items():
        parts = [v[cls] for v in by_block.values() if len(v[cls])]
        pts = np.concatenate(parts) if parts else np.zeros((0, 3))
        out[topic] = rb.cloud(t_ns, FRAME_MAP, pts.astype(np.float32))
    markers = []
    for n, (block, v) in enumerate(sorted(by_block.items())):
        for cls in CLASSES:
            if len(v[cls]):
                markers.append(rb.marker(t_ns, f"changes/{cls}", n, _CUBE_LIST, points=v[cls],
                                         scale=(voxel_m, voxel_m, voxel_m), rgba=COLOURS[cls]))
        allp = np.concatenate([v[c] for c in CLASSES])
        if len(allp):
            top = allp.mean(axis=0) + np.array([0.0, 0.0, 3.0])
            label = f"block {block}: -{len(v['removed'])} +{len(v['added'])} ~{len(v['dynamic'])} voxels"
            markers.append(rb.marker(t_ns, "changes/label", n, _TEXT, text=label, position=top,
                                     scale=(1.0, 1.0, 1.0), rgba=(1.0, 1.0, 1.0, 1.0)))
    out[MARKERS_TOPIC] = rb.serialize(rb.MarkerArray(markers=markers), MSG_MARKERS)
    return out


def add_changes_to_recording(path: str | Path, by_block: dict, voxel_m: float) -> dict[str, int]:
    """Rewrite the MCAP recording at ``path`` with the changes layer (module docstring); returns
    topic -> points (clouds) or markers (``/changes/blocks``) written. VizError naming the file
    when it cannot be read or written (the original is then left as it was)."""
    from mcap.reader import make_reader
    from mcap.well_known import MessageEncoding, SchemaEncoding
    from mcap.writer import CompressionType, Writer

    from blockloc.viz.ros_codec import MSG_CLOUD, MSG_MARKERS, schema_text

    path = Path(path)
    ours = set(cloud_topics()) | {MARKERS_TOPIC}
    try:
        with open(path, "rb") as src, atomic_path(path) as tmp, open(tmp, "wb") as dst:
            reader = make_reader(src)
            summary = reader.get_summary()
            stats = summary.statistics if summary is not None else None
            t_ns = int(stats.message_start_time) if stats is not None and stats.message_count else 0
            header = reader.get_header()
            writer = Writer(dst, compression=CompressionType.ZSTD)
            writer.start(profile=header.profile, library=header.library)
            schema_ids, channel_ids = {}, {}
            for schema, channel, message in reader.iter_messages(log_time_order=False):
                if channel.topic in ours:
                    continue
                if channel.id not in channel_ids:
                    sid = 0
                    if schema is not None:
                        if schema.id not in schema_ids:
                            schema_ids[schema.id] = writer.register_schema(schema.name, schema.encoding, schema.data)
                        sid = schema_ids[schema.id]
                    channel_ids[channel.id] = writer.register_channel(channel.topic, channel.message_encoding,
                                                                      sid, dict(channel.metadata))
                writer.add_message(channel_ids[channel.id], message.log_time, message.data, message.publish_time,
                                   message.sequence)
            cloud_schema = writer.register_schema(MSG_CLOUD, SchemaEncoding.ROS2, schema_text(MSG_CLOUD).encode())
            marker_schema = writer.register_schema(MSG_MARKERS, SchemaEncoding.ROS2, schema_text(MSG_MARKERS).encode())
            for topic, data in _messages(by_block, voxel_m, t_ns).items():
                ch = writer.register_channel(topic, MessageEncoding.CDR,
                                             marker_schema if topic == MARKERS_TOPIC else cloud_schema)
                writer.add_message(ch, t_ns, data, t_ns, 0)
            for meta in reader.iter_metadata():
                writer.add_metadata(meta.name, dict(meta.metadata))
            for att in reader.iter_attachments():
                writer.add_attachment(att.create_time, att.log_time, att.name, att.media_type, att.data)
            writer.finish()
    except OSError as exc:
        raise VizError(f"recording {path}: cannot add the changes layer ({exc.strerror or exc})") from None
    except Exception as exc:  # noqa: BLE001 - mcap's reader raises its own errors for a broken file
        if isinstance(exc, VizError):
            raise
        raise VizError(f"recording {path}: cannot add the changes layer ({type(exc).__name__}: {exc})") from None
    counts = {t: int(sum(len(v[c]) for v in by_block.values())) for t, c in cloud_topics().items()}
    counts[MARKERS_TOPIC] = sum(1 for v in by_block.values() for c in CLASSES if len(v[c])) + sum(
        1 for v in by_block.values() if any(len(v[c]) for c in CLASSES))
    log.info("recording %s: changes layer added (%s)", path, ", ".join(f"{t} {n}" for t, n in counts.items()))
    return counts


# ----------------------------------------------------------------------------- report.html
SECTION_RE = re.compile(r'<section id="changes">.*?</section>\n?', re.S)
ANCHOR = '<section id="metrics">'


def changes_figure_png(map_xy: np.ndarray, by_block: dict, voxel_m: float) -> bytes:
    """A top view (PNG bytes): map points grey (map_xy (K, 2), map frame x/y m), the changed
    voxels over them in their class's colour, each block's name at its changes' centre."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 7))
    try:
        xy = np.asarray(map_xy, float).reshape(-1, 2)
        ax.scatter(xy[:, 0], xy[:, 1], s=0.3, c="#b8b8b8", linewidths=0, label="map", rasterized=True)
        for cls in ("dynamic", "added", "removed"):
            parts = [v[cls][:, :2] for v in by_block.values() if len(v[cls])]
            pts = np.concatenate(parts) if parts else np.zeros((0, 2))
            ax.scatter(pts[:, 0], pts[:, 1], s=4, c=[COLOURS[cls][:3]], marker="s", linewidths=0,
                       label=f"{cls} ({len(pts)} voxels)")
        for block, v in by_block.items():
            allp = np.concatenate([v[c] for c in CLASSES])
            if len(allp):
                c = allp[:, :2].mean(axis=0)
                ax.annotate(f"block {block}", c, fontsize=8, ha="center",
                            bbox={"boxstyle": "round", "fc": "white", "alpha": 0.7, "lw": 0})
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel("x (m, map frame)")
        ax.set_ylabel("y (m)")
        ax.set_title(f"changes since the map was made (voxels of {voxel_m:g} m, seen from above)")
        ax.legend(loc="upper right", markerscale=3, fontsize=8)
        fig.tight_layout()
        buf = io.BytesIO()
        fig.savefig(buf, format="png", dpi=100)
        return buf.getvalue()
    finally:
        plt.close(fig)


def changes_section_html(doc: dict, png: bytes) -> str:
    """The report's changes section: the figure and the per-block table of ``doc`` (the
    ``changes.json`` document)."""
    esc = html.escape
    cols = (("block", "block"), ("removed_voxels", "removed voxels"), ("removed_m3", "removed m³"),
            ("removed_points", "map points removed"), ("added_voxels", "added voxels"), ("added_m3", "added m³"),
            ("dynamic_voxels", "dynamic voxels"), ("confidence", "confidence"), ("confirmed", "confirmed"))
    head = "".join(f"<th>{esc(label)}</th>" for _, label in cols)
    body = "".join("<tr>" + "".join(f"<td>{esc(str(b.get(k, '')))}</td>" for k, _ in cols) + "</tr>"
                   for b in doc.get("blocks", []))
    t = doc.get("totals", {})
    uri = "data:image/png;base64," + base64.b64encode(png).decode("ascii")
    return (f'<section id="changes"><h2>Changes since the map was made</h2>\n'
            f'<p class="hint">From {doc.get("scans_used")} scans of {doc.get("frames_trusted")} trusted frames '
            f'({doc.get("scans_rejected")} dropped by the consistency gate): removed {t.get("removed_voxels")}, '
            f'added {t.get("added_voxels")}, dynamic {t.get("dynamic_voxels")} voxels. A block is rebuilt by '
            f'<code>blockloc map update</code> only when confirmed.</p>\n'
            f'<figure><img alt="changes over the map" src="{uri}"><figcaption>red: map structure the scans now see '
            f'through; green: new structure where the map saw free space; orange: seen briefly, gone later'
            f'</figcaption></figure>\n'
            f'<table class="changes"><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table></section>\n')


def add_changes_to_report(path: str | Path, doc: dict, map_xy: np.ndarray, by_block: dict) -> Path:
    """Insert (or replace) the changes section in the ``report.html`` at ``path`` (atomically).
    VizError naming the file when it cannot be read, is not a blockloc report, or cannot be written."""
    path = Path(path)
    try:
        page = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise VizError(f"report {path}: cannot read it ({getattr(exc, 'strerror', None) or exc})") from None
    page = SECTION_RE.sub("", page)
    if ANCHOR not in page:
        raise VizError(f"report {path}: not a blockloc report (no metrics section); changes section not added")
    section = changes_section_html(doc, changes_figure_png(map_xy, by_block, float(doc["params"]["voxel_m"])))
    page = page.replace(ANCHOR, section + ANCHOR, 1)
    try:
        atomic_write_text(path, page)
    except OSError as exc:
        raise VizError(f"report {path}: cannot write ({exc.strerror})") from None
    return path
