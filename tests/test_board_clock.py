"""The board's own time for link timeouts (host/links/board_clock.py): an emulated board that
runs far slower than the wall is waited for, a real board (nothing published) is not."""

import subprocess
import sys
import time

import pytest

from dmdsm.host.links.board_clock import BoardClock, ClockPublisher, Deadline, clock_path
from dmdsm.host.links.sensor import SensorClient
from dmdsm.sim.servers.emulator import Emulator
from dmdsm.sim.servers.runner import SimConfig


def test_a_deadline_passes_only_once_the_board_had_the_time_too(tmp_path):
    port = str(tmp_path / "port")
    pub = ClockPublisher(port)
    try:
        pub.publish(10.0)
        clock = BoardClock(port)
        assert clock.now() == 10.0
        d = Deadline(0.05, clock)
        time.sleep(0.08)  # the wall's share is over, the board's is not: still waiting
        assert not d.passed() and 0 < d.left() <= 0.05
        pub.publish(10.06)
        assert d.passed()
    finally:
        pub.close()
    assert not clock_path(port).exists()
    assert BoardClock(port).now() is None  # nothing published: wall time only
    d = Deadline(0.01, BoardClock(port))
    time.sleep(0.02)
    assert d.passed()


def test_a_clock_left_by_a_dead_emulator_is_ignored(tmp_path):
    port = str(tmp_path / "port")
    child = subprocess.run([sys.executable, "-c", (
        "import os; from dmdsm.host.links.board_clock import ClockPublisher as P; "
        f"p = P({port!r}); p.publish(1.0); os._exit(0)")], check=True)
    assert child.returncode == 0 and clock_path(port).exists()  # killed: nothing removed
    clock = BoardClock(port)
    assert clock.now() is None
    d = Deadline(0.01, clock)
    time.sleep(0.02)
    assert d.passed()
    clock_path(port).unlink()


@pytest.mark.realtime
def test_a_board_a_hundred_times_slower_than_the_wall_still_answers():
    """On a loaded machine the rehosted NUCLEO ran at 1-7 % of real time and a reply timed out
    while the board was still sending the waveforms before it: an acquisition on a board at
    1 % speed gets every shot and every reply."""
    with Emulator(SimConfig(), speed=0.01) as emu:
        assert BoardClock(emu.sensor).now() is not None  # published per port
        with SensorClient(emu.sensor) as c:
            c.handshake()
            c.configure(n_samples=4096, n_average=1)
            shots = c.acquire(3)
        assert shots.received.all(), shots.received
    assert BoardClock(emu.sensor).now() is None  # removed when the emulator stops
