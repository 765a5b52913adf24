"""The stage under test: a real board (DMDSM_STAGE_PORT=/dev/ttyUSB0), a stage firmware ELF
under simavr (DMDSM_STAGE_FIRMWARE=Marlin.elf, as `make check-marlin` runs it) or the Marlin
emulator, each on a pty."""

import os
import time

import pytest
from stage_link import StageLink

from dmdsm.sim.servers.emulator import Emulator
from dmdsm.sim.servers.runner import SimConfig

SPEED = 20.0  # simulated seconds per wall second for the emulator


@pytest.fixture(scope="module")
def stage_url():
    """Port of the stage board; starts the emulator on a pty when none is given."""
    url = os.environ.get("DMDSM_STAGE_PORT")
    if url:
        yield url, 1.0, time.monotonic
        return
    elf = os.environ.get("DMDSM_STAGE_FIRMWARE", "")
    speed = 1.0 if elf else SPEED  # simavr runs Marlin at about twice real time at most
    with Emulator(SimConfig(seed=1, stage_firmware=elf), speed=speed) as emu:
        yield emu.stage, speed, lambda: emu.sim.t  # simulated seconds


@pytest.fixture
def stage(stage_url):
    """An open link with line numbers reset; link.clock() is the stage's time in seconds
    (simulated time for the emulator, which a loaded machine may run behind the wall clock)."""
    url, speed, clock = stage_url
    link = StageLink(url)
    link.speed = speed
    link.clock = clock
    link.lines(0.2)  # boot banner or leftovers
    link.reset_numbers()
    yield link
    link.close()
