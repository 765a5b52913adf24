"""The stage client against hil_sim: exactly-once moves under faults, clear errors."""

import time

import pytest

from dmdsm.host.links.stage import StageClient, StageError
from dmdsm.host.links.transport import LinkError
from dmdsm.sim.boards.marlin_gcode import parse_words


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
    expect = {"X": sum(parse_words(c)[1]["X"] for c in sent),
              "A": sum(parse_words(c)[1]["A"] for c in sent)}
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
        for _ in range(200):  # keep moving until the port goes away
            st = StageClient(emu.stage, timeout_s=1.0)
            st.send("G91")
            for _ in range(50):
                st.move(a=5, feed_mm_min=5400, wait=True)
            st.close()
    assert time.monotonic() - t0 < 60
