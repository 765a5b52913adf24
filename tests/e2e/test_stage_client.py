"""The stage client against hil_sim: exactly-once moves under faults, clear errors."""

import time

import pytest

from dmdsm.host.links.stage import StageClient, StageError
from dmdsm.host.links.transport import LinkError
from dmdsm.sim.boards.stage.marlin_gcode import parse_words


def test_home_move_where(emulator):
    emu = emulator()
    st = StageClient(emu.stage)
    assert st.home()["X"] == -10.0
    st.move(x=20, y=30, z=5, a=90, feed_mm_min=6000)
    st.wait()
    assert st.where() == {"X": 20.0, "Y": 30.0, "Z": 5.0, "A": 90.0}
    st.move(a=-45, relative=True, wait=True)
    assert st.where()["A"] == 45.0
    assert "AXIS_COUNT:4" in st.firmware_info()
    st.close()


def test_a_move_outside_the_envelope_or_to_nan_is_refused_unsent(emulator):
    """The client is the last guard before the wire, whoever asks for the move: a NaN once
    went out as `G1 Xnan` from a calibration step."""
    from dmdsm.host.links.safety import UnsafeMove

    emu = emulator()
    st = StageClient(emu.stage)
    st.move(x=20, y=30, z=5, wait=True)
    before = len(emu.sim.stage.executed)
    for bad, words in (({"x": float("nan")}, "X nan is not a position"),
                       ({"x": 9999.0}, "X9999 is outside the machine envelope (-10..410 mm)"),
                       ({"z": -50.0}, "Z-50 is outside the machine envelope"),
                       ({"a": float("inf")}, "A inf is not a position")):
        with pytest.raises(UnsafeMove, match=words.replace("(", r"\(").replace(")", r"\)")):
            st.move(**bad)
    with pytest.raises(UnsafeMove, match="X nan"):
        st.move(x=float("nan"), relative=True)
    for feed in (-100.0, 0.0, float("nan")):  # Marlin would keep its last feedrate
        with pytest.raises(UnsafeMove, match="feedrate .* give a positive number"):
            st.move(x=30, feed_mm_min=feed)
    time.sleep(0.1)
    assert len(emu.sim.stage.executed) == before  # nothing reached the firmware
    assert st.where() == {"X": 20.0, "Y": 30.0, "Z": 5.0, "A": 0.0}  # and the link is fine
    st.close()


def moves_executed(sim):
    """G1 moves the emulator executed, in order (its ground-truth log)."""
    return [cmd for n, cmd in sim.stage.executed if cmd.startswith("G1 ")]


@pytest.mark.parametrize("faults", [
    "stage.spurious_resend=0.01,stage.lost_ok=0.002",
    # ~1 % of lines rejected as corrupt, plus real byte damage on the wire at rates where two
    # errors in one line are negligible: Marlin's XOR checksum misses two flips of the same
    # bit, or two dropped identical bytes, in one line (both seen at 2e-4..3e-4 per byte).
    "stage.flip=1e-5,stage.drop=1e-5,stage.spurious_resend=0.01,stage.lost_ok=0.002",
])
def test_every_move_runs_exactly_once_and_in_order_under_faults(emulator, faults):
    emu = emulator(speed=100.0, faults=faults, seed=11)
    st = StageClient(emu.stage, timeout_s=0.5)
    start = st.where()  # X -10 at power-up, as on the real Chiron build
    st.send("G91")
    sent = []
    for i in range(10_000):
        dx = 0.01 * ((i % 7) - 3)
        cmd = f"G1 X{dx:.4f} A{0.05 * ((i % 5) - 2):.4f} F6000"
        st.send(cmd, wait=False)
        sent.append(cmd)
    st.drain(timeout_s=5)
    st.send("G90")
    st.wait()
    assert moves_executed(emu.sim) == sent
    assert st.stats.resent > 0
    expect = {"X": start["X"] + sum(parse_words(c)[1]["X"] for c in sent),
              "A": start["A"] + sum(parse_words(c)[1]["A"] for c in sent)}
    pos = st.where()
    assert pos["X"] == pytest.approx(expect["X"], abs=1e-9)
    assert pos["A"] == pytest.approx(expect["A"], abs=1e-9)
    st.close()


def test_stop_interrupts_a_long_move_and_the_port_stays_usable(emulator):
    emu = emulator(speed=5.0)
    st = StageClient(emu.stage)
    st.send("G92 A0")
    st.move(a=3600, feed_mm_min=5400)
    time.sleep(0.3)
    st.stop()
    a = st.where()["A"]
    assert 0 < a < 3600
    assert st.where()["A"] == a  # still answers, nothing queued moves on
    st.close()


