"""A scan as ROS 2 robot data in one MCAP file (`dmdsm db export SCAN --mcap FILE`): the
stage's pose as /tf, the waveforms, distances and ranges, the object-frame points and the
object's 3D model, in the scan's own time order, so Foxglove replays the scan.

Stamps (header and log time) are the file's `host_time`: Unix seconds of each shot's laser
edge through the clock sync in a fly scan, of the moment the point was stored in a step scan.
Frames (docs/robotics.md): `stage` (the machine's frame {0}) -> `sensor` (origin at the
commanded stage position S, +x along the calibrated beam v: where Range and Distance point),
`stage` -> `table` (origin X_R, z along n, turned by the table angle about n), `table` ->
`object` (identity, on /tf_static: the object frame is the table's frame, as reconstruction
uses it). Points, distances and the reconstruction are those of scan.points.scan_points.
`--bag DIR` writes the same file into a rosbag2 bag folder beside its metadata.yaml
(bag_metadata), which ROS 2 Humble's `ros2 bag` opens as it is.
"""

from __future__ import annotations

import contextlib
import math
import os
import tomllib
from collections.abc import Iterator
from dataclasses import fields
from pathlib import Path

import numpy as np

from ..calibration.geometry import rodrigues
from ..files import atomic_output, write_failed
from ..scan.plan import ScanPlan
from ..scan.points import MODS, scan_points
from ..scan.reconstruct import table_frame
from ..scan.scanfile import ScanData, sample_rate_hz
from . import bag_metadata as bags
from . import messages as msgs
from .mcap_file import McapRecorder, RecordingStopped

CHUNK_BYTES = 256 << 10  # zstd chunks of the export (an indexed file: Foxglove seeks in it)
TOPICS = {"/tf": "tf2_msgs/msg/TFMessage", "/tf_static": "tf2_msgs/msg/TFMessage",
          "/dmdsm/waveform": "dmdsm_msgs/msg/Waveform",
          **{f"/dmdsm/range/{m}": "sensor_msgs/msg/Range" for m in MODS},
          **{f"/dmdsm/distance/{m}": "dmdsm_msgs/msg/Distance" for m in MODS},
          "/dmdsm/points": "sensor_msgs/msg/PointCloud2",
          "/dmdsm/model": "visualization_msgs/msg/Marker"}
LATCHED = ("/tf_static", "/dmdsm/model")  # transient local: a late subscriber gets them
PALETTE = [(0.90, 0.45, 0.20), (0.25, 0.55, 0.85), (0.35, 0.70, 0.35), (0.80, 0.30, 0.60),
           (0.85, 0.75, 0.25), (0.45, 0.80, 0.80), (0.60, 0.45, 0.30), (0.55, 0.55, 0.90)]
GREY = (0.7, 0.7, 0.72)


def quaternion(R: np.ndarray) -> tuple[float, float, float, float]:
    """Unit quaternion (x, y, z, w, w >= 0) of a rotation matrix."""
    R = np.asarray(R, float)
    m = np.array([[R[0, 0] - R[1, 1] - R[2, 2], 0, 0, 0],
                  [R[0, 1] + R[1, 0], R[1, 1] - R[0, 0] - R[2, 2], 0, 0],
                  [R[0, 2] + R[2, 0], R[1, 2] + R[2, 1], R[2, 2] - R[0, 0] - R[1, 1], 0],
                  [R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1],
                   R[0, 0] + R[1, 1] + R[2, 2]]]) / 3.0
    w, v = np.linalg.eigh(m)  # Bar-Itzhack: the eigenvector of the largest eigenvalue
    q = v[:, np.argmax(w)]
    q = q if q[3] >= 0 else -q
    return tuple(float(x) for x in q / np.linalg.norm(q))


def beam_rotation(v: np.ndarray) -> np.ndarray:
    """The sensor frame's axes in the stage frame: the least rotation taking +x to the beam
    direction v (REP 117: a Range points along its frame's +x)."""
    v = np.asarray(v, float) / np.linalg.norm(v)
    x = np.array([1.0, 0.0, 0.0])
    axis = np.cross(x, v)
    s, c = np.linalg.norm(axis), float(x @ v)
    if s < 1e-12:
        return np.eye(3) if c > 0 else np.diag([-1.0, -1.0, 1.0])
    return rodrigues(axis / s, math.atan2(s, c))


def depth_gate_mm(scan: ScanData) -> tuple[float, float]:
    """The beam distances (mm) the scan searched (its plan's depth gate; the default plan's
    when the file's plan text is no plan): Range's min_range and max_range."""
    known = {f.name for f in fields(ScanPlan)}
    try:
        doc = tomllib.loads(str(scan.entry.get("plan", "")))
        flat = {k: v for sec in ("sample", "object", "scan") for k, v in doc.get(sec, {}).items()
                if k in known}
        flat.setdefault("object_id", "?")
        return ScanPlan(**flat).depth_gate_mm()
    except (tomllib.TOMLDecodeError, TypeError, ValueError, AttributeError):
        return ScanPlan("?").depth_gate_mm()


