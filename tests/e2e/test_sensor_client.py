"""The sensor client against hil_sim: no corrupted shot accepted, every loss counted."""

import numpy as np
import pytest

from dmdsm.host.links.sensor import SensorClient, SensorError
from dmdsm.host.links.transport import LinkError
from dmdsm.protocol import FrameDecoder, load_spec

SPEC = load_spec()


def test_10000_shots_through_a_noisy_link_every_shot_accounted(emulator):
    emu = emulator(speed=4.0, faults="sensor.flip=1e-5,sensor.drop=1e-5", seed=21)
    tap = emu.sim.channels[("sensor", "up")].tap = bytearray()
    sc = SensorClient(emu.sensor)
    sc.configure(n_samples=128, n_average=2, trigger_timeout_ms=2000)
    shots = sc.acquire(10_000, timeout_s=120)
    sent = {m.shot_id: m for m in FrameDecoder().feed(bytes(tap)) if m.name == "waveform"}
    got = np.nonzero(shots.received)[0]
    assert len(got) + len(shots.lost) == 10_000
    assert 0 < len(shots.lost) < 500 and shots.link_rejected > 0
    for i in got:  # zero corrupted shots accepted: every delivered one is what the board sent
        np.testing.assert_array_equal(shots.samples[i], sent[i].samples)
        assert shots.timestamp[i] == sent[i].timestamp
    # every lost shot has a cause: its frame rejected on the wire (a board never drops one:
    # it skips the triggers it has no slot for, which take no shot id)
    assert len(shots.lost) <= shots.link_rejected
    sc.close()


def test_configure_naks_name_the_field(emulator):
    sc = SensorClient(emulator().sensor)
    with pytest.raises(SensorError, match="refused set_config .*pretrigger is outside 0..8191"):
        sc.configure(n_samples=256, pretrigger=300)
    with pytest.raises(SensorError, match="unknown setting n_smples"):
        sc.configure(n_smples=256)
    # a value the wire cannot carry is refused with the spec's range, before it is sent
    with pytest.raises(SensorError, match=r"^n_samples 999999 is outside 16\.\.8192$"):
        sc.configure(n_samples=999_999)
    with pytest.raises(SensorError, match=r"^n_average 0 is outside 1\.\.4096$"):
        sc.configure(n_average=0)
    assert sc.configure(n_samples=256)["n_samples"] == 256  # the board still answers
    # shots are kept in memory until written: an acquisition that cannot fit is refused
    # before the board is armed, and says how many would
    with pytest.raises(SensorError, match=r"GiB of memory .* record at most \d+ shots"):
        sc.acquire(10**9)
    with pytest.raises(SensorError, match=r"give 1\.\.4294967295"):
        sc.acquire(2**32)
    assert sc.status()["state"] == SPEC.enums["state"]["idle"]
    assert sc.acquire(2).received.all()
    sc.close()


def test_wrong_device_missing_port_and_incompatible_firmware(emulator, tmp_path):
    emu = emulator()
    with pytest.raises(SensorError, match="is the stage board \\(Marlin\\), not the sensor"):
        SensorClient(emu.stage, timeout_s=0.2, retries=1)
    with pytest.raises(LinkError, match="does not exist"):
        SensorClient(str(tmp_path / "ttyACM9"))
    with pytest.raises(SensorError, match="incompatible sensor firmware.*dmdsm flash stm32"):
        SensorClient(emu.sensor, expected_hash=0x1234)


def test_disconnect_mid_stream_is_reported_and_recovered(emulator):
    emu = emulator(speed=1.0, faults="sensor.disconnect=0.5,sensor.reconnect_s=0.3", seed=2)
    sc = SensorClient(emu.sensor)
    sc.configure(n_samples=256, n_average=1)
    with pytest.raises(SensorError, match="lost the sensor board"):
        for _ in range(20):  # a disconnect comes within a few seconds
            sc.acquire(500, timeout_s=5)
    sc.reconnect()
    assert sc.identity.name == "identify_reply"
    sc.close()


def test_a_pulled_port_keeps_its_name_and_never_names_another_programs_port(emulator):
    """A board that drops comes back as another /dev/pts/N (the kernel gives the freed number
    to the next pty opened anywhere): the emulator names it by a stable link, as udev's
    by-id link names a real board, and the link is gone while the board is. A host that
    reopened the bare old path once took another test's Marlin port and its bytes."""
    import os
    import time

    emu = emulator(speed=1.0, faults="sensor.disconnect=2,sensor.reconnect_s=3", seed=4)
    name = emu.sensor
    assert not name.startswith("/dev/pts/") and os.path.realpath(name).startswith("/dev/pts/")
    end = time.monotonic() + 60
    while os.path.lexists(name):  # the first pull comes within about 0.5 s of the board's time
        assert time.monotonic() < end, "the port was never pulled"
        time.sleep(0.01)
    master, slave = os.openpty()  # another program's pty: it may get the freed number
    try:
        with pytest.raises(LinkError, match="does not exist"):
            SensorClient(name)
        while not os.path.lexists(name):
            assert time.monotonic() < end, "the port never came back"
            time.sleep(0.01)
        assert os.path.realpath(name) != os.ttyname(slave)
    finally:
        os.close(master)
        os.close(slave)
    own = os.path.dirname(name)
    emu.stop()
    assert not os.path.exists(own)  # the emulator's own link folder goes with it


