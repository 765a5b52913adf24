"""The live Foxglove server against the emulator, read by a foxglove.websocket.v1 client of
our own (the `websockets` library) and rosbags' CDR decoder: every record, in order."""

import itertools
import json
import math
import os
import signal
import subprocess
import sys
import threading
import time
from contextlib import closing

import numpy as np
import pytest
from live_helpers import SocketWsClient, WsClient, rosbags_decoder
from test_classify import db, model  # noqa: F401  (fixtures: a material model, trained once)

from dmdsm.host.links.sensor import SensorClient
from dmdsm.host.robotics.live import live
from dmdsm.host.robotics.server import TOPICS, LiveServer, ServeError, parse_serve
from dmdsm.sim.data.dataset import true_setup

N = 200


def decoders(client: WsClient) -> dict:
    """topic -> a decoder built from the advertised schema text alone."""
    assert {c["encoding"] for c in client.channels.values()} == {"cdr"}
    assert {c["schemaEncoding"] for c in client.channels.values()} == {"ros2msg"}
    return {c["topic"]: rosbags_decoder(c["schemaName"], c["schema"])
            for c in client.channels.values()}


def test_a_client_receives_every_record_in_order_and_a_stalled_one_stalls_nothing(emulator):
    emu = emulator(speed=2.0)
    sc = SensorClient(emu.sensor)
    sc.configure(n_samples=1024, n_average=1)
    srv = LiveServer("127.0.0.1", 0, sample_rate_hz=float(sc.identity.adc_rate_hz))
    stalled = WsClient(f"ws://127.0.0.1:{srv.port}", read=False)
    client = WsClient(f"ws://127.0.0.1:{srv.port}")
    for c in (client, stalled):
        assert c.subscribed.wait(10) and c.error is None, c.error
    recs, backlog = [], []
    publish_s = 0.0
    t0 = time.perf_counter()
    with closing(live(sc, true_setup(emu.sim.model))) as g:
        for r in itertools.islice(g, N):
            t = time.perf_counter()
            srv.publish(r)
            publish_s += time.perf_counter() - t
            recs.append(r)
            backlog.append(len(sc.stream or []))
    loop_s = time.perf_counter() - t0
    assert [r.seq for r in recs] == list(range(N))
    # the stalled client took nothing after subscribing, yet publishing never waited for
    # it (the server queued for it and dropped its oldest messages): a small share of the
    # loop, and the waveforms were taken as they came. Shares and counts, not a rate: on a
    # loaded machine the emulator itself slows down
    assert publish_s < 0.7 * loop_s, (publish_s, loop_s)
    assert max(backlog) < N // 2, max(backlog)
    got = {t: client.wait_for(t, N, 30) for t in ("/dmdsm/waveform", "/dmdsm/range/oa",
                                                   "/dmdsm/distance/us")}
    assert set(client.channels[i]["topic"] for i in client.channels) == set(TOPICS)
    dec = decoders(client)
    waves = [dec["/dmdsm/waveform"](p) for _, p, _ in got["/dmdsm/waveform"]]
    assert [w.shot_id for w in waves] == list(range(N))  # in order, none lost
    for r, w, (log_ns, _, _) in zip(recs, waves, got["/dmdsm/waveform"]):
        np.testing.assert_array_equal(w.samples, r.samples)
        assert w.timestamp_ticks == r.device_ticks and w.n_average == 1
        assert w.header.frame_id == "sensor"
        assert w.header.stamp.sec + w.header.stamp.nanosec * 1e-9 == pytest.approx(
            r.unix_s, abs=1e-6)
        assert log_ns == w.header.stamp.sec * 10**9 + w.header.stamp.nanosec
    ranges = [dec["/dmdsm/range/oa"](p) for _, p, _ in got["/dmdsm/range/oa"]]
    dists = [dec["/dmdsm/distance/us"](p) for _, p, _ in got["/dmdsm/distance/us"]]
    assert len(ranges) == len(dists) == N
    for r, rg, d in zip(recs, ranges, dists):
        oa, us = r.distance_mm["oa"], r.distance_mm["us"]
        assert rg.range == (math.inf if oa is None else pytest.approx(oa * 1e-3))
        assert rg.min_range == pytest.approx(0.005) and rg.max_range == pytest.approx(0.071)
        assert d.shot_id == r.seq and d.modality == "us" and d.valid == (us is not None)
        if us is not None:
            assert d.distance_m == pytest.approx(us * 1e-3)
            assert d.sigma_m == pytest.approx(r.distance_std_mm["us"] * 1e-3)
    client.close()
    stalled.close()
    srv.close()
    sc.close()


