"""The stage under test driven in-process for tests that read its STEP pins: the Marlin
emulator, or a stage firmware ELF under simavr (DMDSM_STAGE_FIRMWARE, as `make check-marlin`
runs it). A real board on DMDSM_STAGE_PORT is not used here: its pins cannot be recorded, so
these tests check the emulator or the ELF whatever port is set."""

import os

import pytest
from differential import Stage, send_both


class PinBench:
    """The stage under test in-process, homed, driven line by line in simulated time."""

    def __init__(self) -> None:
        self.stage = Stage(os.environ.get("DMDSM_STAGE_FIRMWARE", ""))
        self.n = 0
        for cmd in ("G28", "G90", "M400"):
            self.send(cmd)

    def send(self, cmd: str) -> list[str]:
        """One numbered line, answered (busy lines left out)."""
        self.n += 1
        (replies,) = send_both([self.stage], cmd, self.n)
        assert replies and replies[-1].startswith(f"ok N{self.n} "), (cmd, replies)
        return replies


def bench_fixture(cls: type) -> object:
    """A module-scoped fixture giving one homed `cls` (a PinBench) for the module."""

    @pytest.fixture(scope="module")
    def bench():
        b = cls()
        yield b
        b.stage.close()

    return bench
