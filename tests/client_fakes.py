"""In-process fakes of the board clients for the fly executor's unit tests: a sensor that
streams on a known clock (links.interfaces.StreamSensor) and a stage that only takes time
(links.interfaces.Stage); tests/test_client_interfaces.py keeps them in step with the
Protocols."""

import time
from collections import deque
from types import SimpleNamespace

import numpy as np

from dmdsm.host.links.sensor import ClockSync

NO_CHANGE = {"triggers_skipped": 0, "adc_overruns": 0, "integrity_faults": 0}


class FakeSensor:
    """A sensor board streaming waveforms on a clock of 240 MHz ticks while `motion` runs,
    with one X STEP burst report per stream (`edges_off` steps off the motion's count) and
    the waveform times shifted by `jump_s` (a board whose clock restarted). The motion's
    first step comes FIRST_STEP_S (s) after the arm."""

    FIRST_STEP_S = 0.02

    def __init__(self, motion, jump_s=0.0, edges_off=0):
        self.identity = SimpleNamespace(tick_hz=240_000_000, adc_rate_hz=120_000_000)
        self.clock = ClockSync(offset_ticks=5e9, ticks_per_s=240e6, residual_s=2e-5,
                               rtt_s=1e-3)
        self.motion, self.jump_s, self.edges_off = motion, jump_s, edges_off
        self.motion_syncs = deque()
        self.t0 = None

    def edges_before(self, t):
        """X STEP edges at or before t seconds after the first (the board's count)."""
        if t < 0:
            return 0
        return int(min(self.motion.n, np.floor(self.motion.steps_at(np.array([t]))[0]) + 1))

    def ticks(self, t):
        """Device ticks at host monotonic time t (s)."""
        return int(self.clock.offset_ticks + self.clock.ticks_per_s * t)

    def clock_exchanges(self, n=16, spacing_s=0.0):
        """n exchanges 1 ms apart, answered without delay (RTT 1 ms), the first now."""
        t = time.monotonic()
        return [(t + 1e-3 * i, float(self.ticks(t + 1e-3 * i)), 1e-3) for i in range(n)]

    def stream_start(self):
        self.t0 = time.monotonic()
        self.taken = 0  # waveforms handed out by stream_take

    def _waves(self, t1):
        """Waveforms every 12 ms from stream_start to t1 (host s), their step counts from
        the motion that started FIRST_STEP_S after the arm."""
        start = self.t0 + self.FIRST_STEP_S  # the first step, after the first waveforms
        times = np.arange(self.t0 + 0.001, t1 - 0.001, 0.012)
        return [SimpleNamespace(shot_id=i, timestamp=self.ticks(t + self.jump_s), n_average=12,
                                trigger_phase=7, samples=np.zeros(64, np.uint16),
                                sync_steps=sum(self.edges_before(t + 1e-3 * k - start)
                                               for k in range(12)), sync_steps_a=0)
                for i, t in enumerate(times)]

    def stream_take(self, wait_s=0.0):
        """The waveforms of the stream up to now not taken yet (no waiting: they are due)."""
        waves = self._waves(time.monotonic())[self.taken:]
        self.taken += len(waves)
        return waves

    def stream_stop(self):
        """The waveforms not taken since stream_start, and one X STEP burst report for the
        motion; no device counter changed."""
        waves = self._waves(time.monotonic())[self.taken:]
        start = self.t0 + self.FIRST_STEP_S
        self.motion_syncs.append(SimpleNamespace(
            burst_id=len(self.motion_syncs), first_edge=self.ticks(start),
            last_edge=self.ticks(start + self.motion.last_step_s),
            edges=self.motion.n + self.edges_off, input=0))
        return waves, dict(NO_CHANGE)


class FakeStage:
    """A stage whose every wait lasts the fake sensor's line (plus 30 ms); it stays put."""

    def __init__(self, motion):
        self.motion = motion
        self.moves = []

    def move(self, x=None, y=None, z=None, a=None, feed_mm_min=None, wait=False):
        self.moves.append({"x": x, "y": y, "z": z, "a": a, "feed_mm_min": feed_mm_min})

    def wait(self):
        time.sleep(self.motion.last_step_s + 0.03)

    def where(self):
        return {"X": self.motion.x0, "Y": 0.0, "Z": 0.0, "A": 0.0}

    def send(self, cmd):
        return []

    def stop(self):
        pass

    def home(self):
        return self.where()
