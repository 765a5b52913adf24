"""Builds the rehost's ARM test programs (Debian's gcc-arm-none-eabi) once per session."""

import shutil
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
LD = REPO / "firmware/stm32/board/nucleo_h743zi/h743zi.ld"
CFLAGS = ["-mcpu=cortex-m7", "-mthumb", "-mfpu=fpv5-d16", "-mfloat-abi=hard", "-O1", "-Wall",
          "-Wextra", "-Werror", "-std=c11", "-nostartfiles", "--specs=nosys.specs"]


@pytest.fixture(scope="session")
def sequence_elf(tmp_path_factory):
    """sequence_elf(case) -> ELF of tests/rehost/wrong_sequences.c built with -DCASE=case."""
    if shutil.which("arm-none-eabi-gcc") is None:
        pytest.fail("arm-none-eabi-gcc missing: make deps installs gcc-arm-none-eabi")
    out = tmp_path_factory.mktemp("sequences")

    def build(case: int) -> Path:
        elf = out / f"case{case}.elf"
        if not elf.exists():
            subprocess.run(["arm-none-eabi-gcc", *CFLAGS, f"-DCASE={case}", "-T", str(LD),
                            str(Path(__file__).with_name("wrong_sequences.c")), "-o", str(elf)],
                           check=True)
        return elf

    return build
