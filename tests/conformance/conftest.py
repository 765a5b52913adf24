"""The device under test: a real board (DMDSM_SENSOR_PORT=/dev/ttyACM0) or the ARM build in QEMU."""

import os

import pytest
from link import Link

from dmdsm.sim.boards.qemu import QemuSensor


@pytest.fixture(scope="module")
def sensor_url():
    """Port name or URL of the sensor board; starts QEMU when none is given."""
    url = os.environ.get("DMDSM_SENSOR_PORT")
    if url:
        yield url
        return
    with QemuSensor() as qemu:
        yield qemu.url


@pytest.fixture
def dut(sensor_url):
    """An open link to the device, disarmed and with the default test configuration."""
    link = Link(sensor_url)
    link.request("disarm")
    link.pump(0.2)
    link.unsolicited.clear()
    yield link
    link.request("disarm")
    link.close()
