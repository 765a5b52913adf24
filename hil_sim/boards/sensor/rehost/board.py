"""The rehosted NUCLEO as the SIL's sensor board: its USART3 is the link, the physics its ADC input.

It has the interface the Simulation drives (`receive`, `step`, `sampling`, `link_blocked`),
so `dmdsm sim --sensor-firmware nucleo` serves the very ELF a user flashes. The laser fires
at `rep_rate_hz` (rising edge on PA0, 100 ns wide); the ADC's input around each edge is the
physics waveform for the stage pose at that edge, drawn once per shot on the ADC's own
sample grid, so pretrigger samples, the trigger phase and averaging are all the firmware's.
A broken hardware rule halts the board and is kept in `violation` (the board goes silent,
as a faulted MCU would).
"""

from __future__ import annotations

import math
import subprocess
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from ....physics.scene import Hit, Scene
from ....physics.signals import SensorModel, synthesize, to_adc
from ..core_board import SensorBoard
from .bus import RuleViolation
from .h743 import H743

REPO = Path(__file__).resolve().parents[4]
NUCLEO_ELF = REPO / "firmware/stm32/build/nucleo_h743zi/firmware.elf"
PULSE_S = 100e-9
POWER_ON_S = 0.02  # the firmware runs this long before the simulation's time 0
Pose = Callable[[float], tuple[np.ndarray, float]]


def nucleo_elf(path: str | Path | None = None, build: bool = True) -> Path:
    """The NUCLEO ELF to run: `path`, or the repository's build (made if missing)."""
    if path not in (None, "", "nucleo"):
        p = Path(path)
        if not p.is_file():
            raise FileNotFoundError(f"{p}: no such firmware ELF")
        return p
    if build:
        r = subprocess.run(["make", "-s", "-C", str(REPO / "firmware/stm32"),
                            "BOARD=nucleo_h743zi"], capture_output=True, text=True)
        if r.returncode:
            raise RuntimeError(f"NUCLEO build failed: {r.stderr.strip()[-300:]}")
    if not NUCLEO_ELF.exists():
        raise FileNotFoundError(f"{NUCLEO_ELF} not found: make -C firmware/stm32")
    return NUCLEO_ELF


class Laser:
    """A pulsed laser seen by the photodiode: one rising edge every 1/rate s, from t = 0."""

    def __init__(self, rate_hz: float) -> None:
        self.rate_hz = rate_hz

    def edges(self, t0: float, t1: float) -> list[tuple[float, float]]:
        """(rise, fall) times (s) of the pulses with rise in (t0, t1]."""
        k0, k1 = math.floor(t0 * self.rate_hz) + 1, math.floor(t1 * self.rate_hz)
        return [(k / self.rate_hz, k / self.rate_hz + PULSE_S) for k in range(k0, k1 + 1)]

    def next_edge(self, t: float) -> float:
        """Time (s) of the first pulse after t."""
        return (math.floor(t * self.rate_hz) + 1) / self.rate_hz


class SyncInput:
    """The motion-sync wires: rising edges (s) from the stage's X STEP line (input 0, PB3)
    and its A STEP line (input 1, PB10); an input with no wire has no edges."""

    LOOKAHEAD_S = 0.002  # how far ahead the next edge is looked for (an idle jump's bound)

    def __init__(self, edges: Sequence[Callable[[float, float], np.ndarray] | None]) -> None:
        self._edges = list(edges)

    def edges(self, t0: float, t1: float, input: int = 0) -> np.ndarray:
        """Times (s) of input's edges in (t0, t1]."""
        src = self._edges[input] if input < len(self._edges) else None
        return src(t0, t1) if src is not None else np.zeros(0)

    def next_edge(self, t: float) -> float:
        """Time (s) of the first edge of any input after t, or inf if none within the
        look-ahead."""
        first = math.inf
        for src in self._edges:
            if src is not None:
                e = src(t, t + self.LOOKAHEAD_S)
                if len(e):
                    first = min(first, float(e[0]))
        return first