def test_clock_sync_recovers_the_tick_rate(emulator):
    sc = SensorClient(emulator(speed=1.0).sensor)
    cs = sc.sync_clock(16)
    assert cs.ticks_per_s == pytest.approx(240e6, rel=0.02)
    assert cs.residual_s < 0.01 and cs.rtt_s < 0.1
    # a reply is taken as it arrives: the reader once waited its 20 ms port timeout for
    # more bytes on every reply, so every request took 21 ms even on a pty
    rtts = [r for _, _, r in sc.clock_exchanges(16)]
    assert np.median(rtts) < 0.015, rtts
    sc.close()


def test_a_clock_exchanges_round_trip_ends_when_the_reply_is_read(emulator):
    """The reply's leg ends when the reader takes in its bytes, not when the asking thread
    gets to it (held off the interpreter for ms under a live stream's load): that delay is
    the host's alone and only on the way back, so it widened the round trip and moved the
    mid-time off the board's reading. Here the asking thread takes every reply 30 ms late."""
    import time

    class LateTake(dict):
        def pop(self, *args):
            time.sleep(0.03)
            return super().pop(*args)

    sc = SensorClient(emulator(speed=1.0).sensor)
    sc.responses = LateTake(sc.responses)
    t0 = time.monotonic()
    ex = sc.clock_exchanges(5)
    took = time.monotonic() - t0
    sc.responses = dict(sc.responses)
    assert took > 5 * 0.03 and len(ex) == 5
    # every one was >= 30 ms before; a loaded machine may hold one reply's read itself
    assert np.median([rtt for _, _, rtt in ex]) < 0.02, ex
    sc.close()


def test_a_clock_exchange_whose_write_was_held_is_made_again(emulator, monkeypatch):
    """Under a live stream's load the thread that stamps a clock_sync's send can be held off
    the interpreter for ms before the bytes go out; the board then reads its clock that
    much later than the stamp says. Such an exchange is made again, not fitted."""
    import time

    from dmdsm.host.links import sensor as sensor_module

    sc = SensorClient(emulator(speed=1.0).sensor)
    write, request, calls = sc._write, sc.request, []  # calls: held by the test or not
    attempts: list[tuple[float, float, bool, bool]] = []  # send s, write's lag s, held, resent

    def held_every_other(data: bytes) -> None:
        calls.append(len(calls) % 2 == 0)
        if calls[-1]:  # this thread held off 5 ms between its send stamp and the write
            time.sleep(0.005)
        write(data)

    def stamped(name, sent_ns=None, written_ns=None, **fields):
        r = request(name, sent_ns=sent_ns, written_ns=written_ns, **fields)
        attempts.append((sent_ns[0] / 1e9, (written_ns[-1] - sent_ns[-1]) / 1e9,
                         calls[-1], len(sent_ns) > 1))
        return r

    monkeypatch.setattr(sc, "_write", held_every_other)
    monkeypatch.setattr(sc, "request", stamped)
    ex = sc.clock_exchanges(6)
    # A loaded machine can hold a write the test did not (the bound is 0.5 ms), so which
    # exchanges are kept follows from the lags measured, not from the test's pattern alone:
    # those written within the bound, sent once, and the last of the 2n attempts as it is.
    assert all(lag > 0.005 for _, lag, by_test, _ in attempts if by_test)
    kept = [sent for i, (sent, lag, _, resent) in enumerate(attempts)
            if not resent and (lag <= sensor_module.HELD_WRITE_S or i == 11)]
    assert len(ex) == 6 or len(attempts) == 12
    assert np.allclose([mid - rtt / 2 for mid, _, rtt in ex], kept[:6], rtol=0, atol=1e-6)
    calls.clear()
    monkeypatch.setattr(sc, "_write", lambda data: (time.sleep(0.005),
                                                    calls.append(True), write(data)))
    ex = sc.clock_exchanges(2)  # every write held: as many again, then the last one kept
    assert len(calls) == 4 and len(ex) == 1
    assert sensor_module.HELD_WRITE_S < 0.005
    sc.close()


def test_leaving_the_client_by_an_error_disarms_the_board(emulator):
    """Issue 30: SensorClient is a context manager, as StageClient is; an error inside it
    leaves the board idle, not streaming."""
    emu = emulator(speed=4.0)
    spec = load_spec()
    with pytest.raises(RuntimeError, match="mid-stream"):
        with SensorClient(emu.sensor) as sc:
            sc.stream_start()
            raise RuntimeError("mid-stream")
    with SensorClient(emu.sensor) as sc:
        assert not sc.took_over  # idle already: the next client had nothing to disarm
        assert sc.status()["state"] == spec.enums["state"]["idle"]
