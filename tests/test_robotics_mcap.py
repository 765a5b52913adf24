"""The MCAP recorder (host/robotics/mcap_file.py, issue 34): schemas and channels registered
as ROS 2 tools expect; a full disk stops the recording with a one-line error and leaves a file
the `mcap` reader and rosbags open, holding every message written before it; Ctrl-C (inside a
write, between writes, or a real SIGINT to a recording process) closes the file properly."""

import errno
import os
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rosbags.highlevel import AnyReader
from rosbags.interfaces import QosDurability

from dmdsm.host.files import OutputError
from dmdsm.host.robotics import mcap_file as F
from dmdsm.host.robotics import messages as M

ROOT = Path(__file__).resolve().parents[1]
DIST = "dmdsm_msgs/msg/Distance"
WAVE = "dmdsm_msgs/msg/Waveform"


def distance(i: int) -> dict:
    return M.distance_msg(1.7e9 + i, "us", 10.0 + i, 0.05, 20.0, shot_id=i)


def read_back(path: Path) -> tuple[list[tuple[str, int, int]], object]:
    """(topic, shot_id, log_time) of every message by mcap's reader with mcap-ros2's
    decoder, checked equal to what rosbags reads; and the summary (None if none)."""
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        got = [(ch.topic, m.shot_id, msg.log_time)
               for _, ch, msg, m in reader.iter_decoded_messages()]
        f.seek(0)
        summary = make_reader(f).get_summary()
    with AnyReader([path]) as ar:
        other = [(c.topic, ar.deserialize(raw, c.msgtype).shot_id, t)
                 for c, t, raw in ar.messages()]
    assert sorted(other, key=lambda x: x[2]) == sorted(got, key=lambda x: x[2])
    return got, summary


