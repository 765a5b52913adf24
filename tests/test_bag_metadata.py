"""rosbag2's metadata.yaml of an MCAP file (host/robotics/bag_metadata.py), read by rosbags.

From the file's own summary (or its records, when it ended without one): rosbags' rosbag2
Reader opens the bag folder with the same counts, topics, types, QoS and times as the `mcap`
reader gives; the YAML reads back as the same values whatever the strings hold (names, QoS
text), laid out as Humble writes it."""

import errno
import os
import string

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader
from rosbags.interfaces import QosDurability
from rosbags.rosbag2 import Reader
from ruamel.yaml import YAML

from dmdsm.host.files import OutputError
from dmdsm.host.robotics import bag_metadata as B
from dmdsm.host.robotics import mcap_file as F

TYPES = ["sensor_msgs/msg/Range", "dmdsm_msgs/msg/Distance", "tf2_msgs/msg/TFMessage",
         "dmdsm_msgs/msg/Waveform"]
CDR = b"\x00\x01\x00\x00" + bytes(12)  # any payload: nothing here decodes it


def record(path, plan, chunk_size=None, latched=()) -> dict[str, list[int]]:
    """An MCAP file of plan [(topic, datatype, [log times ns])] (channels in that order, a
    topic with no times registered all the same; messages in time order); topic -> times."""
    with F.McapRecorder(path, chunk_size=chunk_size, reserve_bytes=0) as rec:
        for topic, dt, _ in plan:
            rec.channel(topic, dt, latched=topic in latched)
        for t, topic, dt in sorted((t, topic, dt) for topic, dt, ts in plan for t in ts):
            rec.write(topic, dt, CDR, t)
    return {topic: sorted(ts) for topic, _, ts in plan}


def mcap_view(path) -> tuple[dict, dict, list[int]]:
    """What the `mcap` reader sees, messages read through: topic -> type, topic -> count,
    every log time."""
    with open(path, "rb") as f:
        reader = make_reader(f)
        types, counts, times = {}, {}, []
        for schema, ch, msg in reader.iter_messages(log_time_order=False):
            types[ch.topic] = schema.name
            counts[ch.topic] = counts.get(ch.topic, 0) + 1
            times.append(msg.log_time)
    return types, counts, times


def check_bag(bag, mcap, want: dict[str, list[int]], types: dict[str, str]) -> dict:
    """rosbags opens the folder through its metadata.yaml: the same topics, types, counts and
    times as the plan (and the mcap reader); the metadata as YAML."""
    meta = YAML(typ="safe").load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    times = sorted(t for ts in want.values() for t in ts)
    with Reader(bag) as r:
        assert [c.topic for c in r.connections] == list(want)
        assert {c.topic: (c.msgtype, c.msgcount) for c in r.connections} == {
            k: (types[k], len(v)) for k, v in want.items()}
        assert r.message_count == len(times)
        got: dict[str, list[int]] = {k: [] for k in want}
        for c, t, _ in r.messages():
            got[c.topic].append(t)
        assert got == want
        if times:  # rosbags' end time is one past the last message
            assert (r.start_time, r.end_time) == (times[0], times[-1] + 1)
        else:
            assert r.message_count == 0
    seen_types, seen_counts, seen_times = mcap_view(mcap)
    assert seen_counts == {k: len(v) for k, v in want.items() if v}
    assert all(seen_types[k] == types[k] for k in seen_types)
    assert sorted(seen_times) == times
    assert meta["version"] == 5 and meta["storage_identifier"] == "mcap"
    assert meta["relative_file_paths"] == [mcap.name] and meta["files"][0]["path"] == mcap.name
    start = times[0] if times else 0
    assert meta["starting_time"]["nanoseconds_since_epoch"] == start
    assert meta["duration"]["nanoseconds"] == (times[-1] - start if times else 0)
    assert meta["files"][0]["message_count"] == meta["message_count"] == len(times)
    assert meta["compression_format"] == meta["compression_mode"] == ""
    for tm in meta["topics_with_message_count"]:
        assert tm["topic_metadata"]["serialization_format"] == "cdr"
    return meta