class RehostedSensor:
    """The NUCLEO firmware ELF on a rehosted H743 with laser, physics and link."""

    def __init__(self, scene: Scene, pose: Pose, model: SensorModel | None = None,
                 seed: int = 0, rep_rate_hz: float = 1000.0, elf: str | Path | None = None,
                 rev: str = "V", faults: tuple[str, ...] = (),
                 sync_edges: Sequence[Callable[[float, float], np.ndarray] | None] | None
                 = None) -> None:
        self.scene, self.pose = scene, pose
        self.model = model or SensorModel()
        self.seed = seed
        self.laser = Laser(rep_rate_hz)
        self.mcu = H743(nucleo_elf(elf), rev=rev, faults=faults)
        self.mcu.laser = self.laser
        self.mcu.analog = self.analog
        self.mcu.event_sources += [lambda: self.laser.next_edge(self.mcu.t),
                                   self.mcu.usart3.next_event]
        if sync_edges is not None:  # the stage's X and A STEP lines on PB3, PB10 (TIM2 CH2, 3)
            self.mcu.sync = SyncInput(sync_edges)
            self.mcu.event_sources.append(lambda: self.mcu.sync.next_edge(self.mcu.t))
        self.link_blocked = False
        self.violation: RuleViolation | None = None
        self.now = 0.0
        self.shots = 0
        self._hit_cache: tuple[tuple, Hit] | None = None
        self._shot_cache: dict[tuple, tuple[int, np.ndarray]] = {}
        # powered on before anyone connects: bytes sent before USART3 is enabled (at about
        # 0.6 ms) would be lost, as on a board still in reset
        self._run(POWER_ON_S)

    # ---------------------------------------------------------------- Simulation interface
    def sampling(self) -> bool:
        """True while the firmware waits for laser edges (TIM2 CC1 interrupt enabled)."""
        return bool(self.mcu.tim2.regs.get(0x0C, 0) & 2)

    def receive(self, data: bytes, now: float) -> None:
        """Bytes from the host reach the RX pin from time now (s)."""
        self._run(now)
        self.mcu.usart3.receive(data, now)

    def step(self, now: float) -> bytes:
        """Run to `now` (s); returns the bytes the TX pin sent meanwhile."""
        if self.link_blocked:
            self.mcu.usart3.hold(max(0.0, now - self.now))
        self._run(now)
        return self.mcu.usart3.take_tx()

    def _run(self, now: float) -> None:
        if self.violation is None and now > self.mcu.t:
            try:
                self.mcu.run_until(now)
            except RuleViolation as e:
                self.violation = e
        self.now = max(self.now, now)

    # ---------------------------------------------------------------- physics
    hit = SensorBoard.hit  # what the beam sees at time t, cached while the pose holds
    _hits = SensorBoard._hits

    def analog(self, ks: np.ndarray, times: np.ndarray, grid: tuple[float, float]) -> np.ndarray:
        """ADC codes for conversions ks at times (s) on the grid (TIM8 start, period)."""
        rate = self.laser.rate_hz
        pre = 0.2 / rate  # samples this long before an edge belong to its shot
        edge = np.floor((times + pre) * rate) / rate
        out = np.empty(ks.size, np.uint16)
        for te in np.unique(edge):
            sel = edge == te
            k_lo, codes = self._shot(float(te), grid, pre)
            out[sel] = codes[ks[sel] - k_lo]
        return out

    def _shot(self, te: float, grid: tuple[float, float], pre: float) -> tuple[int, np.ndarray]:
        key = (te, grid)
        if key not in self._shot_cache:
            t_start, period = grid
            k_lo = math.floor((te - pre - t_start) / period) - 1
            n = math.ceil(1.0 / self.laser.rate_hz / period) + 4
            t_us = (t_start + (np.arange(k_lo, k_lo + n) + 1) * period - te) * 1e6
            rng = np.random.default_rng([self.seed, round(te * 1e9)])
            codes = to_adc(synthesize(self.hit(te), self.model, t_us, rng, self.seed),
                           self.model)
            if len(self._shot_cache) > 8:
                self._shot_cache.clear()
            self._shot_cache[key] = (k_lo, codes)
            self.shots += 1
        return self._shot_cache[key]
