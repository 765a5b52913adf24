"""The ROS 2 messages dmdsm publishes (host/robotics/messages.py, issue 34): their schema text
is Humble's field for field, and every builder's message, encoded by us, is decoded to the
same values by mcap-ros2-support's decoder and by rosbags (with Humble's own type store for
the standard types), and encoded to the same bytes by mcap-ros2-support's encoder."""

import array
import dataclasses
import math
import re
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from mcap.records import Schema
from mcap_ros2._dynamic import serialize_dynamic
from mcap_ros2.decoder import DecoderFactory
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from dmdsm.host.robotics import messages as M
from dmdsm.host.robotics.msg_defs import DEFINITIONS, SEPARATOR

HUMBLE = get_typestore(Stores.ROS2_HUMBLE)
FINITE = st.floats(-1e4, 1e4, allow_nan=False)
TIME = st.floats(0, 2**31 - 1, allow_nan=False)  # Unix seconds to 2038: int32 sec
NAME = st.text(st.characters(blacklist_categories=("Cs",), blacklist_characters="\x00"),
               max_size=12)


def mcap_ros2_decode(datatype: str, data: bytes) -> object:
    """Decoded by mcap-ros2-support from the schema text alone (as a reader of our files)."""
    schema = Schema(id=1, name=datatype, encoding="ros2msg", data=M.SCHEMAS[datatype].encode())
    return DecoderFactory().decoder_for("cdr", schema)(data)


def rosbags_decode(datatype: str, data: bytes) -> object:
    """Decoded by rosbags: Humble's own definitions for the standard types, a fresh store
    parsed from our schema text for dmdsm_msgs."""
    if datatype in HUMBLE.fielddefs:
        return HUMBLE.deserialize_cdr(data, datatype)
    ts = get_typestore(Stores.EMPTY)
    ts.register(get_types_from_msg(M.SCHEMAS[datatype], datatype))
    return ts.deserialize_cdr(data, datatype)


def plain(value: object) -> object:
    """A decoded message (either library's) as nested dicts and lists."""
    if isinstance(value, (bytes, bytearray, memoryview, array.array)):
        return list(bytes(value)) if not isinstance(value, array.array) else list(value)
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (list, tuple)):
        return [plain(x) for x in value]
    if dataclasses.is_dataclass(value):  # rosbags: fields, constants (upper case), __msgtype__
        return {f.name: plain(getattr(value, f.name)) for f in dataclasses.fields(value)
                if f.name[0].islower()}
    if hasattr(value, "__slots__"):  # mcap-ros2-support
        return {k: plain(getattr(value, k)) for k in value.__slots__}
    return value


def same(a: object, b: object) -> bool:
    """Equal as values (NaN equal to NaN)."""
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
    if isinstance(a, list):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, float) and math.isnan(a):
        return isinstance(b, float) and math.isnan(b)
    return a == b


def mcap_ros2_encode(datatype: str, msg: dict) -> bytes:
    """The same dict encoded by mcap-ros2-support (lists for arrays, bytes for uint8[])."""
    def lists(v: object) -> object:
        if isinstance(v, dict):
            return {k: lists(x) for k, x in v.items()}
        if isinstance(v, np.ndarray):
            return v.tobytes() if v.dtype == np.uint8 else v.tolist()
        if isinstance(v, list):
            return [lists(x) for x in v]
        return v
    name = datatype.replace("/msg/", "/")
    return serialize_dynamic(name, M.SCHEMAS[datatype])[name](lists(msg))


def check_round_trip(datatype: str, msg: dict) -> tuple[object, object]:
    """Encode msg; both decoders give the same values; mcap-ros2-support encodes the same
    bytes. Returns (mcap-ros2 decoded, rosbags decoded)."""
    data = M.encode(datatype, msg)
    a, b = mcap_ros2_decode(datatype, data), rosbags_decode(datatype, data)
    assert same(plain(a), plain(b)), (plain(a), plain(b))
    assert mcap_ros2_encode(datatype, msg) == data
    return a, b


def test_standard_schemas_are_humbles_field_for_field():
    """Every standard type we write (with its constants and defaults) parses to exactly the
    fields rosbags' Humble store holds, and every schema parses in mcap-ros2-support."""
    for datatype, text in M.SCHEMAS.items():
        types = get_types_from_msg(text, datatype)
        for name, (consts, fields) in types.items():
            if name.startswith("dmdsm_msgs/"):
                continue
            hc, hf = HUMBLE.fielddefs[name]
            assert (list(consts), list(fields)) == (list(hc), list(hf)), name
        schema = Schema(id=1, name=datatype, encoding="ros2msg", data=text.encode())
        assert DecoderFactory().decoder_for("cdr", schema) is not None
    assert "texture" in M.SCHEMAS["visualization_msgs/msg/Marker"]  # Humble's, not Foxy's


