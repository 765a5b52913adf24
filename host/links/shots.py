"""The waveforms of one acquisition as numpy arrays, with what was lost: the sensor client's
result type, apart from the client so the interfaces and the emulator can name it."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

LOSS_COUNTERS = ("adc_overruns", "integrity_faults")  # device counters of real losses


@dataclass
class Shots:
    """Waveforms of one acquisition, indexed by shot id (0 .. n-1 after arm)."""

    samples: np.ndarray         # (n, n_samples) u16 means or u32 sums
    received: np.ndarray        # bool per shot id
    timestamp: np.ndarray       # device ticks of the first averaged edge
    trigger_phase: np.ndarray   # ticks from the edge to the first sample
    n_average: np.ndarray
    config: dict = field(default_factory=dict)
    triggers_skipped: int = 0   # laser shots the board skipped, every waveform slot waiting
    # for the link (its counter, this run): by design at a rate above the link's, not a loss
    adc_overruns: int = 0       # bursts the ADC/DMA overran (device counter, this run)
    integrity_faults: int = 0   # bursts dropped: DMA position disagreed with the timer
    link_rejected: int = 0      # frames the host decoder rejected during this run
    # host monotonic times (s): arm acknowledged, first byte after it, last shot decoded;
    # armed -> first byte is the laser and capture time, first byte -> done the transfer
    armed_s: float | None = None
    first_byte_s: float | None = None
    done_s: float | None = None

    @property
    def lost(self) -> np.ndarray:
        """Shot ids that never arrived."""
        return np.nonzero(~self.received)[0]
