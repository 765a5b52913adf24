"""stage_harness, the simavr runner for the stage board's real firmware, tested with a small
AVR program of ours (build/avr/uart_pins_test.elf): UART0 on a pty at 250000 baud, step
pulses counted with their direction, the endstop pin driven from the count, simulated time
paced to the wall clock. Marlin itself runs under it in `make check-marlin`."""

import time

import numpy as np
import pytest
import serial

from dmdsm.sim.boards.stage.avr_pty import REPO, AvrStage, AvrStageError, AxisPins

ELF = REPO / "build/avr/uart_pins_test.elf"
X = (AxisPins("X", "F0", "F1", "E5", trigger_steps=0),)


def ask(port, data, lines=1, timeout_s=5.0):
    port.write(data)
    out = b""
    end = time.monotonic() + timeout_s
    while out.count(b"\n") < lines and time.monotonic() < end:
        out += port.read(64)
    return out


@pytest.fixture
def board():
    b = AvrStage(ELF, X)
    port = serial.Serial(b.port, 250000, timeout=0.05)
    yield b, port
    port.close()
    b.close()


def test_uart_echo_and_pins_through_the_pty(board):
    b, port = board
    assert ask(port, b"ok N1\n") == b"ok N1\n"  # UART0 both ways at 250000 baud
    assert ask(port, b"e") == b"E1\n"  # count 0 <= trigger: the min endstop reads triggered
    assert ask(port, b"+") == b"S\n"
    assert ask(port, b"e") == b"E0\n"  # 100 steps away from it
    time.sleep(0.2)
    assert b.counts.tolist() == [100]
    assert ask(port, b"--", lines=2) == b"S\nS\n"
    time.sleep(0.2)
    assert b.counts.tolist() == [-100] and ask(port, b"e") == b"E1\n"
    assert b.positions([80.0])[0] == -100 / 80.0


def test_inverted_direction_counts_the_other_way():
    b = AvrStage(ELF, (AxisPins("X", "F0", "F1", "E5", dir_inverted=True),))
    port = serial.Serial(b.port, 250000, timeout=0.05)
    try:
        assert ask(port, b"+") == b"S\n"
        time.sleep(0.2)
        assert b.counts.tolist() == [-100]
    finally:
        port.close()
        b.close()


def test_simulated_time_is_paced_to_the_wall_clock(board):
    b, port = board
    time.sleep(0.2)
    t0, w0 = b.time_s, time.monotonic()
    time.sleep(1.0)
    rate = (b.time_s - t0) / (time.monotonic() - w0)
    # never ahead of real time (speed 1); behind it only as far as this machine's load makes
    # simavr slower than a 16 MHz ATmega2560
    assert 0.05 < rate < 1.1, rate


def test_a_bad_firmware_file_is_one_clear_error(tmp_path):
    junk = tmp_path / "junk.elf"
    junk.write_bytes(b"not an elf")
    with pytest.raises(AvrStageError, match="cannot read .* as an AVR ELF"):
        AvrStage(junk, X)
    with pytest.raises(AvrStageError, match="no such firmware file"):
        AvrStage(tmp_path / "none.elf", X)


# ---------------------------------------------------------------- lock-step (dmdsm sim)
# the same program as the stage board of a Simulation: `dmdsm sim --stage-firmware ELF`

def lockstep_board(**kw):
    from dmdsm.sim.boards.stage.avr_lockstep import AvrStageBoard
    return AvrStageBoard(ELF, axes=(AxisPins("X", "F0", "F1", "E5", trigger_steps=-80),
                                    AxisPins("Y", "F6", "F7", "-"), AxisPins("Z", "C1", "C3", "-"),
                                    AxisPins("A", "A4", "A6", "-")), **kw)


def run(board, t0, seconds, data=b""):
    board.receive(data, t0)
    out, t = b"", t0
    while t < t0 + seconds:
        t += 0.001
        out += board.step(t)
    return out, t


def test_lockstep_echo_steps_and_their_cycle_exact_times():
    b = lockstep_board()
    try:
        out, t = run(b, 0.0, 0.002)  # the program enables its UART first
        out, t = run(b, t, 0.01, b"ok N1\n")
        assert out == b"ok N1\n"
        t_plus = t
        out, t = run(b, t, 0.01, b"+")
        assert out == b"S\n"
        edges = b.step_edges(0, 0.0, t)
        assert len(edges) == 100 and np.all(np.diff(edges) > 0) and edges[0] > t_plus
        # 2 us high + 2 us low + the loop: 4.5-6 us apart, exact to the CPU cycle
        assert 4e-6 < np.median(np.diff(edges)) < 6e-6
        assert b.position_at(edges[49])[0] == pytest.approx((80 + 50) / 80.0)
        assert b.position_at(t_plus)[0] == pytest.approx(1.0)  # 80 steps above the stop
        out, t = run(b, t, 0.01, b"-e")
        assert out == b"S\nE0\n"  # back where it started, 80 steps above the endstop
        out, t = run(b, t, 0.01, b"-e")
        assert out == b"S\nE1\n"  # past it: triggered
        out, t = run(b, t, 0.01, b"+")
        assert b.traces[0].runs == [100, -200, 100]
    finally:
        b.close()


def test_lockstep_reset_drops_bytes_meanwhile_and_lost_oks_are_whole_lines():
    from dmdsm.sim.boards.stage.marlin import StageFaults
    b = lockstep_board(faults=StageFaults(lose_next_oks=1))
    try:
        out, t = run(b, 0.0, 0.002)
        out, t = run(b, t, 0.01, b"ok N1\nok N2\n")
        assert out == b"ok N2\n"  # the first ok never reached the host
        b.reset(t, boot_s=0.05)
        out, t = run(b, t, 0.02, b"lost")  # the bootloader has it
        out2, t = run(b, t + 0.05, 0.01, b"ok N3\n")
        assert out == b"" and out2 == b"ok N3\n"
    finally:
        b.close()


def test_a_stage_firmware_that_halts_is_one_clear_error():
    b = lockstep_board()
    try:
        out, t = run(b, 0.0, 0.002)
        with pytest.raises(AvrStageError, match="stage firmware stopped"):
            run(b, t, 0.01, b"h")
    finally:
        b.close()


@pytest.mark.realtime
def test_sim_cli_runs_a_stage_firmware_and_refuses_a_bad_one(tmp_path):
    import json
    import subprocess
    import sys
    with subprocess.Popen([sys.executable, "-m", "dmdsm.host", "sim", "--json",
                           "--stage-firmware", str(ELF)], stdout=subprocess.PIPE,
                          stderr=subprocess.PIPE, text=True) as p:
        try:
            ports = json.loads(p.stdout.readline())
            port = serial.Serial(ports["stage"], 250000, timeout=0.05)
            time.sleep(0.3)  # bytes sent before the program enables its UART are lost
            assert ask(port, b"ok N7\n") == b"ok N7\n" and ask(port, b"+") == b"S\n"
            port.close()
        finally:
            p.terminate()
            assert p.wait(10) == 0
    junk = tmp_path / "junk.elf"
    junk.write_bytes(b"\x7fELF junk")
    r = subprocess.run([sys.executable, "-m", "dmdsm.host", "sim", "--stage-firmware",
                        str(junk)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "cannot read" in r.stderr and "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1, r.stderr
    r = subprocess.run([sys.executable, "-m", "dmdsm.host", "demo", "--out", str(tmp_path / "o"),
                        "--stage-firmware", str(junk)], capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 2 and "cannot read" in r.stderr and "Traceback" not in r.stderr
