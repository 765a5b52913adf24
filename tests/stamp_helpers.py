"""The emulator in a child process for the stamp tests (as bench/live.py and `dmdsm sim` run
it: its physics does not share the host's interpreter lock), with its truth times."""

from __future__ import annotations

import multiprocessing as mp
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np


def emulator_child(conn: object, seed: int) -> None:
    """Serve the emulator here; on "times" send back what the truth needs; stop on "stop"."""
    from live_helpers import EmulatorTimes

    from dmdsm.sim.servers.emulator import Emulator
    from dmdsm.sim.servers.runner import SimConfig

    emu = Emulator(SimConfig(seed=seed), speed=1.0)
    times = EmulatorTimes(emu)
    emu.start()
    conn.send(emu.sensor)
    try:
        while conn.recv() == "times":
            conn.send({"wall0": times.wall0, "sim0": times.sim0,
                       "lag": float(np.median(times.lags)), "tick_hz": times.tick_hz})
    finally:
        emu.stop()


class ChildTimes:
    """The truth on the host's clock of a child's emulator (EmulatorTimes.laser_s)."""

    def __init__(self, t: dict) -> None:
        self.t = t

    def laser_s(self, ticks: np.ndarray) -> np.ndarray:
        """Host monotonic (s) of the laser edges at these device ticks."""
        t = self.t
        return t["wall0"] + (np.asarray(ticks, float) / t["tick_hz"] - t["sim0"]) + t["lag"]


@contextmanager
def child_emulator(seed: int = 3) -> Iterator[tuple[str, object]]:
    """(sensor port, truth()) of an emulator in a child process; truth() -> ChildTimes."""
    here, there = mp.get_context("spawn").Pipe()
    child = mp.get_context("spawn").Process(target=emulator_child, args=(there, seed),
                                            daemon=True)
    child.start()
    try:
        if not here.poll(60):
            raise TimeoutError("the emulator's child process did not start")
        sensor = here.recv()

        def truth() -> ChildTimes:
            here.send("times")
            return ChildTimes(here.recv())

        yield sensor, truth
    finally:
        here.send("stop")
        child.join(10)
        if child.is_alive():
            child.kill()
