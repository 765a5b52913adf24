"""The host's stage client against the stage under test with faults injected (issue 20): the
Marlin emulator here, the real Marlin under simavr in `make check-marlin`. Every move runs
exactly once and in order, as read from the steps the stage made (the firmware's STEP pins,
the emulator's log), and a lost `ok` costs about one probe timeout."""

import os
import time

import numpy as np
import pytest

from dmdsm.host.links.stage import StageClient, StageError
from dmdsm.marlin_patch import load_machine
from dmdsm.sim.servers.emulator import Emulator
from dmdsm.sim.servers.runner import SimConfig

ELF = os.environ.get("DMDSM_STAGE_FIRMWARE", "")
SPEED = 1.0 if ELF else 5.0  # simavr runs Marlin at about twice real time at most
X_STEPS_PER_MM = load_machine().steps_per_unit[0]


@pytest.fixture
def stage_sim():
    """Factory: a Simulation with these faults on a pty (stage firmware if asked)."""
    running = []

    def start(faults: str = "", seed: int = 3):
        emu = Emulator(SimConfig(seed=seed, faults=faults, stage_firmware=ELF),
                       speed=SPEED).start()
        running.append(emu)
        return emu.sim, emu.server, emu.stage

    yield start
    for emu in running:
        emu.stop()


def x_runs(sim) -> list[int]:
    """The X moves the stage made, in steps, one per change of direction."""
    if ELF:
        return list(sim.stage.traces[0].runs)
    runs = []
    for _, cmd in sim.stage.executed:
        words = dict((w[0], w[1:]) for w in cmd.split()[1:])
        if cmd.startswith("G1 ") and "X" in words:
            runs.append(round(float(words["X"]) * X_STEPS_PER_MM))
    return runs


@pytest.mark.parametrize("faults", [
    "stage.lost_ok=0.03",
    # byte damage both ways at rates where two errors in one line (which Marlin's XOR
    # checksum can miss) stay negligible over this run
    "stage.lost_ok=0.01,stage.flip=5e-5,stage.drop=5e-5",
])
def test_every_move_runs_exactly_once_and_in_order(stage_sim, faults):
    sim, server, port = stage_sim(faults)
    st = StageClient(port, timeout_s=0.5)
    st.send("G91")
    before = len(x_runs(sim))
    # alternating directions and all sizes different: a move run twice, skipped or swapped
    # changes the sequence of runs the X STEP pin makes
    steps = [(40 + i % 37) * (-1) ** i for i in range(300)]
    for k in steps:
        st.send(f"G1 X{k / X_STEPS_PER_MM:.4f} F6000", wait=False)
    st.drain(timeout_s=10)
    st.send("G90")
    st.wait()
    assert x_runs(sim)[before:] == steps
    assert st.stats.probes + st.stats.resent > 0  # the faults did happen
    st.close()


def test_a_lost_ok_is_proven_by_a_numbered_probe_and_keeps_the_reply(stage_sim):
    sim, server, port = stage_sim()
    st = StageClient(port, timeout_s=0.5)
    st.send("G92 X12.5 Y3 Z4 A7")
    with server.lock:
        sim.stage.faults.lose_next_oks = 1
    n = st.next_n
    t0 = time.monotonic()
    st.send("M114", wait=False)
    st.drain(timeout_s=0.5)  # silent: a probe goes out and its `ok N` acknowledges n too
    recovery_s = time.monotonic() - t0
    assert st.stats.probes == 1 and n not in st.unacked
    report = [x for x in st.replies[n] if x.startswith("X:")]
    assert report and report[0].startswith("X:12.50 Y:3.00 Z:4.00 A:7.00")
    assert recovery_s < 2.0, recovery_s
    st.close()


def test_an_over_long_line_is_refused_before_it_is_sent(stage_sim):
    sim, server, port = stage_sim()
    st = StageClient(port)
    st.send("G92 A1")
    t0 = time.monotonic()
    with pytest.raises(StageError, match="too long for Marlin"):
        st.send("M117 " + "x" * 130)  # longer than Marlin's line and its receive ring
    assert time.monotonic() - t0 < 1.0  # refused at once, not after waiting for room
    st.send("G92 A2 ; " + "x" * 100)  # a comment is not sent: Marlin would drop it anyway
    assert st.where()["A"] == 2.0  # run, and the link goes on
    st.send("G92 A1")
    st.close()


def test_an_extra_plain_ok_acknowledges_no_numbered_line(stage_sim):
    sim, server, port = stage_sim()
    st = StageClient(port)
    n = st.next_n
    st.send("G4 P2000", wait=False)  # holds its ok for 2 s
    time.sleep(0.1 / SPEED)
    with server.lock:  # as Marlin adds after an error in a burst
        if ELF:
            sim.stage.out_buffer += b"ok\n"
        else:
            sim.stage.out.append("ok")
    time.sleep(0.1)
    for line in st._read_lines():
        st._handle(line)
    assert n in st.unacked
    st.drain(timeout_s=5)
    assert n not in st.unacked
    st.close()


def test_the_dtr_reset_restarts_the_firmware_once(stage_sim):
    """Held in the bootloader, the firmware does not run; it starts once when the hold ends
    (the lock-step harness used to restart the AVR at every step of the hold)."""
    from stage_link import StageLink
    sim, server, port = stage_sim()
    link = StageLink(port)
    link.lines(0.5)
    with server.lock:
        sim.stage.reset(sim.t, boot_s=1.0)
    t_end = sim.t + 3.0
    seen = []
    while sim.t < t_end:
        seen += link.lines(0.1)
    link.close()
    assert seen.count("start") == 1, seen[:12]
    assert any("Marlin bugfix-2.1.x" in x for x in seen)


def test_connect_survives_the_board_resetting_when_the_port_opens(stage_sim):
    sim, server, port = stage_sim()
    time.sleep(0.5)
    with server.lock:  # as DTR does: the first M110 goes to the bootloader
        sim.stage.reset(sim.t, boot_s=1.5)
    t0 = time.monotonic()
    st = StageClient(port)
    assert time.monotonic() - t0 > 1.0 / SPEED  # it waited for the board, it did not fail
    home = st.home()
    assert home["Z"] == 5.0 and np.isclose(home["X"], load_machine().min_pos[0])
    st.close()