def test_publish_never_waits_for_a_client_that_does_not_read():
    """Without a board: 3000 waveform records (6 MB) to a client that never reads return
    as fast as with no client at all (the SDK's per-client queue drops the oldest)."""
    from dmdsm.host.robotics.live import LiveRecord

    srv = LiveServer("127.0.0.1", 0, sample_rate_hz=3.3e6)
    stalled = WsClient(f"ws://127.0.0.1:{srv.port}", read=False)
    assert stalled.subscribed.wait(10) and stalled.error is None
    done = threading.Event()

    def publish():
        for i in range(3000):
            srv.publish(LiveRecord(i, i, 1.0, 1e-4, 1.7e9 + i * 1e-3, 1.0, 1, 0,
                                   np.full(1024, i % 65536, np.uint16)))
        done.set()

    threading.Thread(target=publish, daemon=True).start()
    assert done.wait(60), "publish() blocked on a client that does not read"
    stalled.close()
    srv.close()


def test_the_benchs_socket_client_stamps_every_message_after_it_was_published():
    """bench/live.py's timing client (one blocking socket, websockets' sans-I/O framing):
    subscribed through the handshake and advertise, it gets every record's last message,
    in order, each stamped after the publish that sent it and before the next one's end."""
    from dmdsm.host.robotics.live import LiveRecord

    srv = LiveServer("127.0.0.1", 0, sample_rate_hz=3.3e6)
    client = SocketWsClient(f"ws://127.0.0.1:{srv.port}")
    assert set(client.subs.values()) == set(TOPICS)

    def record(i: int) -> LiveRecord:
        rec = LiveRecord(i, i, 1.0, 1e-4, 1.7e9 + i * 1e-3, 1.0, 1, 0,
                         np.full(1024, i, np.uint16))
        rec.distance_mm, rec.distance_std_mm, rec.snr_db = {"us": 7.0}, {"us": 0.01}, \
            {"us": 30.0}
        return rec

    for _ in range(200):  # the server applies the subscription on its own task: until one
        srv.publish(record(0))  # message comes back
        if client.read("/dmdsm/distance/us", 0.05):
            break
    else:
        raise AssertionError("the subscription never took effect")
    while client.read("/dmdsm/distance/us", 0.2) is not None:
        pass  # the warm-up's stragglers
    before, got = [], []
    for i in range(100):
        rec = record(i)
        before.append(time.monotonic())
        srv.publish(rec)
        while len(got) <= i:  # this record's message, stamped as its recv returned
            new = client.read("/dmdsm/distance/us", 10)
            assert new is not None, f"record {i} never arrived"
            got.extend(new)
    client.close()
    srv.close()
    assert len(got) == 100
    assert all(b <= a for b, a in zip(before, got)), "an arrival stamped before its publish"
    assert all(g <= t for g, t in zip(got, before[1:])), "an arrival stamped late"


def test_serve_refuses_another_network_and_a_port_in_use():
    assert parse_serve("8765") == ("127.0.0.1", 8765)
    assert parse_serve("localhost:9000") == ("localhost", 9000)
    assert parse_serve("[::1]:9000") == ("::1", 9000)
    with pytest.raises(ServeError, match="not a loopback address.*--allow-remote"):
        parse_serve("0.0.0.0:8765")
    assert parse_serve("0.0.0.0:8765", allow_remote=True) == ("0.0.0.0", 8765)
    with pytest.raises(ServeError, match="port 0..65535"):
        parse_serve("127.0.0.1:http")
    with pytest.raises(ServeError, match="not a loopback"):
        LiveServer("192.0.2.1", 0)
    a = LiveServer("127.0.0.1", 0)
    with pytest.raises(ServeError, match="the port is in use"):
        LiveServer("127.0.0.1", a.port)
    a.close()


