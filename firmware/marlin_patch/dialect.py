"""Facts of Marlin's serial and motion dialect that the host and the emulator both rely on.

Each is written once here: the stage client (`host/links/stage.py`, `host/scan/fly.py`) and the
Marlin emulator (`hil_sim/boards/stage/`) import it, so a change to Marlin is one edit.
"""

from __future__ import annotations

# steps/s: Marlin's lowest step rate (stepper.h minimal_step_rate = F_CPU / 500000 on the
# 16 MHz AVR since 2.1's #26881, 2024-07; it was 120). A move starts and ends at this rate.
MINIMAL_STEP_RATE = 32.0

# s: after M410 (emergency parser) quickstop_stepper() flushes the planner and waits in idle()
# until the clean-up counter runs out (planner.cpp cleaning_buffer_counter: 1000 ms): no
# command runs meanwhile, then the ones queued behind run as usual (issue 29)
QUICK_STOP_CLEAN_S = 1.0

# s: after M112 kill() -> minkill() waits 1000 x 600 us with interrupts on (the steppers keep
# stepping through the planned blocks), then cli(): nothing moves or answers until a reset
MINKILL_S = 0.6


def checksum(line: str) -> int:
    """Marlin's line checksum: XOR of every byte of the line before its '*' (mod 256)."""
    c = 0
    for b in line.encode():
        c ^= b
    return c


def numbered(n: int, command: str) -> str:
    """The line `N<n> <command>*<checksum>` with its newline, as Marlin checks it."""
    body = f"N{n} {command}"
    return f"{body}*{checksum(body)}\n"
