"""The `emulator` fixture: hil_sim on pseudo-terminals in a background thread, one per test."""

import threading

import pytest

from dmdsm.sim.servers.pty_server import PtyServer
from dmdsm.sim.servers.runner import SimConfig, Simulation


class Running:
    """A started emulator: ports by name plus the Simulation for ground truth."""

    def __init__(self, cfg: SimConfig, speed: float) -> None:
        self.sim = Simulation(cfg)
        self.server = PtyServer(self.sim, speed=speed)
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()
        self.stage = self.server.ports["stage"].name_for_host
        self.sensor = self.server.ports["sensor"].name_for_host

    def stop(self) -> None:
        self.server.stop()
        self.thread.join(5)
        self.sim.close()  # a stage firmware's simavr harness, if one runs


@pytest.fixture
def emulator():
    """Factory: emulator(faults=..., speed=...) -> Running; stopped after the test."""
    started = []

    def start(speed: float = 20.0, **kw) -> Running:
        r = Running(SimConfig(**kw), speed)
        started.append(r)
        return r

    yield start
    for r in started:
        r.stop()
