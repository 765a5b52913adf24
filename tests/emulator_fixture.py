"""The `emulator` fixture: hil_sim on pseudo-terminals in a background thread, one per test."""

import pytest

from dmdsm.sim.servers.emulator import Emulator
from dmdsm.sim.servers.runner import SimConfig


@pytest.fixture
def emulator(tmp_path_factory):
    """Factory: emulator(faults=..., speed=...) -> a started Emulator (.stage, .sensor port
    names, .sim for ground truth); stopped after the test. The ports have stable names (as
    `dmdsm sim` gives them): a port the emulator drops and reopens may come back as another
    /dev/pts/N while other processes open terminals, and the client reopens it by name."""
    started = []

    def start(speed: float = 20.0, **kw) -> Emulator:
        links = tmp_path_factory.mktemp("ports")
        emu = Emulator(SimConfig(**kw), speed=speed, link_dir=str(links)).start()
        started.append(emu)
        return emu

    yield start
    for emu in started:
        emu.stop()