def test_schema_text_is_ros2msg_each_dependency_once():
    """The main definition first, then each type it uses once, after 80 '=' and MSG: line."""
    for datatype, text in M.SCHEMAS.items():
        parts = text.split(SEPARATOR + "\n")
        assert parts[0].rstrip("\n") == DEFINITIONS[datatype].rstrip("\n")
        names = [re.match(r"MSG: (\S+)\n", p).group(1) for p in parts[1:]]
        assert len(names) == len(set(names)) and datatype.replace("/msg/", "/") not in names
        for p, name in zip(parts[1:], names, strict=True):
            pkg, typ = name.split("/")
            assert p.split("\n", 1)[1].rstrip("\n") == \
                DEFINITIONS[f"{pkg}/msg/{typ}"].rstrip("\n")
    assert len(M.SCHEMAS["visualization_msgs/msg/Marker"].split(SEPARATOR)) == 12


@settings(max_examples=40)
@given(t=TIME, d=st.one_of(st.floats(0, 500), st.just(math.nan)), fov=st.floats(0, 3),
       lo=st.floats(0, 50), hi=st.floats(50, 500), kind=st.sampled_from([0, 1]))
def test_range_round_trips_in_metres(t, d, fov, lo, hi, kind):
    a, _ = check_round_trip("sensor_msgs/msg/Range", M.range_msg(
        t, d, field_of_view_rad=fov, min_range_mm=lo, max_range_mm=hi, radiation_type=kind))
    f32 = lambda x: float(np.float32(x))  # noqa: E731
    assert a.range == (f32(d / 1000) if math.isfinite(d) else math.inf)  # REP 117: +inf
    assert (a.min_range, a.max_range) == (f32(lo / 1000), f32(hi / 1000))
    assert a.radiation_type == kind and a.header.frame_id == "sensor"
    assert abs(a.header.stamp.sec + a.header.stamp.nanosec * 1e-9 - t) <= 1e-9 * max(1, t)


@settings(max_examples=40)
@given(t=TIME, m=st.sampled_from(["oa", "us"]),
       d=st.one_of(st.floats(0, 500), st.just(math.nan)),
       s=st.one_of(st.floats(0, 10), st.just(math.nan), st.none()), snr=FINITE,
       shot=st.integers(0, 2**32 - 1))
def test_distance_round_trips_with_sigma(t, m, d, s, snr, shot):
    a, _ = check_round_trip("dmdsm_msgs/msg/Distance",
                            M.distance_msg(t, m, d, s, snr, shot_id=shot))
    assert a.valid == math.isfinite(d) and a.modality == m and a.shot_id == shot
    assert same(a.distance_m, d * 1e-3) and same(a.sigma_m, math.nan if s is None else s * 1e-3)


@settings(max_examples=30)
@given(t=TIME, x=hnp.arrays(np.uint16, st.integers(0, 2048)), rate=st.floats(1e3, 1e9),
       n_avg=st.integers(1, 65535), ticks=st.integers(0, 2**64 - 1),
       phase=st.integers(0, 65535), received=st.booleans(), shot=st.integers(0, 2**32 - 1))
def test_waveform_round_trips_raw_samples(t, x, rate, n_avg, ticks, phase, received, shot):
    a, _ = check_round_trip("dmdsm_msgs/msg/Waveform", M.waveform_msg(
        t, x, shot_id=shot, sample_rate_hz=rate, n_average=n_avg, timestamp_ticks=ticks,
        trigger_phase_ticks=phase, received=received))
    assert list(a.samples) == (x.tolist() if received else [])
    assert (a.sample_rate_hz, a.n_average, a.timestamp_ticks, a.trigger_phase_ticks) == (
        rate, n_avg, ticks, phase)


@settings(max_examples=30)
@given(t=TIME, p=st.lists(st.floats(0, 1, width=32), max_size=8), data=st.data())
def test_material_round_trips_and_names_the_best(t, p, data):
    names = data.draw(st.lists(NAME, min_size=len(p), max_size=len(p)))
    a, _ = check_round_trip("dmdsm_msgs/msg/Material", M.material_msg(
        t, names, p, model="m.toml", distance_mm=12.5))
    assert a.classes == names and list(a.probabilities) == p
    assert a.best == (names[int(np.argmax(p))] if p else "")
    assert a.distance_m == 0.0125


@settings(max_examples=30)
@given(t=TIME, xyz=st.lists(st.tuples(FINITE, FINITE, FINITE), max_size=3),
       q=st.tuples(FINITE, FINITE, FINITE, FINITE))
def test_tf_round_trips_in_metres(t, xyz, q):
    msg = M.tf_msg([M.transform(t, "stage", f"c{i}", p, q) for i, p in enumerate(xyz)])
    a, _ = check_round_trip("tf2_msgs/msg/TFMessage", msg)
    for tr, p in zip(a.transforms, xyz, strict=True):
        v = tr.transform.translation
        assert (v.x, v.y, v.z) == tuple(c * 1e-3 for c in p)
        r = tr.transform.rotation
        assert (r.x, r.y, r.z, r.w) == q and tr.header.frame_id == "stage"


