"""What the sensor link carries: the bytes of one waveform on the wire and the waveform rate a
configuration sustains (the laser, the averaging or the 2 Mbaud UART, whichever is slower).

A board armed for N waveforms sends N: while every waveform slot waits for the link it skips
laser shots (status `triggers_skipped`), so settings above the link's rate cost time, not data.
These figures say how much, before an acquisition and in its summary.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from dmdsm.protocol import load_spec
from dmdsm.protocol.spec import CRC_SIZE, HEADER, SAMPLE_DTYPES

LINK_BAUD = 2_000_000  # the NUCLEO's ST-LINK virtual COM port (docs/firmware.md)
BITS_PER_BYTE = 10     # 8N1: start, 8 data, stop
LASER_HZ = 1000.0      # the paper's laser repetition rate (Hz)


def waveform_wire_bytes(n_samples: int, sample_format: int = 0) -> int:
    """Bytes one waveform frame takes on the wire at most: header, fixed fields, samples and
    CRC, COBS-stuffed (one byte per 254 and one more), between two delimiters."""
    fixed = load_spec().by_name["waveform"].fixed.size
    raw = HEADER.size + fixed + n_samples * int(SAMPLE_DTYPES[sample_format][-1]) + CRC_SIZE
    return raw + raw // 254 + 1 + 2


@dataclass(frozen=True)
class LinkRate:
    """Waveforms per second a configuration sustains and what limits it."""

    n_samples: int
    n_average: int
    wire_bytes: int        # one waveform frame on the wire
    shot_hz: float         # the laser's repetition rate
    link_hz: float         # waveforms/s the UART carries
    laser_hz: float        # waveforms/s the laser makes at this averaging
    waveforms_hz: float    # the slower of the two
    limit: str             # "link" or "laser"
    skipped_share: float   # share of laser shots skipped at this rate (0..1)
    free_average: int      # shots per waveform that cost no extra time at this size

    def text(self) -> str:
        """One line for `dmdsm info` and the acquire summary."""
        n_samples, n_average = self.n_samples, self.n_average
        s = (f"a waveform of {n_samples} samples is {self.wire_bytes} B on the wire: the link "
             f"carries {self.link_hz:.0f} waveforms/s, the {self.shot_hz:.0f} Hz laser at "
             f"--average {n_average} makes {self.laser_hz:.0f}/s")
        if self.limit == "link":
            s += f"; {self.skipped_share:.0%} of laser shots are skipped (not a loss)"
            if self.free_average > 1:
                s += f", and --average up to {self.free_average} takes no longer"
        return s


def link_rate(n_samples: int, n_average: int, sample_format: int = 0,
              baud: int = LINK_BAUD, laser_hz: float = LASER_HZ) -> LinkRate:
    """The waveform rate (Hz) of n_samples-sample waveforms averaging n_average shots."""
    wire = waveform_wire_bytes(n_samples, sample_format)
    link_hz = baud / BITS_PER_BYTE / wire
    made_hz = laser_hz / n_average
    rate = min(link_hz, made_hz)
    free = max(1, math.floor(laser_hz / link_hz)) if link_hz < laser_hz else 1
    limit = "link" if link_hz < made_hz else "laser"
    skipped = 1.0 - link_hz * n_average / laser_hz if limit == "link" else 0.0
    return LinkRate(n_samples, n_average, wire, laser_hz, link_hz, made_hz, rate, limit,
                    skipped, free)