class FullDisk:
    """A file system of `capacity` bytes holding the recording and its reserve file: a write
    past it fills what is left and then fails with ENOSPC, as the kernel does."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch, path: Path, capacity: int) -> None:
        self.files = [path, path.with_name(f".{path.name}-reserve")]
        self.capacity = capacity
        monkeypatch.setattr(F, "_write", self.write)

    def write(self, fd: int, data: bytes) -> int:
        pos, size = os.lseek(fd, 0, os.SEEK_CUR), os.fstat(fd).st_size
        used = sum(p.stat().st_size for p in self.files if p.exists())
        room = self.capacity - used
        if pos + len(data) - size > room:
            fits = size + room - pos
            if fits <= 0:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            data = bytes(data)[:fits]
        return os.write(fd, data)


def test_channels_and_schemas_are_registered_as_ros2_tools_expect(tmp_path):
    path = tmp_path / "a.mcap"
    with F.McapRecorder(path) as rec:
        rec.write("/dmdsm/distance/us", DIST, distance(0), 5, publish_time_ns=7)
        rec.write("/dmdsm/distance/oa", DIST, M.encode(DIST, distance(1)), 6)  # bytes as is
        rec.channel("/tf_static", "tf2_msgs/msg/TFMessage", latched=True)
        with pytest.raises(ValueError, match="carries dmdsm_msgs/msg/Distance"):
            rec.channel("/dmdsm/distance/us", WAVE)
        with pytest.raises(ValueError, match="no schema"):
            rec.channel("/x", "sensor_msgs/msg/Image")
    assert not path.with_name(".a.mcap-reserve").exists()
    with open(path, "rb") as f:
        reader = make_reader(f)
        assert reader.get_header().profile == "ros2"
        s = reader.get_summary()
        msgs = list(reader.iter_messages())
    assert [(x.name, x.encoding, x.data.decode()) for x in s.schemas.values()] == [
        (DIST, "ros2msg", M.SCHEMAS[DIST]), ("tf2_msgs/msg/TFMessage", "ros2msg",
                                             M.SCHEMAS["tf2_msgs/msg/TFMessage"])]
    assert {c.topic: (c.message_encoding, c.schema_id) for c in s.channels.values()} == {
        "/dmdsm/distance/us": ("cdr", 1), "/dmdsm/distance/oa": ("cdr", 1),
        "/tf_static": ("cdr", 2)}
    assert [(m.log_time, m.publish_time) for _, _, m in msgs] == [(5, 7), (6, 6)]
    assert s.statistics.message_count == 2
    with AnyReader([path]) as ar:
        qos = {c.topic: c.ext.offered_qos_profiles for c in ar.connections}
    assert qos["/tf_static"][0].durability == QosDurability.TRANSIENT_LOCAL
    assert qos["/dmdsm/distance/us"] == []


@settings(max_examples=25)
@given(capacity=st.integers(400, 6000), chunk=st.sampled_from([None, 700]),
       reserve=st.sampled_from([0, 256]))
def test_a_full_disk_stops_the_recording_and_leaves_a_readable_file(capacity, chunk, reserve):
    with tempfile.TemporaryDirectory() as tmp, pytest.MonkeyPatch.context() as mp:
        path = Path(tmp) / "full.mcap"
        FullDisk(mp, path, capacity + reserve)
        rec = F.McapRecorder(path, chunk_size=chunk, reserve_bytes=reserve)
        with pytest.raises(F.RecordingStopped) as e, rec:
            for i in range(10_000):
                rec.write("/d", DIST, distance(i), 1000 + i)
        assert "No space left on device" in str(e.value) and "\n" not in str(e.value)
        assert e.value.error.errno == errno.ENOSPC
        got, _ = read_back(path)
        assert got == [("/d", i, 1000 + i) for i in range(rec.on_disk)]
        assert f"holds the {rec.messages} messages" in str(e.value) if \
            rec.on_disk == rec.messages else f"{rec.on_disk} of the {rec.messages}" in str(e.value)
        if reserve and not chunk:  # nothing written is lost
            assert rec.on_disk == rec.messages
        assert rec.messages > 0 or capacity < 1500  # the schema record alone is ~600 bytes
        assert not path.with_name(".full.mcap-reserve").exists()
        with pytest.raises(F.RecordingStopped, match="stopped: No space"):
            rec.write("/d", DIST, distance(0), 0)  # it stays stopped, and says so again
        rec.finish()


def test_a_disk_full_to_the_byte_gives_up_the_last_message_for_the_files_end(
        tmp_path, monkeypatch):
    """No reserve, and the disk full exactly at the end of message 7: the file's end needs
    room, so message 7 makes it; the file holds 0..6 and says so."""
    probe = F.McapRecorder(tmp_path / "probe.mcap", reserve_bytes=0)
    ends = []
    for i in range(8):
        probe.write("/d", DIST, distance(i), i)
        ends.append(probe.good)
    probe.finish()
    path = tmp_path / "full.mcap"
    FullDisk(monkeypatch, path, ends[7])
    rec = F.McapRecorder(path, reserve_bytes=0)
    with pytest.raises(F.RecordingStopped, match="holds 7 of the 8 messages"):
        for i in range(9):
            rec.write("/d", DIST, distance(i), i)
    assert [s for _, s, _ in read_back(path)[0]] == list(range(7))


def test_ctrl_c_inside_a_write_cuts_the_partial_record_and_closes_the_file(tmp_path,
                                                                          monkeypatch):
    path = tmp_path / "int.mcap"
    calls = {"n": 0}

    def interrupted(fd, data):  # the 6th message: half its record lands, then Ctrl-C
        if len(data) > 1000:
            calls["n"] += 1
            if calls["n"] == 6:
                os.write(fd, bytes(data)[:len(data) // 2])
                raise KeyboardInterrupt
        return os.write(fd, data)

    monkeypatch.setattr(F, "_write", interrupted)
    with pytest.raises(KeyboardInterrupt), F.McapRecorder(path, reserve_bytes=0) as rec:
        for i in range(10):
            rec.write("/w", WAVE, M.waveform_msg(i, range(1024), shot_id=i,
                                                 sample_rate_hz=1e6), i)
    assert [s for _, s, _ in read_back(path)[0]] == [0, 1, 2, 3, 4]
    assert "interrupted while writing" in rec.stopped


def test_ctrl_c_or_an_error_between_writes_closes_the_file_with_its_summary(tmp_path):
    for kind in (KeyboardInterrupt, ValueError):
        path = tmp_path / f"{kind.__name__}.mcap"
        with pytest.raises(kind), F.McapRecorder(path) as rec:
            for i in range(5):
                rec.write("/d", DIST, distance(i), i)
            raise kind
        got, summary = read_back(path)
        assert [s for _, s, _ in got] == list(range(5))
        assert summary.statistics.message_count == 5 and len(summary.channels) == 1


def test_sigint_to_a_recording_process_leaves_a_closed_readable_file(tmp_path):
    path = tmp_path / "live.mcap"
    # Ctrl-C's own handler, set here: a child inherits an ignored SIGINT from a shell's
    # background job (`make test &`), and Python then installs no KeyboardInterrupt at all
    script = f"""