def poses(scan: ScanData, row: int, t: float, _known: dict | None = None) -> dict:
    """/tf of one row: the sensor and the turned table in the stage frame (R_n(theta) B:
    reconstruct.object_points undoes it, X = X_R + R_n(theta) B P). _known: a dict this
    function fills with what is the same for every row (the sensor's rotation, one table
    rotation per angle) when a caller passes the same one for each row."""
    cal, p = scan.calibration, scan.points
    known = {} if _known is None else _known
    if "sensor" not in known:
        known["sensor"] = quaternion(beam_rotation(cal["v"]))
    theta = float(p["theta_deg"][row])
    if theta not in known:
        n = np.asarray(cal["n"], float)
        known[theta] = quaternion(rodrigues(n, math.radians(theta)) @ table_frame(n))
    return msgs.tf_msg([
        msgs.transform(t, "stage", "sensor", p["stage_position_mm"][row], known["sensor"]),
        msgs.transform(t, "stage", "table", cal["X_R"], known[theta])])


def model_marker(model: object, t_s: float) -> dict:
    """The object's 3D model (store.ObjectModel) as a TRIANGLE_LIST in the object frame,
    each vertex coloured by its most probable material (grey where it has none)."""
    names = list(model.classes)
    best = model.material
    colors = np.array([(*(PALETTE[names.index(b) % len(PALETTE)] if b in names else GREY), 1.0)
                       for b in best]) if len(best) else None
    return msgs.mesh_marker(t_s, "object", model.vertices_mm, model.faces, colors,
                            ns=f"dmdsm/model/{model.object_id}", id=int(model.version))


def scan_messages(scan: ScanData, model: object | None = None
                  ) -> Iterator[tuple[float, str, dict]]:
    """(stamp s, topic, message dict) of a scan in time order (stable: a row's /tf, waveform,
    ranges and distances; a line's point cloud after its last row), made as they are asked
    for. ValueError (one line) if the file's host times cannot be ROS stamps."""
    p = scan.points
    n = scan.n_points
    t = np.asarray(p["host_time"], float)
    if n and not (np.isfinite(t).all() and 0 <= t.min() and t.max() < 2**31):
        bad = t[~np.isfinite(t)][:1].tolist() or [t.min(), t.max()]
        raise ValueError(f"{scan.path}: host_time holds {bad}, not Unix times a ROS stamp "
                         f"can hold: the file is damaged; restore it from a copy")
    return _messages(scan, model, t)


def _messages(scan: ScanData, model: object | None, t: np.ndarray
              ) -> Iterator[tuple[float, str, dict]]:
    p = scan.points
    n = scan.n_points
    order = np.argsort(t, kind="stable")
    pts = scan_points(scan)
    std = {m: np.full(n, np.nan) for m in MODS}
    for m in MODS:
        std[m][pts[m]["row"]] = pts[m]["d_std"]
    lo, hi = depth_gate_mm(scan)
    rate = sample_rate_hz(scan)
    known: dict = {}
    t0 = float(t[order[0]]) if n else 0.0
    yield t0, "/tf_static", msgs.tf_msg([msgs.transform(t0, "table", "object", (0, 0, 0))])
    if model is not None:
        yield t0, "/dmdsm/model", model_marker(model, t0)
    group: list[int] = []
    for k, row in enumerate(order):
        ts = float(t[row])
        yield ts, "/tf", poses(scan, row, ts, known)
        yield ts, "/dmdsm/waveform", msgs.waveform_msg(
            ts, scan.waveforms[row], shot_id=int(p["point_index"][row]), sample_rate_hz=rate,
            n_average=int(p["n_average"][row]), timestamp_ticks=int(p["timestamp"][row]),
            trigger_phase_ticks=int(p["trigger_phase"][row]),
            received=bool(p["received"][row]))
        if p["received"][row]:
            for m in MODS:
                d = float(p[f"distance_{m}_mm"][row])
                yield ts, f"/dmdsm/range/{m}", msgs.range_msg(
                    ts, d, field_of_view_rad=msgs.FIELD_OF_VIEW_RAD, min_range_mm=lo,
                    max_range_mm=hi)
                yield ts, f"/dmdsm/distance/{m}", msgs.distance_msg(
                    ts, m, d, std[m][row], float(p[f"snr_{m}_db"][row]),
                    shot_id=int(p["point_index"][row]))
        group.append(row)
        key = (int(p["level"][row]), int(p["angle_index"][row]))
        nxt = order[k + 1] if k + 1 < n else None
        if nxt is None or (int(p["level"][nxt]), int(p["angle_index"][nxt])) != key:
            yield ts, "/dmdsm/points", _cloud(pts, p, set(group), ts)
            group = []


