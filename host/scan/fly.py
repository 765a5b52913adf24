"""Fly scanning's pure part: line speed, ramps, Marlin's trapezoid in time, and shot placement.

A fly line is one G1 along X from rest to rest. Marlin runs it as a trapezoid in step rates
that starts and ends at the block's minimum planner speed, sqrt(a / 2 * steps_per_mm) steps/s
(the average rate over one step from rest; 118 steps/s on X), not at zero. The sensor board
time-stamps the X STEP pulses (first, last, count: the motion_sync message) in the clock of
its waveforms, so each shot is placed by `LineMotion.x_at` on the model anchored at the first
step, with the time scaled so the model's last step falls on the measured one (Marlin's
crystal against the sensor's). docs/scanning.md gives the error budget.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dmdsm.marlin_patch import MINIMAL_STEP_RATE

SCALE_TOLERANCE = 0.01     # |measured / modelled duration - 1| above this: not the move we made
CRUISE_TOLERANCE = 0.03    # |counted / planned advance per waveform - 1| within this: cruising


def line_speed_mm_s(step_mm: float, laser_hz: float, average: int) -> float:
    """Speed (mm/s) that puts consecutive averaged waveforms step_mm apart."""
    return step_mm * laser_hz / average


def ramp_mm(v_mm_s: float, accel_mm_s2: float, step_mm: float) -> float:
    """Run-up (and run-out) length (mm) beyond the measured part: the distance to reach v
    from rest, one waveform's travel, and 1 mm to spare."""
    return v_mm_s * v_mm_s / (2 * accel_mm_s2) + step_mm + 1.0


@dataclass(frozen=True)
class LineMotion:
    """Marlin's rest-to-rest move of one axis: x0 -> x1 (mm) at up to v (mm/s), accel a
    (mm/s^2), steps_per_mm; positions in time since the first STEP pulse (s).

    Its twin is the emulator's planner block `dmdsm.sim.boards.stage.block.Move` (the whole
    planner: junctions, queued blocks); the host may not import the emulator, so the model is
    written twice on purpose, and tests/test_fly_model.py
    (`test_the_host_model_puts_each_instant_within_a_step_of_the_emulated_marlin`) holds the
    two within a step of each other."""

    x0: float
    x1: float
    v: float
    a: float
    steps_per_mm: float

    @property
    def n(self) -> int:
        """Steps of the move (whole steps between the two quantised ends)."""
        return abs(round(self.x1 * self.steps_per_mm) - round(self.x0 * self.steps_per_mm))

    @property
    def direction(self) -> float:
        """+1 towards larger X, -1 towards smaller."""
        return 1.0 if self.x1 >= self.x0 else -1.0

    def _rates(self) -> tuple[float, float, float, float]:
        """(start rate, peak rate, acceleration in steps/s^2, steps to the peak)."""
        k = self.steps_per_mm
        A = self.a * k
        r0 = max(min(math.sqrt(0.5 * A), self.v * k), MINIMAL_STEP_RATE)  # planner.cpp
        peak = max(self.v * k, r0)
        d = (peak * peak - r0 * r0) / (2 * A)
        if 2 * d > self.n:  # a triangle: never reaches v
            peak = math.sqrt(A * self.n + r0 * r0)
            d = self.n / 2
        return r0, peak, A, d

    def steps_at(self, t: np.ndarray) -> np.ndarray:
        """Steps done (continuous) t seconds after the first STEP pulse."""
        r0, r1, A, d = self._rates()
        t_acc = (r1 - r0) / A
        t_cruise = (self.n - 2 * d) / r1
        t = np.clip(np.asarray(t, dtype=float), 0.0, 2 * t_acc + t_cruise)
        acc = r0 * t + 0.5 * A * t * t
        cruise = d + r1 * (t - t_acc)
        tau = t - t_acc - t_cruise
        dec = self.n - d + r1 * tau - 0.5 * A * tau * tau
        return np.where(t < t_acc, acc, np.where(t < t_acc + t_cruise, cruise, dec))

    def time_of_step(self, s: float) -> float:
        """Seconds after the first STEP pulse when s steps (continuous) are done."""
        r0, r1, A, d = self._rates()
        t_acc = (r1 - r0) / A
        if s < d:
            return (math.sqrt(r0 * r0 + 2 * A * s) - r0) / A
        if s <= self.n - d:
            return t_acc + (s - d) / r1
        x = s - (self.n - d)
        return t_acc + (self.n - 2 * d) / r1 + (r1 - math.sqrt(max(r1 * r1 - 2 * A * x,
                                                                    0.0))) / A

    @property
    def last_step_s(self) -> float:
        """When the last STEP pulse comes (s after the first): pulse k at k - 1 steps done."""
        return self.time_of_step(self.n - 1)

    @property
    def cruise_s(self) -> tuple[float, float]:
        """(start, end) of the constant-speed part (s after the first pulse)."""
        r0, r1, A, d = self._rates()
        t_acc = (r1 - r0) / A
        return t_acc, t_acc + (self.n - 2 * d) / r1

    def x_at(self, t: np.ndarray) -> np.ndarray:
        """Axis position (mm) t seconds after the first STEP pulse: pulse k has made k steps,
        so the mean over the step's duration is half a step past the continuous count."""
        s = np.minimum(self.steps_at(t) + 0.5, self.n)
        x0 = round(self.x0 * self.steps_per_mm) / self.steps_per_mm
        return x0 + self.direction * s / self.steps_per_mm


