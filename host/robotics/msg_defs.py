"""The .msg text of every ROS 2 type dmdsm publishes (Humble's field lists, and dmdsm_msgs').

Each entry is one type's own definition, as its .msg file holds it (comments dropped for
the standard types, kept for ours: they are the docs); `full_text` joins a type with every
type it uses, in the "ros2msg" schema encoding MCAP and Foxglove expect: the main definition,
then for each dependency a line of 80 '=', a line `MSG: pkg/Name` and its definition.
tests/test_robotics_messages.py checks the standard ones field for field against rosbags'
Humble type store.
"""

from __future__ import annotations

import re

SEPARATOR = "=" * 80

#: "pkg/msg/Name" -> that type's own .msg text
DEFINITIONS: dict[str, str] = {
    "builtin_interfaces/msg/Time": "int32 sec\nuint32 nanosec\n",
    "builtin_interfaces/msg/Duration": "int32 sec\nuint32 nanosec\n",
    "std_msgs/msg/Header": "builtin_interfaces/Time stamp\nstring frame_id\n",
    "std_msgs/msg/ColorRGBA": "float32 r\nfloat32 g\nfloat32 b\nfloat32 a\n",
    "geometry_msgs/msg/Vector3": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/msg/Point": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/msg/Quaternion": "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n",
    "geometry_msgs/msg/Pose": "Point position\nQuaternion orientation\n",
    "geometry_msgs/msg/Transform": "Vector3 translation\nQuaternion rotation\n",
    "geometry_msgs/msg/TransformStamped": (
        "std_msgs/Header header\nstring child_frame_id\nTransform transform\n"),
    "tf2_msgs/msg/TFMessage": "geometry_msgs/TransformStamped[] transforms\n",
    "sensor_msgs/msg/Range": (
        "uint8 ULTRASOUND=0\nuint8 INFRARED=1\n"
        "std_msgs/Header header\nuint8 radiation_type\nfloat32 field_of_view\n"
        "float32 min_range\nfloat32 max_range\nfloat32 range\n"),
    "sensor_msgs/msg/PointField": (
        "uint8 INT8    = 1\nuint8 UINT8   = 2\nuint8 INT16   = 3\nuint8 UINT16  = 4\n"
        "uint8 INT32   = 5\nuint8 UINT32  = 6\nuint8 FLOAT32 = 7\nuint8 FLOAT64 = 8\n"
        "string name\nuint32 offset\nuint8  datatype\nuint32 count\n"),
    "sensor_msgs/msg/PointCloud2": (
        "std_msgs/Header header\nuint32 height\nuint32 width\nPointField[] fields\n"
        "bool    is_bigendian\nuint32  point_step\nuint32  row_step\nuint8[] data\n"
        "bool is_dense\n"),
    "sensor_msgs/msg/CompressedImage": "std_msgs/Header header\nstring format\nuint8[] data\n",
    "visualization_msgs/msg/UVCoordinate": "float32 u\nfloat32 v\n",
    "visualization_msgs/msg/MeshFile": "string filename\nuint8[] data\n",
    "visualization_msgs/msg/Marker": (
        "int32 ARROW=0\nint32 CUBE=1\nint32 SPHERE=2\nint32 CYLINDER=3\nint32 LINE_STRIP=4\n"
        "int32 LINE_LIST=5\nint32 CUBE_LIST=6\nint32 SPHERE_LIST=7\nint32 POINTS=8\n"
        "int32 TEXT_VIEW_FACING=9\nint32 MESH_RESOURCE=10\nint32 TRIANGLE_LIST=11\n"
        "int32 ADD=0\nint32 MODIFY=0\nint32 DELETE=2\nint32 DELETEALL=3\n"
        "std_msgs/Header header\nstring ns\nint32 id\nint32 type\nint32 action\n"
        "geometry_msgs/Pose pose\ngeometry_msgs/Vector3 scale\nstd_msgs/ColorRGBA color\n"
        "builtin_interfaces/Duration lifetime\nbool frame_locked\n"
        "geometry_msgs/Point[] points\nstd_msgs/ColorRGBA[] colors\n"
        "string texture_resource\nsensor_msgs/CompressedImage texture\n"
        "UVCoordinate[] uv_coordinates\nstring text\nstring mesh_resource\n"
        "MeshFile mesh_file\nbool mesh_use_embedded_materials\n"),
    # ---- dmdsm's own (docs/robotics.md shows these texts) ----
    "dmdsm_msgs/msg/Waveform": """\
# One raw waveform of the dmdsm sensor board as it arrived. Both modalities share it:
# the optoacoustic (OA) arrival and the ultrasound (US) echo are windows of one record.
std_msgs/Header header        # stamp: the shot (docs/robotics.md, Stamps); frame: sensor
uint32 shot_id                # the shot's id in its acquisition (a scan: its point_index)
uint16[] samples              # raw ADC codes (the on-board mean when n_average > 1)
float64 sample_rate_hz        # samples per second of `samples`
uint16 n_average              # laser shots averaged on board
uint64 timestamp_ticks        # board timer ticks of the first averaged laser edge
uint16 trigger_phase_ticks    # board timer ticks from the laser edge to the first sample
bool received                 # false: the waveform was lost (samples then empty)
""",
    "dmdsm_msgs/msg/Distance": """\
# One modality's distance from one waveform, with its uncertainty (sensor_msgs/Range has
# no field for it). SI units: metres.
std_msgs/Header header        # stamp: the waveform's; frame_id: sensor
uint32 shot_id                # the waveform's shot_id (dmdsm_msgs/Waveform)
string modality               # "oa" (optoacoustic) or "us" (ultrasound pulse-echo)
bool valid                    # false: no arrival found (distance_m and sigma_m are NaN)
float64 distance_m            # sensor face to surface along the sensor axis (m)
float64 sigma_m               # standard deviation of distance_m (m); NaN if unknown
float32 snr_db                # signal-to-noise ratio of the arrival (dB)
""",
    "dmdsm_msgs/msg/Material": """\
# The material a classifier model gives one waveform: every class with its probability.
std_msgs/Header header        # stamp: the waveform's; frame_id: sensor
uint32 shot_id                # the waveform's shot_id (dmdsm_msgs/Waveform)
string model                  # the classifier model that decided (its file or id)
string[] classes              # class names, in the model's order
float32[] probabilities       # one per class, summing to 1
string best                   # the most probable class ("" if none)
float32 best_probability      # its probability
float64 distance_m            # the distance the decision used (m); NaN if none
""",
}

