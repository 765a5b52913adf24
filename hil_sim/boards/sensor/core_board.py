"""Sensor-board emulator: the real firmware core (PC build) fed by a simulated laser and ADC.

The laser fires at `rep_rate_hz`; for every shot the armed core will average, the physics
computes the waveform for the stage pose at that instant, sampled with a random start phase
(which the core reports as the trigger phase), and the core averages, frames and queues it;
a shot it skips (no free slot) is counted without samples. The link to
the host carries `link_bytes_per_s` (2 Mbaud 8N1 by default), so a slow link drops shots on
the device exactly as on hardware.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Callable, Sequence

import numpy as np

from ...physics.scene import Hit, Scene
from ...physics.signals import SensorModel, synthesize, to_adc
from .firmware_core import FirmwareCore

TICK_HZ = 240_000_000
ADC_RATE_HZ = TICK_HZ / 72  # the NUCLEO's paced rate, 3.333 MS/s (docs/firmware.md)
BATCH = 16  # laser shots whose ray casts are computed together

Pose = Callable[[float], tuple[np.ndarray, float]]  # time (s) -> (S in mm, theta in deg)
Edges = Callable[[float, float], np.ndarray]  # (t_from, t_to] (s) -> times of sync edges (s)


SYNC_LOOKBACK_S = 1e-3  # s: how far back each delivery of sync edges looks again


class SyncWire:
    """A STEP wire (X or A) as this board takes its edges: each delivery looks SYNC_LOOKBACK_S
    back and passes every edge once. A block the stage starts on the very instant of the
    previous delivery (its third queued block arrived then, ending Marlin's lone-block
    hold) steps first at that instant, which a plain (t_from, t_to] window misses."""

    def __init__(self, source: Callable[[float, float], np.ndarray]) -> None:
        self.source = source
        self.last = -math.inf  # s: the last edge delivered

    def take(self, t_from: float, t_to: float) -> np.ndarray:
        """The edges (s) up to t_to not delivered yet."""
        e = self.source(t_from - SYNC_LOOKBACK_S, t_to)
        e = e[e > self.last]
        if e.size:
            self.last = float(e[-1])
        return e


def averaged_shots(hit: Hit | list[Hit], model: SensorModel, n_samples: int, n_average: int,
                   rng: np.random.Generator, seed: int = 0,
                   fs_hz: float = ADC_RATE_HZ) -> tuple[np.ndarray, int]:
    """One waveform as the core averages it (acquire.c): n_average shots of one hit (or of
    n_average hits, one per shot: a sensor moving while it averages), each sampled from its
    own random start phase (the ADC runs free of the laser), summed and rounded, with the
    phases' rounded mean as the trigger phase. The phases' spread (one sample, 0.3 us at
    3.333 MS/s) low-passes the average; a generator that gave every shot one phase would
    make waveforms sharper than the board's. Returns (uint16 samples, trigger phase in
    ticks)."""
    period = int(round(TICK_HZ / fs_hz))
    total = np.zeros(n_samples, np.int64)
    phases = rng.integers(1, period + 1, size=n_average)
    hits = hit if isinstance(hit, list) else [hit] * n_average
    for phase, one in zip(phases, hits, strict=True):
        t_us = (np.arange(n_samples) / fs_hz + int(phase) / TICK_HZ) * 1e6
        total += to_adc(synthesize(one, model, t_us, rng, seed), model).astype(np.int64)
    wave = ((total + n_average // 2) // n_average).astype(np.uint16)
    return wave, int((int(phases.sum()) + n_average // 2) // n_average)


class SensorBoard:
    """One emulated NUCLEO: firmware core + laser + physics + link pacing."""

    def __init__(self, scene: Scene, pose: Pose, model: SensorModel | None = None,
                 seed: int = 0, rep_rate_hz: float = 1000.0,
                 link_bytes_per_s: float = 200_000.0, max_samples: int = 8192,
                 frozen_noise: bool = False,
                 sync_edges: Sequence[Edges | None] | None = None) -> None:
        self.scene = scene
        # the stage's X and A STEP lines, wired to sync inputs 0 and 1 (None: not wired)
        self.sync_sources = [SyncWire(e) if e is not None else None
                             for e in (sync_edges or ())]
        self.sync_until = 0.0          # edges up to this time (s) have been delivered
        self.pose = pose
        self.model = model or SensorModel()
        self.seed = seed
        self.rng = np.random.default_rng(seed)
        self.rep_rate_hz = rep_rate_hz
        self.link_bytes_per_s = link_bytes_per_s
        self.core = FirmwareCore(name="SIL sensor board (hil_sim)", tick_hz=TICK_HZ,
                                 adc_rate_hz=int(ADC_RATE_HZ), max_samples=max_samples)
        self.core.set_link_rate(link_bytes_per_s)
        self.now = 0.0
        self.next_shot = 0.0
        self.link_credit = 0.0
        self.link_t = 0.0            # the UART has sent what it could up to this time (s)
        self._out = bytearray()      # sent since the last step()
        self.link_blocked = False  # the host side cannot take more (pty full): back-pressure
        self.shots = 0
        self._hit_cache: tuple[tuple, Hit] | None = None
        self._skipped = np.zeros(max_samples, dtype=np.uint16)  # a skipped shot's burst
        # frozen noise: every arm draws from a generator seeded by (seed, pose, config), so
        # measuring a pose again gives the same waveforms (exact regression comparisons)
        self.frozen_noise = frozen_noise
        self._in_arm = False

    def sampling(self) -> bool:
        """True while the core waits for laser edges (the Simulation then steps finely)."""
        return self.core.armed() is not None

    def _ticks(self, t: float) -> int:
        return int(round(t * TICK_HZ)) & 0xFFFFFFFF

    def hit(self, t: float) -> Hit:
        """What the beam sees at time t (cached while the pose does not change)."""
        return self._hits([t])[0]

    def _hits(self, times: list[float]) -> list[Hit]:
        """What the beam sees at each time (s): the poses not seen last are cast together,
        one ray-cast pass per table angle (a fly line's shots all differ in X)."""
        keys, poses = [], []
        for t in times:
            S, theta = self.pose(t)
            keys.append((tuple(np.round(S, 6)), round(theta, 6)))
            poses.append((np.asarray(S, float), float(theta)))
        known = dict([self._hit_cache]) if self._hit_cache is not None else {}
        todo: dict[float, dict[tuple, np.ndarray]] = {}
        for key, (S, theta) in zip(keys, poses):
            if key not in known:
                todo.setdefault(theta, {})[key] = S
        for theta, group in todo.items():
            known.update(zip(group, self.scene.cast_many(np.array(list(group.values())),
                                                         theta)))
        self._hit_cache = (keys[-1], known[keys[-1]])
        return [known[k] for k in keys]

    def _fire(self, t: float, cfg: dict, hit: Hit) -> None:
        ticks = self._ticks(t)
        self.core.set_ticks(ticks)
        if not self.core.takes_shot(ticks):
            # the core skips it (every waveform slot waits for the link): the edge is
            # counted, its samples are never looked at, so none are computed. At the link's
            # limit that is 9 shots in 10, most of the emulator's time.
            self.core.capture(self._skipped, ticks, 0)
            self.shots += 1
            return
        fs = ADC_RATE_HZ / cfg["sample_rate_div"]
        period_ticks = int(round(TICK_HZ / fs))
        phase = int(self.rng.integers(1, period_ticks + 1))  # edge to first sample (ticks)
        k = np.arange(cfg["n_samples"]) - cfg["pretrigger"]
        t_us = (k / fs + phase / TICK_HZ) * 1e6
        x = synthesize(hit, self.model, t_us, self.rng, self.seed)
        self.core.capture(to_adc(x, self.model), ticks, phase)
        self.shots += 1

    def _reseed(self, t: float, cfg: dict) -> None:
        S, theta = self.pose(t)
        key = f"{self.seed}:{np.round(S, 4).tolist()}:{round(theta, 4)}:{sorted(cfg.items())}"
        h = hashlib.blake2b(key.encode(), digest_size=8).digest()
        self.rng = np.random.default_rng(int.from_bytes(h, "little"))

    def receive(self, data: bytes, now: float) -> None:
        """Bytes from the host arrive at time now (s)."""
        self.step_to(now)
        self.core.rx(data)

    def _sync_to(self, t: float) -> None:
        """Deliver the motion-sync edges up to time t (s) to the core, before anything at t."""
        if t > self.sync_until:
            for k, source in enumerate(self.sync_sources):
                if source is not None:
                    edges = source.take(self.sync_until, t)
                    if edges.size:
                        self.core.sync_edges(np.rint(edges * TICK_HZ).astype(np.int64), k)
            self.sync_until = t

    def step_to(self, now: float) -> None:
        """Fire every laser shot up to `now` (s)."""
        period = 1.0 / self.rep_rate_hz
        if self.core.armed() is None:  # idle: the laser fires but nothing samples it
            self._in_arm = False
            self.next_shot = max(self.next_shot, now - now % period + period)
        fired = 0
        while self.next_shot <= now and fired < 100_000:
            times = [self.next_shot]  # the shots due, BATCH at most: their casts in one pass
            while len(times) < BATCH and times[-1] + period <= now:
                times.append(times[-1] + period)
            # arming comes only from the host (between calls): an idle core stays idle here
            hits = self._hits(times) if self.core.armed() is not None else None
            for i, t in enumerate(times):
                self._sync_to(t)
                self._drain(t)
                cfg = self.core.armed()  # a counted arm may end within the batch
                if cfg is not None and hits is not None:
                    if self.frozen_noise and not self._in_arm:
                        self._reseed(t, cfg)
                    self._in_arm = True
                    self._fire(t, cfg, hits[i])
                else:
                    self._in_arm = False
                self.next_shot += period
                fired += 1
        self._sync_to(now)
        self.now = max(self.now, now)
        self.core.set_ticks(self._ticks(self.now))

    def _drain(self, t: float) -> None:
        """The UART sends what it can up to time t (s). Called at every shot, not once per
        emulator step, so the device's queue fills and empties as on hardware however
        coarsely the emulator is stepped."""
        dt = t - self.link_t
        if dt <= 0:
            return
        self.link_t = t
        burst = 0.005 * self.link_bytes_per_s + 64  # a UART does not save up idle time
        self.link_credit = min(self.link_credit + dt * self.link_bytes_per_s, burst)
        n = 0 if self.link_blocked else int(self.link_credit)
        if n > 0:
            self.core.set_ticks(self._ticks(t))  # the core polls at t: no edge is after it
            data = self.core.tx(n)
            self.link_credit -= len(data)
            self._out += data
            if len(data) < n:
                # the queue ran dry: the wire idles from here, and an idle UART saves no
                # time, so the next frame (queued at a shot, after this drain) takes its
                # full time on the wire, not a head start of the idle gap
                self.link_credit = 0.0

    def step(self, now: float) -> bytes:
        """Advance to `now` and return what the link carries to the host meanwhile."""
        self.step_to(now)
        self._drain(now)
        data = bytes(self._out)
        self._out.clear()
        return data
