"""The `emulator` fixture: hil_sim on pseudo-terminals in a background thread, one per test."""

import pytest

from dmdsm.sim.servers.emulator import Emulator
from dmdsm.sim.servers.runner import SimConfig


@pytest.fixture
def emulator():
    """Factory: emulator(faults=..., speed=...) -> a started Emulator (.stage, .sensor port
    names, .sim for ground truth); stopped after the test."""
    started = []

    def start(speed: float = 20.0, **kw) -> Emulator:
        emu = Emulator(SimConfig(**kw), speed=speed).start()
        started.append(emu)
        return emu

    yield start
    for emu in started:
        emu.stop()