T0 = 1_764_800_000_000_000_000
PLANS = {
    "no channels at all": [],
    "channels, no messages": [("/a", TYPES[0], []), ("/b", TYPES[1], [])],
    "one message": [("/dmdsm/range/us", TYPES[0], [T0])],
    "a topic left empty": [("/tf", TYPES[2], [T0, T0 + 5]), ("/empty", TYPES[1], []),
                           ("/dmdsm/waveform", TYPES[3], [T0 + 1, T0 + 2, T0 + 9])],
    "stamps at time 0": [("/tf", TYPES[2], [0, 0, 0])],
}


@pytest.mark.parametrize("chunked", [False, True])
@pytest.mark.parametrize("case", list(PLANS))
def test_the_metadata_of_a_recording_opens_as_a_bag(tmp_path, case, chunked):
    plan = PLANS[case]
    bag = tmp_path / "run"
    mcap = B.bag_file(bag)
    assert mcap == bag / "run_0.mcap" and not bag.exists()  # checks, touches nothing
    assert B.make_bag_dir(bag) and not B.make_bag_dir(bag)
    want = record(mcap, plan, 4096 if chunked else None, latched=("/tf",))
    B.write_bag_metadata(bag, mcap)
    assert sorted(os.listdir(bag)) == ["metadata.yaml", "run_0.mcap"]
    meta = check_bag(bag, mcap, want, {t: dt for t, dt, _ in plan})
    qos = {tm["topic_metadata"]["name"]: tm["topic_metadata"]["offered_qos_profiles"]
           for tm in meta["topics_with_message_count"]}
    assert all(q == (F.LATCHED_QOS if t == "/tf" else "") for t, q in qos.items())
    if "/tf" in want:
        with Reader(bag) as r:
            (c,) = [c for c in r.connections if c.topic == "/tf"]
            assert c.ext.offered_qos_profiles[0].durability == QosDurability.TRANSIENT_LOCAL


def test_a_recording_a_full_disk_ended_without_summary_is_counted_from_its_records(
        tmp_path, monkeypatch):
    bag = tmp_path / "b"
    B.make_bag_dir(bag)
    mcap = B.bag_file(bag)
    rec = F.McapRecorder(mcap, reserve_bytes=F.RESERVE_BYTES)
    rec.channel("/never", TYPES[1])
    for i in range(7):
        rec.write("/dmdsm/range/us" if i % 2 else "/tf", TYPES[0] if i % 2 else TYPES[2],
                  CDR, T0 + 10 * i)

    failed = []

    def full(fd, data):  # the summary's first write fails; the freed reserve takes the end
        if not failed:
            failed.append(1)
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return os.write(fd, data)

    monkeypatch.setattr(F, "_write", full)
    rec.finish()  # the summary does not fit: the file ends plainly after its last record
    assert rec.stopped and "holds the 7 messages" in rec.stopped
    monkeypatch.undo()
    with open(mcap, "rb") as f:
        assert make_reader(f).get_summary() is None
    B.write_bag_metadata(bag, mcap)
    want = {"/never": [], "/tf": [T0, T0 + 20, T0 + 40, T0 + 60],
            "/dmdsm/range/us": [T0 + 10, T0 + 30, T0 + 50]}
    check_bag(bag, mcap, want, {"/never": TYPES[1], "/tf": TYPES[2],
                                "/dmdsm/range/us": TYPES[0]})


def test_a_file_that_is_no_mcap_gets_no_metadata_and_one_line(tmp_path):
    bag = tmp_path / "b"
    bag.mkdir()
    (bag / "b_0.mcap").write_bytes(b"\x89MCAP0\r\n" + bytes(10))  # cut short
    with pytest.raises(OutputError, match=r"cannot read .* as MCAP .*ros2 bag reindex") as e:
        B.write_bag_metadata(bag, bag / "b_0.mcap")
    assert "\n" not in str(e.value) and os.listdir(bag) == ["b_0.mcap"]


def test_a_bag_folder_that_cannot_be_one_is_refused_before_anything_is_written(tmp_path):
    (tmp_path / "file").write_text("x")
    with pytest.raises(OutputError, match="is not a folder: --bag names the bag's folder"):
        B.bag_file(tmp_path / "file")
    with pytest.raises(OutputError, match="the folder .*missing.* does not exist"):
        B.bag_file(tmp_path / "missing" / "bag")
    (tmp_path / "bag").mkdir()
    os.mkfifo(tmp_path / "bag" / "metadata.yaml")
    with pytest.raises(OutputError, match="FIFO"):
        B.bag_file(tmp_path / "bag")
    assert sorted(os.listdir(tmp_path)) == ["bag", "file"]


