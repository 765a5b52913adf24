"""The board's own time for link timeouts (host/links/board_clock.py): an emulated board that
runs far slower than the wall is waited for, a real board (nothing published) is not."""

import subprocess
import sys
import threading
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


@pytest.mark.realtime
def test_a_host_starved_for_a_moment_costs_the_board_no_laser_shot(monkeypatch):
    """The emulator's time is its own: a host that stops reading for a while (starved of CPU
    beside it, as on a loaded machine, where the test's host even shares its process) holds
    the simulation instead of filling the pty, the board's link backing up and the board
    skipping laser shots, as for a host too slow for the board (a sweep under load once
    stored 220 of its 366 waveforms a turn, likely so). Each waveform 2 kB every 16 ms of
    the board's time: a 2.5 s stall fills the pty's ~130 kB many times over (14 295 shots
    skipped before the hold)."""
    stall = threading.Event()
    chunk_reader = SensorClient._chunk_reader

    def stalling(self):
        read = chunk_reader(self)

        def r():
            if stall.is_set():
                time.sleep(2.5)  # the reader thread, as the scheduler might hold it
                stall.clear()
            return read()
        return r

    monkeypatch.setattr(SensorClient, "_chunk_reader", stalling)
    with Emulator(SimConfig(seed=4), speed=20.0) as emu:
        with SensorClient(emu.sensor) as sc:
            sc.configure(n_samples=1024, n_average=16)
            sc.stream_start()
            got, end = [], time.monotonic() + 300
            while len(got) < 20 and time.monotonic() < end:
                got += sc.stream_take(0.5)
            t0 = emu.sim.t
            stall.set()
            while (len(got) < 200 or stall.is_set()) and time.monotonic() < end:
                got += sc.stream_take(0.5)
            rest, change = sc.stream_stop()
    ids = [int(w.shot_id) for w in got + rest]
    assert len(ids) >= 200 and emu.sim.t - t0 > 2.0  # the board ran on after the stall
    assert change["triggers_skipped"] == 0 and ids == list(range(len(ids))), change
