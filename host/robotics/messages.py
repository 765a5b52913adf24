"""The ROS 2 messages dmdsm publishes: their schema text, CDR encoding, and builders from
dmdsm's values (mm at our side, metres and seconds in every message: converted here).

Encoding: rosbags' CDR serializer over a type store built from SCHEMAS themselves, so the
bytes follow exactly the text written beside them; it writes numeric arrays (waveforms,
point clouds) as numpy blocks, where mcap_ros2's writer packs them element by element.
Builders return plain dicts (field name -> value, nested dicts for nested messages, numpy
arrays or lists for arrays); `encode` turns one into CDR bytes. Every Range, Distance,
Waveform and Material is in the `sensor` frame (docs/robotics.md, "Frames").
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from functools import cache

import numpy as np
from rosbags.interfaces import Nodetype

from .msg_defs import DEFINITIONS, full_text

#: the datatypes dmdsm publishes (topic types); their dependencies are in DEFINITIONS
PUBLISHED = ("sensor_msgs/msg/Range", "tf2_msgs/msg/TFMessage", "sensor_msgs/msg/PointCloud2",
             "visualization_msgs/msg/Marker", "dmdsm_msgs/msg/Waveform",
             "dmdsm_msgs/msg/Distance", "dmdsm_msgs/msg/Material")
#: datatype ("pkg/msg/Name") -> full ros2msg schema text (main definition + dependencies)
SCHEMAS: dict[str, str] = {t: full_text(t) for t in DEFINITIONS}
SCHEMA_ENCODING = "ros2msg"
MESSAGE_ENCODING = "cdr"
PROFILE = "ros2"

ULTRASOUND, INFRARED = 0, 1       # sensor_msgs/Range radiation_type
TRIANGLE_LIST, ADD = 11, 0        # visualization_msgs/Marker type, action
FLOAT32 = 7                       # sensor_msgs/PointField datatype
SENSOR_FRAME = "sensor"
FIELD_OF_VIEW_RAD = 0.1           # Range.field_of_view: the transducer's beam, full angle
MM = 1e-3                         # metres per millimetre

_NUMPY = {"bool": np.bool_, "byte": np.uint8, "char": np.uint8, "int8": np.int8,
          "uint8": np.uint8, "int16": np.int16, "uint16": np.uint16, "int32": np.int32,
          "uint32": np.uint32, "int64": np.int64, "uint64": np.uint64,
          "float32": np.float32, "float64": np.float64}


@cache
def typestore() -> object:
    """A rosbags type store holding exactly the types of SCHEMAS (parsed from their text)."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    ts = get_typestore(Stores.EMPTY)
    for name, text in SCHEMAS.items():
        ts.register(get_types_from_msg(text, name))
    return ts


def _value(ts: object, node: tuple, v: object) -> object:
    """One field's value as rosbags' dataclasses hold it."""
    kind, detail = node
    if kind == Nodetype.NAME:
        return _build(ts, detail, v if v is not None else {})
    if kind == Nodetype.BASE:
        typ = detail[0]
        if typ == "string":
            return "" if v is None else str(v)
        if typ == "bool":
            return bool(v)
        if typ.startswith("float"):
            return 0.0 if v is None else float(v)
        return 0 if v is None else int(v)
    sub, _ = detail
    items = [] if v is None else v
    if sub[0] == Nodetype.BASE and sub[1][0] != "string":
        return np.ascontiguousarray(items, dtype=_NUMPY[sub[1][0]]).reshape(-1)
    return [_value(ts, sub, x) for x in items]


def _build(ts: object, datatype: str, msg: Mapping | object) -> object:
    """A rosbags message object of datatype from a dict (missing fields: zero values)."""
    if not isinstance(msg, Mapping):
        return msg  # already a message object
    _, fields = ts.fielddefs[datatype]
    unknown = set(msg) - {name for name, _ in fields}
    if unknown:
        raise ValueError(f"{datatype} has no field {sorted(unknown)}")
    return ts.types[datatype](**{name: _value(ts, node, msg.get(name))
                                 for name, node in fields})


def encode(datatype: str, msg: Mapping) -> bytes:
    """CDR bytes (little endian, with the 4-byte encapsulation header) of msg, a dict of
    datatype's fields (absent fields are zero/empty). ValueError for an unknown field."""
    ts = typestore()
    if datatype not in ts.fielddefs:
        raise ValueError(f"unknown message type {datatype!r} (known: {', '.join(SCHEMAS)})")
    return bytes(ts.serialize_cdr(_build(ts, datatype, msg), datatype))