def test_emergency_stop_explains_the_reset(emulator):
    emu = emulator()
    st = StageClient(emu.stage)
    assert "press the board's reset button" in st.emergency_stop()
    with pytest.raises(StageError, match="halted.*reset button"):
        st.send("M114")


def test_wrong_device_and_missing_port(emulator, tmp_path):
    emu = emulator()
    with pytest.raises(StageError, match="is the dmdsm sensor board, not the stage"):
        StageClient(emu.sensor, timeout_s=0.5)
    with pytest.raises(LinkError, match="does not exist"):
        StageClient(str(tmp_path / "ttyUSB7"))


def test_port_in_use_is_reported(emulator):
    emu = emulator()
    st = StageClient(emu.stage)
    with pytest.raises(LinkError, match="in use by another program"):
        StageClient(emu.stage)
    st.close()


def test_m154_reports_never_confuse_m114(emulator):
    emu = emulator(speed=10.0)
    st = StageClient(emu.stage)
    st.send("M154 S1")  # unsolicited position lines from now on, without ok
    st.send("G92 A0")
    for k in range(1, 6):
        st.move(a=90 * k, feed_mm_min=5400)
        st.wait()
        assert st.where()["A"] == 90 * k
        time.sleep(0.15)
    assert st.last_position is not None
    st.send("M154 S0")
    st.close()


def test_an_error_during_motion_quick_stops(emulator):
    emu = emulator(speed=5.0)
    with pytest.raises(RuntimeError), StageClient(emu.stage) as st:
        st.send("G92 A0")
        st.move(a=3600, feed_mm_min=5400)
        time.sleep(0.3)
        raise RuntimeError("user code failed mid-move")
    time.sleep(0.3)
    st2 = StageClient(emu.stage)
    a = st2.where()["A"]
    time.sleep(0.3)
    assert st2.where()["A"] == a and 0 < emu.sim.stage.position()[3] < 3600
    st2.close()


def test_disconnect_mid_move_is_a_clear_error_not_a_hang(emulator):
    emu = emulator(speed=2.0, faults="stage.disconnect=0.7,stage.reconnect_s=0.5", seed=4)
    t0 = time.monotonic()
    with pytest.raises(StageError, match="lost the stage|stopped answering"):
        # one connection kept moving until the port goes away under it (reopening between
        # moves could meet the port already gone: a different, open-time error)
        st = StageClient(emu.stage, timeout_s=1.0)
        st.send("G91")
        for _ in range(10000):
            st.move(a=5, feed_mm_min=5400, wait=True)
    assert time.monotonic() - t0 < 60


def _until(cond, timeout_s=10.0):
    end = time.monotonic() + timeout_s
    while not cond() and time.monotonic() < end:
        time.sleep(0.005)
    assert cond()


def test_a_lost_ok_is_proven_by_a_numbered_probe_and_keeps_the_reply(emulator):
    emu = emulator(speed=5.0)
    st = StageClient(emu.stage, timeout_s=0.5)
    st.send("G92 X12.5 Y3 Z4 A7")
    marlin = emu.sim.stage
    marlin.faults.lost_ok = 1.0  # the ok of the next line is lost
    n = st.next_n
    st.send("M114", wait=False)
    _until(lambda: marlin.executed[-1] == (n, "M114"))
    marlin.faults.lost_ok = 0.0
    st.drain(timeout_s=0.5)  # silent: a probe goes out and its `ok N` acknowledges n too
    assert st.stats.probes == 1 and n not in st.unacked
    report = [x for x in st.replies[n] if x.startswith("X:")]
    assert report and report[0].startswith("X:12.50 Y:3.00 Z:4.00 A:7.00")
    assert [c for k, c in marlin.executed if k is not None and k >= n] == ["M114", "M114"]
    st.close()


def test_an_over_long_line_is_refused_before_it_is_sent(emulator):
    emu = emulator()
    st = StageClient(emu.stage)
    before = len(emu.sim.stage.executed)
    with pytest.raises(StageError, match="too long for Marlin"):
        st.send("M117 " + "x" * 100)
    assert len(emu.sim.stage.executed) == before
    assert st.where()  # and the link goes on
    st.close()


def test_connect_survives_the_board_resetting_when_the_port_opens(emulator):
    emu = emulator(speed=1.0)
    marlin = emu.sim.stage
    marlin.reset(marlin.now, boot_s=1.5)  # as DTR does: the first M110 goes to the bootloader
    t0 = time.monotonic()
    st = StageClient(emu.stage)
    assert time.monotonic() - t0 > 1.0  # it waited for the board, it did not fail
    assert st.home()["Z"] == 5.0
    st.close()
