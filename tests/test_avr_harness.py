"""stage_harness, the simavr runner for the stage board's real firmware, tested with a small
AVR program of ours (build/avr/uart_pins_test.elf): UART0 on a pty at 250000 baud, step
pulses counted with their direction, the endstop pin driven from the count, simulated time
paced to the wall clock. Marlin itself runs under it in `make check-marlin`."""

import time

import pytest
import serial

from dmdsm.sim.boards.avr_stage import REPO, AvrStage, AvrStageError, AxisPins

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
