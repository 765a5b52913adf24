"""The emulator in a child process for the stamp tests (as bench/live.py and `dmdsm sim` run
it: its physics does not share the host's interpreter lock), with its truth times."""

from __future__ import annotations

import multiprocessing as mp
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np


def emulator_child(conn: object, seed: int) -> None:
    """Serve the emulator here; on ("times", k) send back what the truth needs (the median
    receive lag from the k-th receive on), on "distance" the sensor's true distance (mm);
    stop on "stop"."""
    from live_helpers import EmulatorTimes

    from dmdsm.sim.servers.emulator import Emulator
    from dmdsm.sim.servers.runner import SimConfig

    emu = Emulator(SimConfig(seed=seed), speed=1.0)
    times = EmulatorTimes(emu)
    emu.start()
    conn.send((emu.sensor, emu.stage))
    try:
        while (ask := conn.recv()) != "stop":
            if ask == "distance":
                conn.send(float(emu.sim.truth()["distance_mm"]))
                continue
            lags = times.lags[ask[1]:] or times.lags
            conn.send({"wall0": times.wall0, "sim0": times.sim0, "receives": len(times.lags),
                       "lag": float(np.median(lags)), "tick_hz": times.tick_hz,
                       "lag_iqr_s": float(np.subtract(*np.percentile(lags, [75, 25]))),
                       "sent": dict(times.sent)})
    finally:
        emu.stop()


class ChildTimes:
    """The truth on the host's clock of a child's emulator (EmulatorTimes.laser_s); `sent`:
    host monotonic (s) at which each waveform's last byte left the board, by its ticks;
    `receives`: how many receives the board had made; `lag_sigma_s`: the receive lag's
    scatter (IQR / 1.349), how well laser_s knows the board's clock: on a loaded machine the
    emulator's loop falls behind its pacing by a varying lag (median 10 ms, 5-95 %
    0.5-35 ms with two busy loops beside it), so its clock is read that late and laser_s
    is that uncertain."""

    def __init__(self, t: dict) -> None:
        self.t, self.sent, self.receives = t, t["sent"], t["receives"]
        self.lag_sigma_s = t["lag_iqr_s"] / 1.349

    def laser_s(self, ticks: np.ndarray) -> np.ndarray:
        """Host monotonic (s) of the laser edges at these device ticks."""
        t = self.t
        return t["wall0"] + (np.asarray(ticks, float) / t["tick_hz"] - t["sim0"]) + t["lag"]


class ChildEmulator:
    """An emulator served by a child process: its ports, its truth on request."""

    def __init__(self, conn: object, sensor: str, stage: str) -> None:
        self.conn, self.sensor, self.stage = conn, sensor, stage

    def truth(self, from_receive: int = 0) -> ChildTimes:
        """The truth times, the receive lag's median taken from receive `from_receive` on."""
        self.conn.send(("times", from_receive))
        return ChildTimes(self.conn.recv())

    def distance_mm(self) -> float:
        """The sensor's true distance (mm) to the surface in front of it."""
        self.conn.send("distance")
        return self.conn.recv()


@contextmanager
def child_emulator(seed: int = 3) -> Iterator[tuple[str, ChildEmulator]]:
    """(sensor port, child) of an emulator in a child process: child.truth() -> ChildTimes,
    child.stage, child.distance_mm() for what stands in front of the sensor."""
    here, there = mp.get_context("spawn").Pipe()
    child = mp.get_context("spawn").Process(target=emulator_child, args=(there, seed),
                                            daemon=True)
    child.start()
    try:
        if not here.poll(60):
            raise TimeoutError("the emulator's child process did not start")
        sensor, stage = here.recv()
        yield sensor, ChildEmulator(here, sensor, stage)
    finally:
        here.send("stop")
        child.join(10)
        if child.is_alive():
            child.kill()
