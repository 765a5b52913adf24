"""Stock Marlin's own definitions (code, not settings) that the host and the emulator share."""

from __future__ import annotations

MINIMAL_STEP_RATE = 32.0  # steps/s: Marlin's lowest step rate (stepper.h
# minimal_step_rate = F_CPU / 500000 on the 16 MHz AVR since 2.1's #26881, 2024-07; it was 120)


def checksum(line: str) -> int:
    """Marlin's line checksum (queue.cpp): XOR of every byte before the line's last '*', so
    `line` is the text that goes in front of `*<checksum>`."""
    c = 0
    for b in line.encode():
        c ^= b
    return c