# strings a bare YAML word would turn into something else, or that need escapes
AWKWARD = ["", "yes", "No", "null", "~", "true", "1", "0x10", "1e3", ".inf", "-", "- a", "a: b",
           "#c", " lead", "trail ", "'q'", '"dq"', "back\\slash", "tab\there", "line\nbreak",
           "\x85", "\u2028", "\ufeff", "\x00", "Ünïcödé", "\U0001f600", "\U000e0001", "%x",
           "@at", "`tick`", "{a}", "[a]", "&anchor", "*alias", "!tag", "|", ">", "?",
           "/dmdsm/range/us", "sensor_msgs/msg/Range", "2024_run_0.mcap"]
TEXT = st.one_of(st.sampled_from(AWKWARD),
                 st.text(st.characters(blacklist_categories=("Cs",)), max_size=30),
                 st.text(string.printable, max_size=30))


@st.composite
def infos(draw) -> dict:
    """Bag information as bag_metadata makes it, with any strings and numbers in it."""
    n = draw(st.integers(0, 4))
    topics = [{"topic_metadata": {"name": draw(TEXT), "type": draw(TEXT),
                                  "serialization_format": "cdr",
                                  "offered_qos_profiles": draw(st.one_of(
                                      TEXT, st.just(F.LATCHED_QOS)))},
               "message_count": draw(st.integers(0, 2**40))} for _ in range(n)]
    name = draw(TEXT)
    ns = st.integers(0, 2**63 - 1)
    times = {"starting_time": {"nanoseconds_since_epoch": draw(ns)},
             "duration": {"nanoseconds": draw(ns)}}
    total = sum(t["message_count"] for t in topics)
    return {"version": 5, "storage_identifier": "mcap", **times, "message_count": total,
            "topics_with_message_count": topics, "compression_format": "",
            "compression_mode": "", "relative_file_paths": [name],
            "files": [{"path": name, **times, "message_count": total}]}


@settings(max_examples=200, deadline=None)
@given(infos())
def test_the_yaml_reads_back_as_the_same_values_whatever_the_strings(info):
    text = B.metadata_yaml(info)
    assert YAML(typ="safe").load(text) == {"rosbag2_bagfile_information": info}
    assert YAML(typ="safe", pure=True).load(text) == {"rosbag2_bagfile_information": info}
    assert text.isascii() or all(c.isprintable() or c == "\n" for c in text)


def test_the_yaml_is_laid_out_as_humble_writes_it():
    info = {"version": 5, "storage_identifier": "mcap",
            "duration": {"nanoseconds": 7}, "starting_time": {"nanoseconds_since_epoch": 9},
            "message_count": 3,
            "topics_with_message_count": [{"topic_metadata": {
                "name": "/tf", "type": "tf2_msgs/msg/TFMessage", "serialization_format": "cdr",
                "offered_qos_profiles": ""}, "message_count": 3}],
            "compression_format": "", "compression_mode": "",
            "relative_file_paths": ["x_0.mcap"],
            "files": [{"path": "x_0.mcap", "starting_time": {"nanoseconds_since_epoch": 9},
                       "duration": {"nanoseconds": 7}, "message_count": 3}]}
    assert B.metadata_yaml(info) == """\
rosbag2_bagfile_information:
  version: 5
  storage_identifier: mcap
  duration:
    nanoseconds: 7
  starting_time:
    nanoseconds_since_epoch: 9
  message_count: 3
  topics_with_message_count:
    - topic_metadata:
        name: /tf
        type: tf2_msgs/msg/TFMessage
        serialization_format: cdr
        offered_qos_profiles: ""
      message_count: 3
  compression_format: ""
  compression_mode: ""
  relative_file_paths:
    - x_0.mcap
  files:
    - path: x_0.mcap
      starting_time:
        nanoseconds_since_epoch: 9
      duration:
        nanoseconds: 7
      message_count: 3
"""
