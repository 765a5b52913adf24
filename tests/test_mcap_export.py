"""`dmdsm db export SCAN --mcap FILE` (issue 34): the file, read back by the `mcap` reader
with mcap-ros2-support's decoder and by rosbags (which opens a bare .mcap), holds every
waveform, distance, range and point of the HDF5 scan with its stamp, in time order; its /tf
frames put each distance's point where the reconstruction puts it; the object's model is a
mesh marker; a full disk or a bad target leaves the earlier file and no temporary one."""

import errno
import json
import os

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rosbags.highlevel import AnyReader
from rosbags.interfaces import QosDurability
from test_model_store import tiny_model
from test_parquet_export import write_scan
from test_robotics_messages import plain, same

from dmdsm.host.commands.cli import main
from dmdsm.host.model.store import write_model
from dmdsm.host.robotics import mcap_file
from dmdsm.host.robotics.messages import to_ns
from dmdsm.host.robotics.scan_export import depth_gate_mm, export_scan_mcap
from dmdsm.host.scan.catalogue import find_scan
from dmdsm.host.scan.points import MODS, scan_points
from dmdsm.host.scan.scanfile import read_scan
from dmdsm.sim.data.dataset import make_database


@pytest.fixture(scope="module")
def db(tmp_path_factory):
    """A simulated scan of a soda can (both modalities, no model) and a hand-written fly-like
    scan of a mug (lost waveforms, stamps a second apart) whose object has a 3D model."""
    db = tmp_path_factory.mktemp("mcap") / "db"
    paths = make_database(db, points=24, seed=0, objects=["soda_can"])
    write_scan(db, "mug-fly", paths[0], rows=23)
    write_model(db, tiny_model("mug", sources=[
        {"scan_id": "mug-fly", "content_hash": "0" * 64, "material": "steel"}]))
    return db


