"""The device under test: a real board (DMDSM_SENSOR_PORT=/dev/ttyACM0), else two rehosts of ours.

Without a board the suite runs twice: against the ARM build in QEMU (mps2-an500, the core with
a test-pattern ADC) and against the exact NUCLEO ELF on the rehosted H743 (unicorn with
peripheral models, hil_sim/boards/sensor/rehost), served on a pseudo-terminal as `dmdsm sim
--sensor-firmware nucleo` serves it. A hardware rule the NUCLEO build breaks fails the run.
"""

import os

import pytest
from link import Link

from dmdsm.sim.boards.sensor.qemu import QemuSensor
from dmdsm.sim.servers.emulator import Emulator
from dmdsm.sim.servers.runner import SimConfig

TARGETS = ["board"] if os.environ.get("DMDSM_SENSOR_PORT") else ["qemu", "nucleo-rehost"]


@pytest.fixture(scope="module", params=TARGETS)
def sensor_url(request):
    """Port name or URL of the sensor board under test."""
    if request.param == "board":
        yield os.environ["DMDSM_SENSOR_PORT"]
    elif request.param == "qemu":
        with QemuSensor() as qemu:
            yield qemu.url
    else:
        # boot first: bytes reaching USART3 before it is enabled are lost
        with Emulator(SimConfig(sensor_firmware="nucleo"), boot_s=0.02) as emu:
            yield emu.sensor
        assert emu.sim.sensor.violation is None, f"NUCLEO firmware: {emu.sim.sensor.violation}"


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