def counted_x(motion: LineMotion, sync_steps: np.ndarray, n_average: int) -> np.ndarray:
    """Each waveform's mean X (mm) from the X steps the sensor counted before its shots
    (waveform.sync_steps, summed over its n_average shots): measured, not modelled, so it
    holds whatever ramps the stage's firmware makes (the AVR Marlin's differ from the
    planner's trapezoid by up to 3 ms, 0.3 mm at 83 mm/s)."""
    x0 = round(motion.x0 * motion.steps_per_mm) / motion.steps_per_mm
    steps = np.asarray(sync_steps, dtype=np.float64) / n_average
    return x0 + motion.direction * steps / motion.steps_per_mm


def at_line_speed(x_mm: np.ndarray, v_mm_s: float, n_average: int, laser_period_s: float,
                  tolerance: float = CRUISE_TOLERANCE,
                  shots_apart: np.ndarray | None = None) -> np.ndarray:
    """Waveforms that moved at the line speed: the counted advance to the previous or the
    next waveform is the planned one within `tolerance` (a waveform deep in a ramp moves
    less on both sides). shots_apart: laser shots from each waveform's first to the next's
    (n_average, more where the board skipped shots between them; len(x_mm) - 1)."""
    gaps = n_average if shots_apart is None else np.asarray(shots_apart, dtype=np.float64)
    want = v_mm_s * gaps * laser_period_s
    ok = np.abs(np.abs(np.diff(x_mm)) / want - 1.0) <= tolerance
    out = np.zeros(len(x_mm), bool)
    out[1:] |= ok
    out[:-1] |= ok
    return out


def place_shots(motion: LineMotion, first_edge_ticks: int, last_edge_ticks: int,
                tick_hz: float, timestamps: np.ndarray, n_average: int, laser_period_s: float,
                ) -> tuple[np.ndarray, np.ndarray, float]:
    """Each averaged waveform's mean X (mm) and whether all its shots fall in the cruise;
    and the time scale (measured / modelled line duration).

    timestamps: device ticks of each waveform's first shot; its shots follow at
    laser_period_s. Raises ValueError if the measured duration does not fit the model."""
    measured = (last_edge_ticks - first_edge_ticks) / tick_hz
    scale = measured / motion.last_step_s if motion.last_step_s > 0 else 1.0
    if not abs(scale - 1.0) <= SCALE_TOLERANCE:
        raise ValueError(f"the X move took {measured:.4f} s, the planner model says "
                         f"{motion.last_step_s:.4f} s")
    t_first = (np.asarray(timestamps, dtype=np.float64) - first_edge_ticks) / tick_hz
    k = np.arange(n_average) * laser_period_s
    t = (t_first[:, None] + k[None, :]) / scale  # in the stage's clock
    x = motion.x_at(t).mean(axis=1)
    c0, c1 = motion.cruise_s
    cruise = (t[:, 0] >= c0) & (t[:, -1] <= c1)
    return x, cruise, scale


@dataclass(frozen=True)
class LinePath:
    """A fly line's path in the XY plane (mm): straight joined moves through vertices whose X
    only advances (run-up start, the line's vertices, run-out end). Each segment is linear
    in X, so a shot's counted X gives its Y and its distance along the path."""

    x: np.ndarray  # (k,) vertex X in execution order, strictly monotonic
    y: np.ndarray  # (k,) vertex Y

    def __post_init__(self) -> None:
        dx = np.diff(self.x)
        if len(self.x) < 2 or not (np.all(dx > 0) or np.all(dx < 0)):
            raise ValueError("a fly line's X must advance on every segment")

    def _ascending(self) -> tuple[np.ndarray, np.ndarray]:
        return (self.x, self.y) if self.x[-1] > self.x[0] else (self.x[::-1], self.y[::-1])

    def y_at(self, x_mm: np.ndarray) -> np.ndarray:
        """Y (mm) on the path where X is x_mm."""
        xa, ya = self._ascending()
        return np.interp(x_mm, xa, ya)

    def s_at(self, x_mm: np.ndarray) -> np.ndarray:
        """Path length (mm) from the start to where X is x_mm."""
        s = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(self.x), np.diff(self.y)))])
        if self.x[-1] > self.x[0]:
            return np.interp(x_mm, self.x, s)
        return np.interp(x_mm, self.x[::-1], s[::-1])

    @property
    def length_mm(self) -> float:
        """Total path length (mm)."""
        return float(np.sum(np.hypot(np.diff(self.x), np.diff(self.y))))


def junction_speed_mm_s(u1: np.ndarray, u2: np.ndarray, accel_mm_s2: float,
                        junction_deviation_mm: float) -> float:
    """Marlin's junction-deviation speed limit (mm/s) between segments along unit vectors u1
    and u2: v^2 = a jd sin(theta/2) / (1 - sin(theta/2)), theta the angle the path keeps
    (180 deg straight on)."""
    cos_theta = max(-float(np.dot(u1, u2)), -0.999999)
    if cos_theta > 0.999999:
        return 0.0
    sin_d2 = math.sqrt(0.5 * (1.0 - cos_theta))
    return math.sqrt(accel_mm_s2 * junction_deviation_mm * sin_d2 / (1.0 - sin_d2))
