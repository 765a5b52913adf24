"""What the step and the fly executors do alike: a run's statistics, each stored batch's
bookkeeping (store time, phase times, progress) and the approach to the first point."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from .scanfile import PHASES

if TYPE_CHECKING:
    from ..links.interfaces import Stage
    from .scanfile import ScanWriter

Progress = Callable[[int, int, dict], None]  # (points in the file, planned, phase times s)


@dataclass
class ScanStats:
    """What a run did: points stored, waveforms lost, wall time per phase (s)."""

    stored: int = 0
    lost: int = 0
    # laser shots the board skipped while streaming: every waveform slot waited for the
    # link (the host did not read in time, or the link is slower than the waveforms); a
    # streamed plan counts on every shot
    skipped: int = 0
    phase_s: dict[str, float] = field(default_factory=lambda: dict.fromkeys(PHASES, 0.0))
    store_s: float = 0.0
    wall_s: float = 0.0
    clock: dict = field(default_factory=dict)  # fly: the clock sync (drift, residual, RTT)

    def per_point_ms(self) -> dict[str, float]:
        """Mean wall time per stored point and phase (ms)."""
        n = max(self.stored, 1)
        out = {k: 1e3 * v / n for k, v in self.phase_s.items()}
        out["store"] = 1e3 * self.store_s / n
        return out

    def store(self, write: Callable[[], None], n: int, timing: dict[str, float],
              writer: ScanWriter, planned: int, progress: Progress | None = None) -> None:
        """Store one batch: write() appends its n points to writer's file, timed as the
        store phase; the batch's phase times (s, PHASES) are added, then progress(points
        in the file, planned, timing) is called."""
        t = time.monotonic()
        write()
        self.store_s += time.monotonic() - t
        self.stored += n
        for k in PHASES:
            self.phase_s[k] += timing[k]
        if progress is not None:
            progress(writer.n_done, planned, timing)


def approach(stage: Stage, y_mm: float, feed_mm_min: float) -> None:
    """Queue the move into the front plane (Y = y_mm) along Y alone, X and Z staying where
    they are, at feed_mm_min (mm/min): the path the plan check assumed to the first point."""
    here = stage.where()
    stage.move(x=here["X"], y=y_mm, z=here["Z"], feed_mm_min=feed_mm_min)