def decode(datatype: str, data: bytes) -> object:
    """The message object (attributes per field) of CDR bytes, by rosbags."""
    return typestore().deserialize_cdr(data, datatype)


# ---------------------------------------------------------------- builders


def stamp(t_s: float) -> dict:
    """builtin_interfaces/Time of t_s seconds (nanosecond resolution, rounded); ValueError
    outside its int32 seconds (Unix time 1901..2038) or for NaN."""
    ns = to_ns(t_s)
    sec = ns // 1_000_000_000
    if not -(2**31) <= sec < 2**31:
        raise ValueError(f"{t_s} s is outside a ROS time (int32 seconds)")
    return {"sec": sec, "nanosec": ns % 1_000_000_000}


def to_ns(t_s: float) -> int:
    """t_s seconds as integer nanoseconds, exactly as `stamp` splits them (the whole seconds
    apart from the fraction: a float of Unix time times 1e9 would lose 100 ns); an MCAP log
    time equal to the header stamp. ValueError for NaN or infinity."""
    t = float(t_s)
    if not math.isfinite(t):
        raise ValueError(f"a ROS time must be finite (got {t_s})")
    sec = math.floor(t)
    return sec * 1_000_000_000 + round((t - sec) * 1e9)


def header(t_s: float, frame_id: str = SENSOR_FRAME) -> dict:
    """std_msgs/Header at t_s seconds in frame frame_id."""
    return {"stamp": stamp(t_s), "frame_id": frame_id}


def _m(mm: float | None) -> float:
    return float("nan") if mm is None else float(mm) * MM


def range_msg(t_s: float, distance_mm: float, *, field_of_view_rad: float,
              min_range_mm: float, max_range_mm: float,
              radiation_type: int = ULTRASOUND, frame_id: str = SENSOR_FRAME) -> dict:
    """sensor_msgs/Range of one modality's distance (mm in, m out). No arrival (NaN) is
    +inf, REP 117's "nothing detected". radiation_type ULTRASOUND for OA too: its range is
    the acoustic time of flight of the sound the laser makes at the surface."""
    d = float(distance_mm)
    return {"header": header(t_s, frame_id), "radiation_type": int(radiation_type),
            "field_of_view": float(field_of_view_rad), "min_range": _m(min_range_mm),
            "max_range": _m(max_range_mm), "range": d * MM if math.isfinite(d) else math.inf}


def distance_msg(t_s: float, modality: str, distance_mm: float, sigma_mm: float | None,
                 snr_db: float, *, shot_id: int = 0, frame_id: str = SENSOR_FRAME) -> dict:
    """dmdsm_msgs/Distance of one modality ("oa"/"us"): distance and its standard deviation
    (mm in, m out; NaN distance: valid false), SNR in dB."""
    d = _m(distance_mm)
    return {"header": header(t_s, frame_id), "shot_id": int(shot_id), "modality": modality,
            "valid": math.isfinite(d), "distance_m": d, "sigma_m": _m(sigma_mm),
            "snr_db": float(snr_db)}


def waveform_msg(t_s: float, samples: np.ndarray, *, shot_id: int, sample_rate_hz: float,
                 n_average: int = 1, timestamp_ticks: int = 0, trigger_phase_ticks: int = 0,
                 received: bool = True, frame_id: str = SENSOR_FRAME) -> dict:
    """dmdsm_msgs/Waveform of one raw waveform (uint16 ADC codes, Hz, board ticks)."""
    return {"header": header(t_s, frame_id), "shot_id": int(shot_id),
            "samples": np.asarray(samples, np.uint16) if received else np.zeros(0, np.uint16),
            "sample_rate_hz": float(sample_rate_hz), "n_average": int(n_average),
            "timestamp_ticks": int(timestamp_ticks),
            "trigger_phase_ticks": int(trigger_phase_ticks), "received": bool(received)}


def material_msg(t_s: float, classes: Sequence[str], probabilities: Sequence[float], *,
                 shot_id: int = 0, model: str = "", distance_mm: float | None = None,
                 frame_id: str = SENSOR_FRAME) -> dict:
    """dmdsm_msgs/Material: every class with its probability, the best one named
    (distance in mm in, m out; None: NaN)."""
    p = np.asarray(probabilities, np.float32).reshape(-1)
    if len(p) != len(classes):
        raise ValueError(f"{len(classes)} classes but {len(p)} probabilities")
    best = int(np.argmax(p)) if len(p) else -1
    return {"header": header(t_s, frame_id), "shot_id": int(shot_id), "model": model,
            "classes": [str(c) for c in classes], "probabilities": p,
            "best": str(classes[best]) if best >= 0 else "",
            "best_probability": float(p[best]) if best >= 0 else 0.0,
            "distance_m": _m(distance_mm)}