_BUILTIN = {"bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16",
            "int32", "uint32", "int64", "uint64", "string", "wstring"}


def _deps(datatype: str) -> list[str]:
    """The types one definition's fields use, as "pkg/msg/Name", in field order."""
    pkg = datatype.split("/")[0]
    out = []
    for line in DEFINITIONS[datatype].splitlines():
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        typ = re.split(r"\s+", line)[0]
        base = re.sub(r"(<=\d+)?\[.*\]$", "", typ)
        if base in _BUILTIN:
            continue
        p, _, name = base.rpartition("/")
        out.append(f"{p or pkg}/msg/{name}")
    return out


def full_text(datatype: str) -> str:
    """The schema text of datatype ("pkg/msg/Name") with every type it uses, depth first
    in first-use order, each once (the ros2msg schema encoding)."""
    order: list[str] = []

    def visit(t: str) -> None:
        for d in _deps(t):
            if d not in order and d != datatype:
                order.append(d)
                visit(d)

    visit(datatype)
    parts = [DEFINITIONS[datatype].rstrip("\n")]
    for d in order:
        pkg, _, name = d.split("/")
        parts.append(f"{SEPARATOR}\nMSG: {pkg}/{name}\n{DEFINITIONS[d].rstrip(chr(10))}")
    return "\n".join(parts) + "\n"
