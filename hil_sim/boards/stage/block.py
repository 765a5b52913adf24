"""One Marlin planner block in the emulator: its steps, speeds and trapezoid in step rates,
and when each STEP pulse of each axis comes (stepper.cpp's timing; the planner: motion.py)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from dmdsm.marlin_patch import MINIMAL_STEP_RATE


@dataclass
class Move:
    """One planner block: steps, speeds (mm/s), and once planned its profile in step rates.

    Its twin is the host's `dmdsm.host.scan.fly.LineMotion` (one rest-to-rest line, all the
    fly scan needs; the host may not import the emulator). The two are written apart on
    purpose and held together by tests/test_fly_model.py
    (`test_the_host_model_puts_each_instant_within_a_step_of_the_emulated_marlin`)."""

    start: np.ndarray    # steps
    target: np.ndarray   # steps
    length: float        # mm (or deg for an A-only move)
    v: float             # nominal speed along the move (mm/s)
    a: float             # acceleration along the move (mm/s^2)
    unit: np.ndarray     # direction, for the junction speed
    added: float = 0.0           # when it was queued (s)
    after_idle: bool = False     # queued while the planner was empty (first-move delay)
    max_entry: float = 0.0       # junction limit (mm/s)
    entry: float = 0.0           # the trapezoid's entry and exit speed (mm/s)
    exit: float = 0.0
    entry_sqr: float = 0.0       # Marlin's entry_speed_sqr, max_ and min_entry_speed_sqr
    max_entry_sqr: float = 0.0   # ((mm/s)^2): the look-ahead's state between two blocks
    min_entry_sqr: float = 0.0
    recalculate: bool = True     # Marlin's flag.recalculate: its trapezoid is to be redone
    calculated: bool = False     # a trapezoid was computed (Marlin: initial_rate != 0)
    t0: float | None = None      # when its first step was taken (None: still queued)
    dropped: bool = False        # too few steps: never queued (MIN_STEPS_PER_SEGMENT)
    cut: float = math.inf        # a quick stop ended it here (s)
    slip: np.ndarray | None = None  # the planner's slip when it was queued (steps)
    initial_rate: float | None = None  # steps/s kept from an earlier trapezoid (Marlin's
    # entry factor 0), or the running block's final rate, whatever the axes; None: from entry
    _edges: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.delta = self.target - self.start
        self.n = int(np.max(np.abs(self.delta))) if self.delta.size else 0
        self.profile()

    @property
    def min_speed(self) -> float:
        """Marlin's minimum_planner_speed (mm/s, deg/s): the average speed over one step from
        rest at the block's acceleration, sqrt(a / 2 / steps_per_mm), at most its nominal
        speed; no entry or exit speed is lower (planner.cpp)."""
        if self.n == 0 or self.length <= 0:
            return 0.0
        return min(math.sqrt(0.5 * self.a * self.length / self.n), self.v)

    # --------------------------------------------------------------- trapezoid in steps
    def profile(self) -> None:
        """Rates (steps/s of the dominant axis) and phase lengths from entry and exit."""
        n = self.n
        if n == 0 or self.length <= 0:
            self.r0 = self.r1 = self.r2 = 1.0
            self.A = 1.0
            self.lead = 0.0
            self.d_acc = self.d_dec = self.d_cruise = self._duration = 0.0
            return
        k = n / self.length  # steps per mm along the move
        rn = max(self.v * k, MINIMAL_STEP_RATE)
        r0 = self.initial_rate if self.initial_rate is not None else self.entry * k
        r0 = min(max(r0, MINIMAL_STEP_RATE), rn)
        r2 = min(max(self.exit * k, MINIMAL_STEP_RATE), rn)
        A = self.a * k
        d_acc = (rn * rn - r0 * r0) / (2 * A)
        d_dec = (rn * rn - r2 * r2) / (2 * A)
        if d_acc + d_dec > n:  # never reaches the nominal rate
            rn = math.sqrt((2 * A * n + r0 * r0 + r2 * r2) / 2)
            if rn < r0:  # cannot slow down that much: decelerate over the whole block
                rn, r2 = r0, math.sqrt(max(r0 * r0 - 2 * A * n, MINIMAL_STEP_RATE ** 2))
                d_acc, d_dec = 0.0, float(n)
            elif rn < r2:  # cannot speed up that much: accelerate over the whole block
                rn = r2 = math.sqrt(r0 * r0 + 2 * A * n)
                d_acc, d_dec = float(n), 0.0
            else:
                d_acc = (rn * rn - r0 * r0) / (2 * A)
                d_dec = max(n - d_acc, 0.0)
        self.r0, self.r1, self.r2, self.A = r0, rn, r2, A
        self.d_acc, self.d_dec = d_acc, d_dec
        self.d_cruise = max(n - d_acc - d_dec, 0.0)
        self.lead = 1.0 / r0  # the first step comes one period of the initial rate in
        # (stepper.cpp), the others as the continuous profile places them, the last at the end
        self._duration = self.lead + float(self.time_of(n - 1.0))

    def trapezoid(self, entry: float, exit: float) -> None:
        """Marlin's calculate_trapezoid_for_block: the profile from entry to exit (mm/s); an
        entry of 0 keeps the initial rate the block had."""
        if entry:
            self.initial_rate = None
            self.entry = entry
        elif self.initial_rate is None:
            self.initial_rate = self.r0 if self.n else MINIMAL_STEP_RATE
        self.exit = exit
        self.recalculate = False
        self.calculated = True
        self.profile()

    @property
    def t_acc(self) -> float:
        """Acceleration time (s)."""
        return (self.r1 - self.r0) / self.A

    @property
    def t_cruise(self) -> float:
        """Cruise time (s)."""
        return self.d_cruise / self.r1

    @property
    def t_dec(self) -> float:
        """Deceleration time (s)."""
        return (self.r1 - self.r2) / self.A

    @property
    def duration(self) -> float:
        """Time from the first step until the block hands over to the next (s)."""
        return 0.0 if self.n == 0 else self._duration

    def s_at(self, t: np.ndarray | float) -> np.ndarray:
        """Dominant-axis steps of the continuous profile t seconds after the first step
        (0..n; the first step is taken at 0, step k at k - 1)."""
        t = np.clip(np.asarray(t, dtype=float), 0.0, self.t_acc + self.t_cruise + self.t_dec)
        ta, tc = self.t_acc, self.t_cruise
        acc = self.r0 * t + 0.5 * self.A * t * t
        cru = self.d_acc + self.r1 * (t - ta)
        tau = t - ta - tc
        dec = self.d_acc + self.d_cruise + self.r1 * tau - 0.5 * self.A * tau * tau
        return np.where(t < ta, acc, np.where(t < ta + tc, cru, dec))

    def time_of(self, s: np.ndarray) -> np.ndarray:
        """Inverse of s_at: seconds after the first step when s steps are done."""
        s = np.asarray(s, dtype=float)
        A, r0, r1 = self.A, self.r0, self.r1
        with np.errstate(invalid="ignore"):
            acc = (np.sqrt(np.maximum(r0 * r0 + 2 * A * s, 0.0)) - r0) / A
            cru = self.t_acc + (s - self.d_acc) / r1
            x = s - self.d_acc - self.d_cruise
            dec = self.t_acc + self.t_cruise + (r1 - np.sqrt(np.maximum(r1 * r1 - 2 * A * x,
                                                                         0.0))) / A
        return np.where(s < self.d_acc, acc, np.where(s < self.d_acc + self.d_cruise, cru, dec))

    def steps_after(self, t: float) -> np.ndarray:
        """Signed steps of every axis t seconds after the block was loaded (Bresenham)."""
        if self.n == 0 or t < self.lead:
            return np.zeros_like(self.delta)
        k = min(self.n, int(math.floor(float(self.s_at(t - self.lead)))) + 1)
        if t >= self.duration:
            k = self.n
        moved = (2 * k * np.abs(self.delta) + self.n) // (2 * self.n)
        return np.sign(self.delta) * moved

    def edges(self, axis: int) -> np.ndarray:
        """Times (s after the block was loaded) of the STEP pulses of one axis."""
        if axis not in self._edges:
            d = int(abs(self.delta[axis]))
            if d == 0 or self.n == 0:
                self._edges[axis] = np.zeros(0)
            else:
                k = np.arange(1, self.n + 1, dtype=np.int64)
                m = (2 * k * d + self.n) // (2 * self.n)
                steps_at = k[np.diff(np.concatenate(([0], m))) > 0]
                self._edges[axis] = self.lead + self.time_of(steps_at - 1.0)
        return self._edges[axis]

    @property
    def end(self) -> float:
        """When it ended or will end (s); inf while it has not started."""
        return math.inf if self.t0 is None else min(self.t0 + self.duration, self.cut)
