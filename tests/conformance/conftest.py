"""The device under test: a real board (DMDSM_SENSOR_PORT=/dev/ttyACM0) or the ARM build in QEMU."""

import os
import socket
import subprocess
import time
from pathlib import Path

import pytest
from link import Link

ROOT = Path(__file__).resolve().parents[2]
ELF = ROOT / "firmware/stm32/build/qemu_an500/firmware.elf"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def sensor_url():
    """Port name or URL of the sensor board; starts QEMU when none is given."""
    url = os.environ.get("DMDSM_SENSOR_PORT")
    if url:
        yield url
        return
    subprocess.run(["make", "-s", "-C", str(ROOT / "firmware/stm32"), "BOARD=qemu_an500"],
                   check=True, capture_output=True)
    port = _free_port()
    # wait=off: the guest runs at once; it sends nothing before the host's first command
    qemu = subprocess.Popen(
        ["qemu-system-arm", "-M", "mps2-an500", "-nographic", "-monitor", "none",
         "-serial", f"tcp:127.0.0.1:{port},server=on,wait=off", "-kernel", str(ELF)],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    for _ in range(200):
        try:
            socket.create_connection(("127.0.0.1", port), timeout=0.1).close()
            break
        except OSError:
            time.sleep(0.05)
    else:
        qemu.kill()
        pytest.fail(f"QEMU did not listen on port {port}: {qemu.communicate()[0]!r}")
    yield f"socket://127.0.0.1:{port}"
    qemu.kill()
    qemu.communicate()


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