def _cloud(pts: dict, p: dict, rows: set[int], t_s: float) -> dict:
    """PointCloud2 (object frame) of a line's points: x, y, z, sigma_m (the distance's std
    along the beam), snr_db, modality (0 OA, 1 US), point_index."""
    xyz, extra = [], {"sigma_m": [], "snr_db": [], "modality": [], "point_index": []}
    for i, m in enumerate(MODS):
        q = pts[m]
        sel = np.isin(q["row"], list(rows))
        xyz.append(q["P"][sel])
        extra["sigma_m"].append(q["d_std"][sel] * msgs.MM)
        extra["snr_db"].append(p[f"snr_{m}_db"][q["row"][sel]])
        extra["modality"].append(np.full(int(sel.sum()), float(i)))
        extra["point_index"].append(q["index"][sel].astype(float))
    return msgs.pointcloud2(t_s, "object", np.vstack(xyz),
                            {k: np.concatenate(v) for k, v in extra.items()})


def export_scan_mcap(scan: ScanData, out_path: Path, *, model: object | None = None,
                     flag: str = "--mcap") -> dict:
    """Write the scan (and the object's model, if given) to out_path atomically (a temporary
    file beside it, renamed on success; files.atomic_output refuses folders, devices and
    FIFOs). Returns a summary: path, messages, per-topic counts, start and end stamps (s)."""
    with atomic_output(out_path, flag=flag) as tmp:
        out = _record(scan, tmp, Path(out_path), model, flag)
    return out


def export_scan_bag(scan: ScanData, bag: Path, *, model: object | None = None,
                    flag: str = "--bag") -> dict:
    """Write the scan as a rosbag2 bag folder that ROS 2 (Humble) opens as it is: BAG/NAME_0.mcap
    (export_scan_mcap's file) and BAG/metadata.yaml computed from that file's summary
    (bag_metadata). BAG is created if missing (its parent must exist); other files in it are
    left alone. Both files are written atomically; an earlier metadata.yaml is removed just
    before the new MCAP takes the old one's place, so a crash between the two renames leaves
    a bag without metadata (`ros2 bag reindex BAG mcap`), never one describing another file.
    Returns export_scan_mcap's summary with `bag` (the folder)."""
    mcap = bags.bag_file(bag, flag)
    created = bags.make_bag_dir(bag, flag)
    try:
        with atomic_output(Path(bag) / bags.METADATA, flag=flag) as tmp_yaml:
            with atomic_output(mcap, flag=flag) as tmp:
                out = _record(scan, tmp, mcap, model, flag)
                tmp_yaml.write_text(bags.metadata_yaml(bags.bag_metadata(tmp, mcap.name)),
                                    encoding="utf-8")
                bags.drop_metadata(bag)
    except BaseException:
        if created:  # a new bag that got nothing: no empty folder left behind
            with contextlib.suppress(OSError):
                os.rmdir(bag)
        raise
    return {**out, "bag": str(bag)}


def _record(scan: ScanData, tmp: Path, out_path: Path, model: object | None,
            flag: str) -> dict:
    """Write the scan's messages to tmp (the temporary file of out_path); the summary."""
    items = scan_messages(scan, model)
    counts: dict[str, int] = {}
    first = last = None
    meta = {"scan_id": str(scan.entry.get("scan_id", "")),
            "object_id": str(scan.sample.get("name", "")),
            "material": str(scan.sample.get("material", "")),
            "stamps": "host_time (Unix s)",
            "model_version": str(getattr(model, "version", "")) if model is not None else ""}
    try:
        with McapRecorder(tmp, flag=flag, chunk_size=CHUNK_BYTES, reserve_bytes=0,
                          metadata=meta) as rec:
            for topic in TOPICS:
                if topic != "/dmdsm/model" or model is not None:
                    rec.channel(topic, TOPICS[topic], latched=topic in LATCHED)
            for ts, topic, msg in items:
                rec.write(topic, TOPICS[topic], msg, msgs.to_ns(ts))
                counts[topic] = counts.get(topic, 0) + 1
                first, last = ts if first is None else first, ts
    except RecordingStopped as e:  # the temporary file goes; the target is untouched
        raise write_failed(out_path, e.error or OSError(str(e)), flag) from None
    return {"path": str(out_path), "messages": sum(counts.values()), "topics": counts,
            "start_s": first, "end_s": last, "metadata": meta}
