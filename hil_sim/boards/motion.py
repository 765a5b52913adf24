"""Stage motion for the Marlin emulator: a planner queue of trapezoidal moves, step-quantised.

Each move starts and ends at rest (no junction look-ahead: slightly slower than Marlin on
chained moves, never faster). The feedrate and acceleration along the move are scaled down
until no axis exceeds its own limit, as Marlin's planner does. Positions are in mm (X, Y, Z)
and degrees (A); the steppers hold whole steps.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from dmdsm.marlin_patch import MachineLimits


@dataclass
class Move:
    """One planner block: start/target in steps, start time and its profile (s, mm/s)."""

    start: np.ndarray    # steps
    target: np.ndarray   # steps
    length: float        # mm (or deg for an A-only move)
    v: float             # cruise speed along the move
    a: float             # acceleration along the move
    t_acc: float = 0.0   # s
    t_cruise: float = 0.0
    added: float = 0.0       # when it was queued (s)
    t0: float | None = None  # when it started executing (None: still queued)

    @property
    def duration(self) -> float:
        """Total time of the move (s)."""
        return 2 * self.t_acc + self.t_cruise

    def fraction(self, t: float) -> float:
        """Fraction of the move done t seconds after its start (0..1)."""
        if self.length == 0 or t >= self.duration:
            return 1.0
        if t <= 0:
            return 0.0
        d_acc = 0.5 * self.a * self.t_acc ** 2
        if t < self.t_acc:
            s = 0.5 * self.a * t * t
        elif t < self.t_acc + self.t_cruise:
            s = d_acc + self.v * (t - self.t_acc)
        else:
            td = self.duration - t
            s = self.length - 0.5 * self.a * td * td
        return min(1.0, s / self.length)


@dataclass
class Planner:
    """The planner queue and stepper positions of a 4-axis stage."""

    limits: MachineLimits
    steps: np.ndarray = field(init=False)       # where the steppers are (last update)
    queue: list[Move] = field(default_factory=list)
    prev_end: float = -math.inf  # when the last finished block ended (s)

    def __post_init__(self) -> None:
        self.steps = np.zeros(len(self.limits.axes), dtype=np.int64)
        self.spu = np.asarray(self.limits.steps_per_unit, dtype=float)
        self.vmax = np.asarray(self.limits.max_feedrate, dtype=float)
        self.amax = np.asarray(self.limits.max_acceleration, dtype=float)

    def to_steps(self, pos: np.ndarray) -> np.ndarray:
        """Positions (mm, deg) to whole steps."""
        return np.rint(np.asarray(pos, dtype=float) * self.spu).astype(np.int64)

    def free_blocks(self) -> int:
        """Planner blocks free (Marlin's P in `ok N P B`)."""
        return self.limits.block_buffer_size - len(self.queue)

    def add(self, now: float, start_steps: np.ndarray, target_steps: np.ndarray,
            feed_mm_s: float, accel: float | None = None) -> Move:
        """Queue at time `now` (s) a move from start to target at up to feed_mm_s."""
        delta = (target_steps - start_steps) / self.spu
        linear = float(np.linalg.norm(delta[:3]))
        length = linear if linear > 0 else float(abs(delta[3:]).sum())
        v = feed_mm_s
        a = accel if accel is not None else self.limits.default_acceleration
        if length > 0:
            unit = np.abs(delta) / length  # axis speed per unit of path speed
            with np.errstate(divide="ignore"):
                v = min(v, float(np.min(np.where(unit > 0, self.vmax / unit, np.inf))))
                a = min(a, float(np.min(np.where(unit > 0, self.amax / unit, np.inf))))
        move = Move(start_steps.copy(), target_steps.copy(), length, max(v, 1e-6), max(a, 1e-6),
                    added=now)
        if length > 0:
            t_acc = move.v / move.a
            if move.a * t_acc * t_acc > length:  # triangle: never reaches cruise
                t_acc = math.sqrt(length / move.a)
                move.v = move.a * t_acc
            move.t_acc = t_acc
            move.t_cruise = max(0.0, (length - move.a * t_acc * t_acc) / move.v)
        self.queue.append(move)
        return move

    def update(self, now: float) -> None:
        """Advance execution to time `now` (s): finished blocks leave the queue."""
        while self.queue:
            m = self.queue[0]
            if m.t0 is None:
                m.t0 = max(m.added, self.prev_end)
            end = m.t0 + m.duration
            if end > now:
                f = m.fraction(now - m.t0)
                self.steps = np.rint(m.start + (m.target - m.start) * f).astype(np.int64)
                return
            self.steps = m.target.copy()
            self.prev_end = end
            self.queue.pop(0)

    def busy_until(self, now: float) -> float:
        """Time (s) when the queued moves will all have finished."""
        self.update(now)
        t = now
        for m in self.queue:
            t = max(t, m.t0 if m.t0 is not None else m.added) + m.duration
            if m.t0 is not None:
                t = m.t0 + m.duration
        return t

    def quick_stop(self, now: float) -> None:
        """M410: stop where the steppers are and drop every queued block."""
        self.update(now)
        self.queue.clear()
        self.prev_end = now

    def position(self) -> np.ndarray:
        """Where the steppers are, in mm and degrees."""
        return self.steps / self.spu