import signal, sys, time
signal.signal(signal.SIGINT, signal.default_int_handler)
from dmdsm.host.robotics import mcap_file as F, messages as M
with F.McapRecorder({str(path)!r}) as rec:
    i = 0
    while True:
        rec.write("/d", "{DIST}", M.distance_msg(i, "us", 1.0, 0.1, 20.0, shot_id=i), i)
        i += 1
        if i == 200:
            print("ready", flush=True)
"""
    p = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, cwd=ROOT)
    try:
        assert p.stdout.readline().strip() == "ready"
        p.send_signal(signal.SIGINT)
        _, err = p.communicate(timeout=30)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    assert "KeyboardInterrupt" in err
    got, summary = read_back(path)
    n = len(got)
    assert n >= 200 and [s for _, s, _ in got] == list(range(n))
    assert summary is None or summary.statistics.message_count == n


def test_outputs_that_must_not_be_written_are_refused(tmp_path):
    os.mkfifo(tmp_path / "fifo")
    (tmp_path / "old.mcap").write_bytes(b"keep")
    for target, force, said in ((tmp_path, True, "is a folder"),
                                (tmp_path / "fifo", True, "FIFO"),
                                (tmp_path / "old.mcap", False, "--force"),
                                (tmp_path / "no" / "a.mcap", True, "does not exist")):
        with pytest.raises(OutputError, match=said):
            F.McapRecorder(target, force=force)
    assert (tmp_path / "old.mcap").read_bytes() == b"keep"


def test_a_disk_that_fills_while_the_summary_is_written_says_so_and_keeps_every_message(
        tmp_path, monkeypatch):
    probe = F.McapRecorder(tmp_path / "probe.mcap", reserve_bytes=0)
    for i in range(20):
        probe.write("/d", DIST, distance(i), i)
    end = probe.good
    probe.finish()
    path = tmp_path / "full.mcap"
    FullDisk(monkeypatch, path, end + 60)  # the plain end fits, the summary does not
    with pytest.raises(F.RecordingStopped, match="holds the 20 messages"):
        with F.McapRecorder(path, reserve_bytes=0) as rec:
            for i in range(20):
                rec.write("/d", DIST, distance(i), i)
    got, summary = read_back(path)
    assert [s for _, s, _ in got] == list(range(20)) and summary is None
    path2 = tmp_path / "full2.mcap"
    FullDisk(monkeypatch, path2, end + 60)
    rec = F.McapRecorder(path2, reserve_bytes=0)
    for i in range(20):
        rec.write("/d", DIST, distance(i), i)
    rec.finish()  # called plainly (a finally block), it never raises: stopped says why
    assert "holds the 20 messages" in rec.stopped
    assert [s for _, s, _ in read_back(path2)[0]] == list(range(20))


def test_a_disk_without_room_for_the_reserve_refuses_the_recording_before_it_starts(
        tmp_path, monkeypatch):
    path = tmp_path / "r.mcap"
    FullDisk(monkeypatch, path, 1000)
    with pytest.raises(OutputError, match=f"no space left on the device holding {path}"):
        F.McapRecorder(path, reserve_bytes=4096)
    assert os.listdir(tmp_path) == []