def dmdsm_live(*args, **kw):
    """`dmdsm live ...` as a subprocess (stderr piped, text)."""
    return subprocess.Popen([sys.executable, "-m", "dmdsm.host", "live", *args],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kw)


def test_the_command_serves_records_ctrl_c_stops_it_and_the_mcap_reads_back(emulator, tmp_path):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    emu = emulator(speed=2.0)
    with SensorClient(emu.sensor) as sc:
        sc.configure(n_samples=1024, n_average=1)
    true_setup(emu.sim.model).save(tmp_path / "ranging.json")
    out = tmp_path / "live.mcap"
    p = dmdsm_live("--sensor", emu.sensor, "--ranging", str(tmp_path / "ranging.json"),
                   "--serve", "127.0.0.1:0", "--mcap", str(out), "--json")
    line = p.stderr.readline()  # the server is up: its port
    port = int(line.split("ws://127.0.0.1:")[1].split()[0])
    client = WsClient(f"ws://127.0.0.1:{port}")
    assert client.subscribed.wait(20) and client.error is None
    assert len(client.wait_for("/dmdsm/waveform", 50, 30)) >= 50  # records flow
    p.send_signal(signal.SIGINT)  # Ctrl-C: the normal end of a live run
    stdout, stderr = p.communicate(timeout=30)
    assert p.returncode == 0, stderr
    summary = json.loads(stdout)
    assert summary["records"] >= 50 and summary["lost"] == 0 and summary["mcap"] == str(out)
    client.close()
    with SensorClient(emu.sensor) as sc:  # disarmed on the way out
        assert not sc.took_over
    # the MCAP file, closed properly: summary, every record's waveform in order
    with open(out, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        assert reader.get_summary() is not None
        waves = [m.shot_id for _, ch, _, m in reader.iter_decoded_messages(
            topics=["/dmdsm/waveform"])]
    # (a Ctrl-C that lands while a record is being written is held until it is whole)
    assert waves == list(range(summary["records"]))


def test_the_commands_errors_are_one_line(emulator, tmp_path):
    emu = emulator()
    bad = tmp_path / "ranging.json"
    bad.write_text("{}")
    busy = LiveServer("127.0.0.1", 0)
    for args, text in (
            (["--sensor", emu.stage], "is the stage board (Marlin), not the sensor"),
            (["--sensor", str(tmp_path / "ttyACM9")], "does not exist"),
            (["--sensor", emu.sensor, "--ranging", str(bad)], "not a dmdsm ranging"),
            (["--sensor", emu.sensor, "--model", str(bad)], "--model needs --ranging"),
            (["--sensor", emu.sensor, "--serve", "0.0.0.0:8765"], "--allow-remote"),
            (["--sensor", emu.sensor, "--serve", f"127.0.0.1:{busy.port}"], "port is in use")):
        p = dmdsm_live(*args, "--count", "1")
        _, err = p.communicate(timeout=60)
        assert p.returncode == 2 and text in err, err
        assert len(err.strip().splitlines()) == 1, err
    busy.close()


def test_the_material_of_every_record_reaches_a_client_and_the_bag(
        emulator, model, tmp_path):  # noqa: F811 (model: test_classify's fixture)
    """`dmdsm live --model M --serve --bag DIR` in front of the emulator's aluminium block:
    each record's Material (decoded from the advertised schema by rosbags) carries its
    waveform's stamp and shot id, the model's classes, probabilities summing to 1 and the
    block's material as the most probable; the bag folder opens in rosbags' rosbag2 Reader
    (as many Materials as waveforms as records) and holds one Material per waveform at its
    stamp."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    from rosbags.rosbag2 import Reader

    from dmdsm.host.classify.model_file import read_model
    from dmdsm.host.links.stage import StageClient

    classes = [str(c) for c in read_model(model)[0].classes]
    emu = emulator(speed=2.0, seed=4)
    with StageClient(emu.stage) as st:  # 7 mm in front of the block (tests/test_live.py;
        st.move(x=235, y=266, z=20, wait=True)  # unhomed, the emulator's pose is the same)
        st.wait()
    truth = emu.sim.truth()
    assert truth["material"] == "aluminium" and truth["material"] in classes
    true_setup(emu.sim.model).save(tmp_path / "ranging.json")
    bag = tmp_path / "run"
    p = dmdsm_live("--sensor", emu.sensor, "--ranging", str(tmp_path / "ranging.json"),
                   "--model", str(model), "--serve", "127.0.0.1:0", "--samples", "1024",
                   "--average", "16", "--bag", str(bag), "--duration", "120", "--json")
    try:
        line = p.stderr.readline()  # the server is up: its port
        port = int(line.split("ws://127.0.0.1:")[1].split()[0])
        client = WsClient(f"ws://127.0.0.1:{port}")
        assert client.subscribed.wait(20) and client.error is None, client.error
        got = client.wait_for("/dmdsm/material", 8, 45)
        assert len(got) >= 8, (len(got), client.error)
        waves = client.wait_for("/dmdsm/waveform", 1, 0)  # all so far (each before its material)
    finally:
        p.send_signal(signal.SIGINT)  # Ctrl-C: the normal end of a live run
        stdout, stderr = p.communicate(timeout=30)
    client.close()
    assert p.returncode == 0, stderr
    summary = json.loads(stdout)
    assert summary["lost"] == 0 and summary["bag"] == str(bag) and "bag_error" not in summary

    dec = decoders(client)
    mats, wavs = {}, {}
    for topic, into, msgs in (("/dmdsm/material", mats, got), ("/dmdsm/waveform", wavs, waves)):
        for log_ns, payload, _ in msgs:
            m = dec[topic](payload)
            into[m.shot_id] = (m, log_ns)
    # every record the client saw from its first material on has its Material (the client
    # may have joined a record or two in: the window where both topics were subscribed)
    ids = [i for i in sorted(wavs) if min(mats) <= i <= max(mats)]
    assert ids == sorted(mats) == list(range(min(mats), max(mats) + 1))
    for i in ids:
        (m, m_ns), (w, w_ns) = mats[i], wavs[i]
        assert m_ns == w_ns and m.header.stamp == w.header.stamp
        assert m.header.frame_id == "sensor" and m.model == model.name
        assert list(m.classes) == classes
        assert float(np.sum(m.probabilities, dtype=np.float64)) == pytest.approx(1.0, abs=1e-6)
        assert m.best == classes[int(np.argmax(m.probabilities))] == truth["material"]
        assert m.best_probability == max(m.probabilities)
        assert m.distance_m == pytest.approx(truth["distance_mm"] * 1e-3, abs=1e-3)

    # the bag: written at the end, every record's Material at its waveform's stamp
    assert sorted(os.listdir(bag)) == ["metadata.yaml", "run_0.mcap"]
    with Reader(bag) as r:
        counts = {c.topic: c.msgcount for c in r.connections}
        assert counts["/dmdsm/waveform"] == counts["/dmdsm/material"] == summary["records"]
    # read in file order, so that the stamps' order is checked, not imposed
    stamps: dict[str, list[tuple[int, int]]] = {}
    with open(bag / "run_0.mcap", "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, ch, msg, m in reader.iter_decoded_messages(
                topics=["/dmdsm/waveform", "/dmdsm/material"], log_time_order=False):
            # log time = header stamp, to the nanosecond
            assert msg.log_time == m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec
            stamps.setdefault(ch.topic, []).append((m.shot_id, msg.log_time))
    assert stamps["/dmdsm/material"] == stamps["/dmdsm/waveform"]
    assert all(a[1] < b[1] for a, b in itertools.pairwise(stamps["/dmdsm/waveform"]))
    assert [i for i, _ in stamps["/dmdsm/waveform"]] == list(range(summary["records"]))


def test_a_bag_that_cannot_be_one_is_refused_before_the_board_is_opened(tmp_path):
    (tmp_path / "file").write_text("x")
    for args, text in ((["--bag", str(tmp_path / "file")], "is not a folder"),
                       (["--bag", str(tmp_path / "no" / "bag")], "does not exist"),
                       (["--bag", str(tmp_path / "b"), "--mcap", str(tmp_path / "x.mcap")],
                        "give one")):
        p = dmdsm_live("--sensor", str(tmp_path / "ttyACM9"), *args, "--count", "1")
        _, err = p.communicate(timeout=60)
        assert p.returncode == 2 and text in err, err
        assert len(err.strip().splitlines()) == 1, err
    assert sorted(os.listdir(tmp_path)) == ["file"]