def export(db, scan_id, out, capsys) -> dict:
    assert main(["db", "export", "--db", str(db), scan_id, "--mcap", str(out), "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def read_mcap(path) -> dict[str, list[tuple[int, object]]]:
    """topic -> [(log time ns, decoded)] by mcap + mcap-ros2-support; rosbags reads the same
    topics, types, counts, times and values."""
    out: dict[str, list] = {}
    with open(path, "rb") as f:
        for _, ch, msg, m in make_reader(f, decoder_factories=[DecoderFactory()]
                                         ).iter_decoded_messages(log_time_order=False):
            out.setdefault(ch.topic, []).append((msg.log_time, m))
    other: dict[str, list] = {}
    with AnyReader([path]) as ar:
        for c, t, raw in ar.messages():
            other.setdefault(c.topic, []).append((t, ar.deserialize(raw, c.msgtype)))
    assert other.keys() == out.keys()
    for topic, msgs in out.items():
        assert [t for t, _ in other[topic]] == [t for t, _ in msgs], topic
        for (_, a), (_, b) in zip(msgs, other[topic], strict=True):
            assert same(plain(a), plain(b)), topic
    return out


def quat_matrix(q) -> np.ndarray:
    x, y, z, w = q.x, q.y, q.z, q.w
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def ns(stamp) -> int:
    return stamp.sec * 1_000_000_000 + stamp.nanosec


@pytest.mark.parametrize("scan_id", ["soda_can-s0", "mug-fly"])
def test_the_file_holds_the_scan_as_the_hdf5_does(db, tmp_path, capsys, scan_id):
    out = tmp_path / "scan.mcap"
    summary = export(db, scan_id, out, capsys)
    scan = read_scan(find_scan(db, scan_id)["path"])
    p, n = scan.points, scan.n_points
    pts = scan_points(scan)
    got = read_mcap(out)
    order = np.argsort(p["host_time"], kind="stable")
    received = p["received"][order]
    runs = 1 + int(np.sum(np.diff(p["level"][order] * 1000 + p["angle_index"][order]) != 0))
    has_model = scan_id == "mug-fly"
    counts = {"/tf_static": 1, "/tf": n, "/dmdsm/waveform": n, "/dmdsm/points": runs,
              **{f"/dmdsm/{k}/{m}": int(received.sum()) for k in ("range", "distance")
                 for m in MODS}, **({"/dmdsm/model": 1} if has_model else {})}
    assert {k: len(v) for k, v in got.items()} == counts == summary["mcap"]["topics"]
    with open(out, "rb") as f:  # written in time order, from the first shot's stamp
        written = [m.log_time for _, _, m in make_reader(f).iter_messages(
            log_time_order=False)]
    assert written == sorted(written) and written[0] == to_ns(p["host_time"][order[0]])
    for msgs in got.values():  # log time = header stamp
        for t, m in msgs:
            for h in ([m.header] if hasattr(m, "header") else
                      [x.header for x in getattr(m, "transforms", [])]):
                assert ns(h.stamp) == t

    stamps = [to_ns(x) for x in p["host_time"][order]]
    waves = got["/dmdsm/waveform"]
    assert [t for t, _ in waves] == stamps
    rate = scan.sensor["adc_rate_hz"] / scan.sensor.get("config_sample_rate_div", 1)
    for (_, w), row in zip(waves, order, strict=True):
        assert w.shot_id == p["point_index"][row] and w.received == p["received"][row]
        assert list(w.samples) == (scan.waveforms[row].tolist() if p["received"][row] else [])
        assert (w.n_average, w.timestamp_ticks, w.trigger_phase_ticks, w.sample_rate_hz) == (
            p["n_average"][row], p["timestamp"][row], p["trigger_phase"][row], rate)
        assert w.header.frame_id == "sensor"

    rows = order[received]
    lo, hi = depth_gate_mm(scan)
    for m in MODS:
        std = dict(zip(pts[m]["row"].tolist(), pts[m]["d_std"].tolist(), strict=True))
        dist, rng = got[f"/dmdsm/distance/{m}"], got[f"/dmdsm/range/{m}"]
        assert [t for t, _ in dist] == [t for t, _ in rng] == [stamps[i] for i in
                                                              np.flatnonzero(received)]
        for (_, a), (_, r), row in zip(dist, rng, rows, strict=True):
            d = p[f"distance_{m}_mm"][row]
            assert a.modality == m and a.valid == np.isfinite(d)
            assert same(a.distance_m, d * 1e-3) and same(a.sigma_m, std.get(row, np.nan) * 1e-3)
            assert a.snr_db == np.float32(p[f"snr_{m}_db"][row]) or np.isnan(a.snr_db)
            assert r.range == (np.float32(d * 1e-3) if np.isfinite(d) else np.inf)
            assert (r.min_range, r.max_range) == (np.float32(lo * 1e-3), np.float32(hi * 1e-3))
            assert r.radiation_type == 0 and r.field_of_view > 0

    cloud = []
    for _, c in got["/dmdsm/points"]:
        assert c.header.frame_id == "object" and c.height == 1
        dt = np.dtype({"names": [f.name for f in c.fields], "formats": ["<f4"] * len(c.fields),
                       "offsets": [f.offset for f in c.fields], "itemsize": c.point_step})
        cloud.append(np.frombuffer(bytes(c.data), dt))
    cloud = np.concatenate(cloud)
    for i, m in enumerate(MODS):
        mine = cloud[cloud["modality"] == i]
        key = np.lexsort((mine["z"], mine["y"], mine["x"], mine["point_index"]))
        want = pts[m]["P"] * 1e-3
        ref = np.lexsort((want[:, 2], want[:, 1], want[:, 0], pts[m]["index"]))
        assert len(mine) == len(want)
        xyz = np.column_stack([mine["x"], mine["y"], mine["z"]])[key]
        assert np.allclose(xyz, want[ref], atol=1e-6)
        assert np.allclose(mine["sigma_m"][key], pts[m]["d_std"][ref] * 1e-3, equal_nan=True)

    # the frames: sensor pose + distance along its +x, into the table frame = the point
    tfs = [m for _, m in got["/tf"]]
    static = got["/tf_static"][0][1].transforms[0]
    assert (static.header.frame_id, static.child_frame_id) == ("table", "object")
    assert static.transform.rotation.w == 1.0 and static.transform.translation.x == 0.0
    for m in MODS:
        for k, row in enumerate(pts[m]["row"]):
            tf = {t.child_frame_id: t for t in tfs[int(np.flatnonzero(order == row)[0])]
                  .transforms}
            assert all(t.header.frame_id == "stage" for t in tf.values())
            s, tb = tf["sensor"].transform, tf["table"].transform
            X = np.array([s.translation.x, s.translation.y, s.translation.z]) + \
                quat_matrix(s.rotation) @ [pts[m]["d"][k] * 1e-3, 0, 0]
            P = quat_matrix(tb.rotation).T @ (
                X - [tb.translation.x, tb.translation.y, tb.translation.z])
            assert np.allclose(P, pts[m]["P"][k] * 1e-3, atol=1e-9)

    with AnyReader([out]) as ar:
        qos = {c.topic: c.ext.offered_qos_profiles for c in ar.connections}
    assert qos["/tf_static"][0].durability == QosDurability.TRANSIENT_LOCAL
    if has_model:
        model = tiny_model("mug")
        (_, mk), = got["/dmdsm/model"]
        assert mk.type == 11 and mk.header.frame_id == "object"
        want = model.vertices_mm[model.faces.reshape(-1)] * 1e-3
        assert np.array_equal([[q.x, q.y, q.z] for q in mk.points], want)
        assert len(mk.colors) == len(want)
        assert qos["/dmdsm/model"][0].durability == QosDurability.TRANSIENT_LOCAL


def test_a_full_disk_or_a_bad_target_keeps_the_earlier_file(db, tmp_path, capsys,
                                                            monkeypatch):
    out = tmp_path / "d.mcap"
    out.write_bytes(b"earlier")
    written = {"n": 0}

    def fills(fd, data):
        written["n"] += len(data)
        if written["n"] > 3000:  # the file is ~15 kB
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return os.write(fd, data)

    monkeypatch.setattr(mcap_file, "_write", fills)
    assert main(["db", "export", "--db", str(db), "soda_can-s0", "--mcap", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"no space left on the device holding {out}" in err and len(err.splitlines()) == 1
    assert out.read_bytes() == b"earlier" and os.listdir(tmp_path) == ["d.mcap"]
    monkeypatch.undo()
    os.mkfifo(tmp_path / "fifo")
    for target, said in ((tmp_path, "is a folder"), (tmp_path / "fifo", "FIFO")):
        assert main(["db", "export", "--db", str(db), "soda_can-s0", "--mcap",
                     str(target)]) == 2
        assert said in capsys.readouterr().err
    assert main(["db", "export", "--db", str(db), "soda_can-s0", "--mcap", str(out)]) == 0
    assert out.read_bytes()[:8] == b"\x89MCAP0\r\n"
    assert sorted(os.listdir(tmp_path)) == ["d.mcap", "fifo"]


@pytest.mark.parametrize("bad", [np.nan, -1.0, 2.0**31])
def test_host_times_no_ros_stamp_can_hold_are_refused_before_writing(db, tmp_path, bad):
    scan = read_scan(find_scan(db, "mug-fly")["path"])
    scan.points["host_time"][3] = bad
    with pytest.raises(ValueError, match="host_time holds .* damaged"):
        export_scan_mcap(scan, tmp_path / "x.mcap")
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("scan_id", ["soda_can-s0", "mug-fly"])
def test_a_bag_folder_opens_in_rosbag2s_reader_as_the_file_does(db, tmp_path, capsys,
                                                                 scan_id):
    """`--bag DIR`: the --mcap file, byte for byte, beside a metadata.yaml with which rosbags'
    rosbag2 Reader opens the folder: the same topics, types, counts and stamps as the `mcap`
    reader gives (and rosbags on the bare file)."""
    from rosbags.rosbag2 import Reader

    bag = tmp_path / "scan_bag"
    assert main(["db", "export", "--db", str(db), scan_id, "--bag", str(bag), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)["mcap"]
    mcap = bag / "scan_bag_0.mcap"
    assert sorted(os.listdir(bag)) == ["metadata.yaml", "scan_bag_0.mcap"]
    assert summary["path"] == str(mcap) and summary["bag"] == str(bag)
    plain = export(db, scan_id, tmp_path / "plain.mcap", capsys)["mcap"]
    assert mcap.read_bytes() == (tmp_path / "plain.mcap").read_bytes()
    assert summary["topics"] == plain["topics"]

    times, types = {}, {}
    with open(mcap, "rb") as f:
        for schema, ch, m in make_reader(f).iter_messages(log_time_order=False):
            times.setdefault(ch.topic, []).append(m.log_time)
            types[ch.topic] = schema.name
    assert {k: len(v) for k, v in times.items()} == summary["topics"]
    first, last = min(map(min, times.values())), max(map(max, times.values()))
    assert first == to_ns(summary["start_s"]) and last == to_ns(summary["end_s"])
    for path in (bag, mcap):  # the folder through metadata.yaml; the file alone
        with Reader(path) as r:
            assert {c.topic: (c.msgtype, c.msgcount) for c in r.connections} == {
                k: (types[k], len(v)) for k, v in times.items()}
            assert r.message_count == sum(summary["topics"].values())
            assert (r.start_time, r.end_time) == (first, last + 1)
            got = {}
            for c, t, _ in r.messages():
                got.setdefault(c.topic, []).append(t)
            assert got == times
            qos = {c.topic: c.ext.offered_qos_profiles for c in r.connections}
            assert qos["/tf_static"][0].durability == QosDurability.TRANSIENT_LOCAL
            assert qos["/tf"] == []


def test_a_bag_is_replaced_whole_or_not_at_all(db, tmp_path, capsys, monkeypatch):
    bag = tmp_path / "b"
    assert main(["db", "export", "--db", str(db), "mug-fly", "--bag", str(bag)]) == 0
    assert "ROS 2 messages to" in capsys.readouterr().out
    (bag / "notes.txt").write_text("mine")
    before = {p: (bag / p).read_bytes() for p in os.listdir(bag)}
    written = {"n": 0}

    def fills(fd, data):
        written["n"] += len(data)
        if written["n"] > 3000:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return os.write(fd, data)

    monkeypatch.setattr(mcap_file, "_write", fills)
    for target in (bag, tmp_path / "new"):  # an earlier bag stays; a new one is not made
        assert main(["db", "export", "--db", str(db), "soda_can-s0", "--bag",
                     str(target)]) == 2
        err = capsys.readouterr().err
        assert "no space left on the device holding" in err and len(err.splitlines()) == 1
    monkeypatch.undo()
    assert {p: (bag / p).read_bytes() for p in os.listdir(bag)} == before
    assert sorted(os.listdir(tmp_path)) == ["b"]
    # replaced: the MCAP and metadata.yaml are the new scan's; other files are left alone
    assert main(["db", "export", "--db", str(db), "soda_can-s0", "--bag", str(bag),
                 "--json"]) == 0
    n = json.loads(capsys.readouterr().out)["mcap"]["messages"]
    assert sorted(os.listdir(bag)) == ["b_0.mcap", "metadata.yaml", "notes.txt"]
    assert f"message_count: {n}\n" in (bag / "metadata.yaml").read_text()
    for args, said in ((["--bag", str(bag / "notes.txt")], "is not a folder"),
                       (["--bag", str(tmp_path / "no" / "bag")], "does not exist"),
                       (["--bag", str(bag), "--mcap", str(tmp_path / "x.mcap")], "give one")):
        assert main(["db", "export", "--db", str(db), "soda_can-s0", *args]) == 2
        err = capsys.readouterr().err
        assert said in err and len(err.splitlines()) == 1
    assert sorted(os.listdir(tmp_path)) == ["b"]