@settings(max_examples=30)
@given(t=TIME, pts=hnp.arrays(np.float64, st.tuples(st.integers(0, 50), st.just(3)),
                              elements=FINITE))
def test_pointcloud_fields_hold_the_points_in_metres(t, pts):
    sigma = np.arange(len(pts), dtype=float)
    a, _ = check_round_trip("sensor_msgs/msg/PointCloud2",
                            M.pointcloud2(t, "object", pts, {"sigma_m": sigma}))
    assert [f.name for f in a.fields] == ["x", "y", "z", "sigma_m"]
    assert all(f.datatype == 7 and f.count == 1 for f in a.fields)  # FLOAT32
    dt = np.dtype({"names": [f.name for f in a.fields], "formats": ["<f4"] * 4,
                   "offsets": [f.offset for f in a.fields], "itemsize": a.point_step})
    rec = np.frombuffer(bytes(a.data), dt)
    assert a.width == len(pts) and a.row_step == a.point_step * len(pts)
    assert np.array_equal(np.column_stack([rec["x"], rec["y"], rec["z"]]),
                          (pts * 1e-3).astype(np.float32))
    assert np.array_equal(rec["sigma_m"], sigma.astype(np.float32))


def test_mesh_marker_is_a_triangle_list_in_metres_with_colours():
    v = np.array([[0.0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10]])
    f = np.array([[0, 1, 2], [0, 3, 1]])
    per_vertex = np.linspace(0, 1, 16).reshape(4, 4)
    a, _ = check_round_trip("visualization_msgs/msg/Marker",
                            M.mesh_marker(2.0, "object", v, f, per_vertex))
    assert a.type == 11 and a.action == 0 and a.header.frame_id == "object"
    got = [(p.x, p.y, p.z) for p in a.points]
    assert got == [tuple(x) for x in (v[f.reshape(-1)] * 1e-3).tolist()]
    cols = [(c.r, c.g, c.b, c.a) for c in a.colors]
    assert cols == [tuple(np.float32(x).item() for x in per_vertex[i]) for i in f.reshape(-1)]
    b, _ = check_round_trip("visualization_msgs/msg/Marker",
                            M.mesh_marker(2.0, "object", v, f, np.eye(4)[:2]))
    assert [(c.r, c.g) for c in b.colors] == [(1.0, 0.0)] * 3 + [(0.0, 1.0)] * 3  # per face
    assert (a.pose.orientation.w, a.lifetime.sec, a.lifetime.nanosec) == (1.0, 0, 0)


@pytest.mark.parametrize("t, sec, nanosec", [(0.0, 0, 0), (1.5, 1, 500_000_000),
                                             (1.7e9 + 0.25, 1_700_000_000, 250_000_000),
                                             (-0.25, -1, 750_000_000), (2.9999999999, 3, 0)])
def test_stamp_splits_seconds_and_nanoseconds(t, sec, nanosec):
    assert M.stamp(t) == {"sec": sec, "nanosec": nanosec}


@pytest.mark.parametrize("t", [2.0**31, -(2.0**31) - 1, math.nan, math.inf])
def test_a_time_a_ros_stamp_cannot_hold_is_refused(t):
    with pytest.raises(ValueError, match="ROS time"):
        M.stamp(t)


def test_unknown_fields_and_types_are_refused():
    with pytest.raises(ValueError, match="no field"):
        M.encode("sensor_msgs/msg/Range", {"rang": 1.0})
    with pytest.raises(ValueError, match="unknown message type"):
        M.encode("sensor_msgs/msg/Image", {})
    with pytest.raises(ValueError, match="2 classes but 1"):
        M.material_msg(0.0, ["a", "b"], [1.0])


def test_the_docs_give_every_dmdsm_msgs_definition_and_exported_topic():
    """docs/robotics.md shows each of our .msg texts as the files hold it, and every topic
    the export writes, with its type."""
    from dmdsm.host.robotics.scan_export import TOPICS

    doc = (Path(__file__).resolve().parents[1] / "docs" / "robotics.md").read_text()
    for name in ("Waveform", "Distance", "Material"):
        text = DEFINITIONS[f"dmdsm_msgs/msg/{name}"]
        assert f"### dmdsm_msgs/msg/{name}\n\n```\n{text}```" in doc, name
    for topic, datatype in TOPICS.items():
        stem = topic.rsplit("/", 1)[0] if topic.endswith(("/oa", "/us")) else topic
        row = next(x for x in doc.splitlines() if x.startswith(f"| `{stem}"))
        assert f"`{datatype}`" in row, topic