def transform(t_s: float, parent: str, child: str, translation_mm: Sequence[float],
              quaternion_xyzw: Sequence[float] = (0.0, 0.0, 0.0, 1.0)) -> dict:
    """geometry_msgs/TransformStamped: the child frame's pose in the parent frame
    (translation in mm in, m out; unit quaternion x, y, z, w)."""
    x, y, z = (float(v) * MM for v in translation_mm)
    qx, qy, qz, qw = (float(v) for v in quaternion_xyzw)
    return {"header": header(t_s, parent), "child_frame_id": child,
            "transform": {"translation": {"x": x, "y": y, "z": z},
                          "rotation": {"x": qx, "y": qy, "z": qz, "w": qw}}}


def tf_msg(transforms: Sequence[Mapping]) -> dict:
    """tf2_msgs/TFMessage of TransformStamped dicts (see `transform`)."""
    return {"transforms": list(transforms)}


def pointcloud2(t_s: float, frame_id: str, points_xyz_mm: np.ndarray,
                fields: Mapping[str, np.ndarray] | None = None) -> dict:
    """sensor_msgs/PointCloud2, unordered (height 1), of N points: x, y, z (mm in, m out)
    then each extra field as float32 in the units given (name it with its unit, e.g.
    sigma_m); every field FLOAT32, little endian. NaN points make is_dense false."""
    p = np.asarray(points_xyz_mm, float).reshape(-1, 3) * MM
    cols = {"x": p[:, 0], "y": p[:, 1], "z": p[:, 2]}
    for name, v in (fields or {}).items():
        v = np.asarray(v, float).reshape(-1)
        if len(v) != len(p):
            raise ValueError(f"field {name} has {len(v)} values for {len(p)} points")
        cols[name] = v
    rec = np.zeros(len(p), dtype=[(k, "<f4") for k in cols])
    for k, v in cols.items():
        rec[k] = v
    step = 4 * len(cols)
    return {"header": header(t_s, frame_id), "height": 1, "width": len(p),
            "fields": [{"name": k, "offset": 4 * i, "datatype": FLOAT32, "count": 1}
                       for i, k in enumerate(cols)],
            "is_bigendian": False, "point_step": step, "row_step": step * len(p),
            "data": np.frombuffer(rec.tobytes(), np.uint8),
            "is_dense": bool(np.isfinite(p).all())}


def mesh_marker(t_s: float, frame_id: str, vertices_mm: np.ndarray, faces: np.ndarray,
                colors: np.ndarray | None = None, *, ns: str = "dmdsm/model", id: int = 0,
                rgba: Sequence[float] = (0.7, 0.7, 0.75, 1.0)) -> dict:
    """visualization_msgs/Marker TRIANGLE_LIST of a mesh: vertices (V, 3) in mm (m out),
    faces (F, 3) vertex indices; colors: optional RGBA in 0..1 per vertex (V, 4) or per
    face (F, 4), else one colour rgba for all. The marker never expires (lifetime 0)."""
    v = np.asarray(vertices_mm, float).reshape(-1, 3) * MM
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    tri = v[f.reshape(-1)]
    msg = {"header": header(t_s, frame_id), "ns": ns, "id": int(id), "type": TRIANGLE_LIST,
           "action": ADD, "pose": {"orientation": {"w": 1.0}},
           "scale": {"x": 1.0, "y": 1.0, "z": 1.0},
           "color": dict(zip("rgba", map(float, rgba), strict=True)),
           "points": [{"x": a, "y": b, "z": c} for a, b, c in tri.tolist()]}
    if colors is not None:
        c = np.asarray(colors, float).reshape(-1, 4)
        per = c[f.reshape(-1)] if len(c) == len(v) else np.repeat(c, 3, axis=0)
        if len(per) != len(tri):
            raise ValueError(f"{len(c)} colours for {len(v)} vertices and {len(f)} faces")
        msg["colors"] = [dict(zip("rgba", x, strict=True)) for x in per.tolist()]
    return msg
