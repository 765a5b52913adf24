"""Runs the ARM build of the sensor firmware under qemu-system-arm (mps2-an500), UART on TCP."""

from __future__ import annotations

import shutil
import socket
import subprocess
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[3]
ELF = REPO / "firmware/stm32/build/qemu_an500/firmware.elf"


class QemuError(RuntimeError):
    """QEMU or the ARM build is missing, or QEMU did not start."""


def free_port() -> int:
    """An unused TCP port on 127.0.0.1."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class QemuSensor:
    """The sensor firmware in QEMU; `url` is what pySerial opens (socket://127.0.0.1:PORT)."""

    def __init__(self, elf: Path = ELF, port: int | None = None, build: bool = True) -> None:
        if shutil.which("qemu-system-arm") is None:
            raise QemuError("qemu-system-arm not found: apt-get install qemu-system-arm")
        if build:
            r = subprocess.run(["make", "-s", "-C", str(REPO / "firmware/stm32"),
                                "BOARD=qemu_an500"], capture_output=True, text=True)
            if r.returncode:
                raise QemuError(f"ARM build failed: {r.stderr.strip()[-300:]}")
        if not Path(elf).exists():
            raise QemuError(f"{elf} not found: make -C firmware/stm32 BOARD=qemu_an500")
        self.port = port or free_port()
        self.url = f"socket://127.0.0.1:{self.port}"
        # wait=off: the guest runs at once; it sends nothing before the host's first command
        self.proc = subprocess.Popen(
            ["qemu-system-arm", "-M", "mps2-an500", "-nographic", "-monitor", "none",
             "-serial", f"tcp:127.0.0.1:{self.port},server=on,wait=off", "-kernel", str(elf)],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
        for _ in range(200):
            if self.proc.poll() is not None:
                break
            try:
                socket.create_connection(("127.0.0.1", self.port), timeout=0.1).close()
                return
            except OSError:
                time.sleep(0.05)
        out = self.stop()
        raise QemuError(f"QEMU did not listen on port {self.port}: {out[-300:]!r}")

    def stop(self) -> bytes:
        """Stop QEMU; returns what it printed."""
        self.proc.kill()
        out, _ = self.proc.communicate()
        return out or b""

    def __enter__(self) -> QemuSensor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
