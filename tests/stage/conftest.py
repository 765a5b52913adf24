"""The stage under test: a real Marlin (DMDSM_STAGE_PORT=/dev/ttyUSB0) or hil_sim on a pty."""

import os
import threading

import pytest
from stage_link import StageLink

from dmdsm.sim.servers.pty_server import PtyServer
from dmdsm.sim.servers.runner import SimConfig, Simulation

SPEED = 20.0  # simulated seconds per wall second for the emulator


@pytest.fixture(scope="module")
def stage_url():
    """Port of the stage board; starts the emulator on a pty when none is given."""
    url = os.environ.get("DMDSM_STAGE_PORT")
    if url:
        yield url, 1.0
        return
    server = PtyServer(Simulation(SimConfig(seed=1)), speed=SPEED)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield server.ports["stage"].name_for_host, SPEED
    server.stop()
    thread.join(5)


@pytest.fixture
def stage(stage_url):
    """An open link with line numbers reset."""
    url, speed = stage_url
    link = StageLink(url)
    link.speed = speed
    link.lines(0.2)  # boot banner or leftovers
    link.reset_numbers()
    yield link
    link.close()
