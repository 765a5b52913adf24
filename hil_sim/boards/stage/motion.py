"""Stage motion for the Marlin emulator: Marlin's planner and stepper, in simulated time.

What a host can observe of a real Marlin's motion is modelled as Marlin 2.1 does it
(planner.cpp, stepper.cpp): junction deviation and the look-ahead passes set each block's
entry and exit speed, never below the block's own minimum planner speed (the average speed
over one step from rest at its acceleration, sqrt(a / 2 / steps_per_mm)) nor a step rate
below MINIMAL_STEP_RATE; a block runs a trapezoid in step rates; the stepper takes a block's
first step one period of its initial rate after loading it and loads the next one at its
last step; the look-ahead keeps Marlin's state between blocks (the running block and the
next one to run are never re-planned, the reverse pass stops at the first block whose entry
it cannot raise), and a block queued while only the running one is left starts at that one's
final step rate; the first block after the queue ran dry waits up to
BLOCK_DELAY_FOR_1ST_MOVE unless three blocks are queued; a short block queued while few wait
is slowed (SLOWDOWN, min_segment_time_us), and a shallow corner after a sub-millimetre block
is limited by the arc it approximates (JD_HANDLE_SMALL_SEGMENTS); the dominant axis steps at
the profile's rate and the others follow by Bresenham; a move of fewer than
MIN_STEPS_PER_SEGMENT steps on every axis is dropped, its steps left to the next move (the
planner keeps its own position, apart from the steppers'), and a re-sync of the planner's
position while steps are owed (homing another axis) sets the counts there without a step:
the counts and where the carriage is then differ (`slip`).
Positions are in mm (X, Y, Z) and degrees (A); the steppers hold whole steps.
Not modelled: S-curve acceleration (off in the patch), the ISR's tick quantisation and its
rate running ahead of the trapezoid (docs/marlin.md).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from dmdsm.marlin_patch import MachineLimits

from .block import Move

BLOCK_DELAY_FOR_1ST_MOVE = 0.1  # s: hold of the first block after the queue ran dry
MIN_STEPS_PER_SEGMENT = 6       # Configuration_adv.h: a block whose largest axis step count is
# below this is not queued, and the planner's position stays where it was (planner.cpp)
HISTORY = 512                   # finished blocks kept for position_at() and step_edges():
# a fly line of joined short moves runs dozens of blocks between two queries of the sync wire


def _acos_minus(cos_theta: float) -> float:
    """The junction's turn (rad) as Marlin's JD_HANDLE_SMALL_SEGMENTS estimates it: acos of
    -cos_theta by its min-max polynomial (error up to 0.033 rad, its floor 0.033 rad)."""
    t = abs(cos_theta)
    asin_t = 0.032843707 + t * (-1.451838349 + t * (29.66153956 + t * (
        -131.1123477 + t * (262.8130562 + t * (-242.7199627 + t * 84.31466202)))))
    return math.pi / 2 + (-1.0 if cos_theta < 0 else 1.0) * asin_t


@dataclass
class Planner:
    """The planner queue, the stepper and the step counts of a 4-axis stage."""

    limits: MachineLimits
    steps: np.ndarray = field(init=False)       # the steppers' counts (last update)
    slip: np.ndarray = field(init=False)  # counts minus where the carriage is (steps): what
    # a re-sync with steps owed (sync_plan_position) put on the counts without a step
    pos: np.ndarray = field(init=False)  # Marlin's planner.position: the last queued block's
    # target (steps); a dropped move leaves it, so the next move takes the dropped steps too
    queue: list[Move] = field(default_factory=list)
    prev_end: float = -math.inf  # when the last finished block ended (s)

    def __post_init__(self) -> None:
        self.steps = np.zeros(len(self.limits.axes), dtype=np.int64)
        self.pos = self.steps.copy()
        self.slip = self.steps.copy()
        self.spu = np.asarray(self.limits.steps_per_unit, dtype=float)
        self.vmax = np.asarray(self.limits.max_feedrate, dtype=float)
        self.amax = np.asarray(self.limits.max_acceleration, dtype=float)
        self.jd = float(getattr(self.limits, "junction_deviation_mm", 0.013))
        self.history: deque[Move] = deque(maxlen=HISTORY)

    def to_steps(self, pos: np.ndarray) -> np.ndarray:
        """Positions (mm, deg) to whole steps."""
        return np.rint(np.asarray(pos, dtype=float) * self.spu).astype(np.int64)

    def free_blocks(self) -> int:
        """Planner blocks free (Marlin's P in `ok N P B`)."""
        return self.limits.block_buffer_size - len(self.queue)

    def set_axis(self, axis: int, count: int) -> None:
        """Set an axis's planner position and stepper count where the carriage is (homing;
        the queue is empty)."""
        self.pos[axis] = self.steps[axis] = count
        self.slip[axis] = 0

    def sync_axis(self, axis: int, count: int) -> None:
        """Marlin's sync_plan_position with the queue empty: the planner's position and the
        stepper's count set to `count`, the carriage where it is (steps a dropped move left
        owed are then never taken)."""
        self.slip[axis] += count - self.steps[axis]
        self.pos[axis] = self.steps[axis] = count

    def line_to(self, now: float, target_steps: np.ndarray, feed_mm_s: float) -> Move:
        """Queue at time `now` (s) a move from the planner's position to target (steps), as
        Marlin's buffer_line: it is dropped, and the planner's position kept, if no axis
        moves MIN_STEPS_PER_SEGMENT steps or more (`move.dropped`)."""
        return self.add(now, self.pos, target_steps, feed_mm_s)

    def add(self, now: float, start_steps: np.ndarray, target_steps: np.ndarray,
            feed_mm_s: float, accel: float | None = None) -> Move:
        """Queue at time `now` (s) a move from start to target at up to feed_mm_s; one of
        fewer than MIN_STEPS_PER_SEGMENT steps on every axis is returned `dropped`, not
        queued. A queued move's target becomes the planner's position."""
        delta = (target_steps - start_steps) / self.spu
        linear = float(np.linalg.norm(delta[:3]))
        length = linear if linear > 0 else float(abs(delta[3:]).sum())
        v = self._slowdown(length, feed_mm_s) if length > 0 else feed_mm_s
        a = accel if accel is not None else self.limits.default_acceleration
        unit = delta / length if length > 0 else np.zeros_like(delta)
        if length > 0:
            axis_unit = np.abs(unit)  # axis speed per unit of path speed
            with np.errstate(divide="ignore"):
                v = min(v, float(np.min(np.where(axis_unit > 0, self.vmax / axis_unit,
                                                 np.inf))))
                a = min(a, float(np.min(np.where(axis_unit > 0, self.amax / axis_unit,
                                                 np.inf))))
        move = Move(start_steps.copy(), target_steps.copy(), length, max(v, 1e-6),
                    max(a, 1e-6), unit, added=now, after_idle=not self.queue,
                    slip=self.slip.copy())
        if move.n < MIN_STEPS_PER_SEGMENT:
            move.dropped = True  # Marlin's _populate_block bails out before the position
            return move          # update: the steps stay owed to the next move
        self.pos = np.array(target_steps, dtype=np.int64)
        waiting = [m for m in self.queue if m.t0 is None]
        prev = waiting[-1] if waiting else None  # Marlin joins only to a block not yet running
        move.max_entry = self._junction(prev, move) if prev is not None else move.min_speed
        move.max_entry_sqr = move.max_entry ** 2
        move.entry_sqr = move.min_entry_sqr = move.min_speed ** 2
        self.queue.append(move)
        self._replan(move.min_speed ** 2)
        return move

    def _slowdown(self, length: float, feed_mm_s: float) -> float:
        """Marlin's SLOWDOWN: while 2 to block_buffer_size / slowdown_divisor - 1 blocks wait
        to run (the one running not counted), a block shorter in time at feed_mm_s than
        min_segment_time_us is stretched by twice the shortfall over that count (us, in
        Marlin's integer arithmetic), so the queue drains more slowly; the feed (mm/s)."""
        waiting = sum(1 for m in self.queue if m.t0 is None)
        if not 2 <= waiting <= self.limits.block_buffer_size // self.limits.slowdown_divisor - 1:
            return feed_mm_s
        segment_us = round(1e6 * length / feed_mm_s)
        short_us = int(self.limits.min_segment_time_us) - segment_us
        if short_us <= 0:
            return feed_mm_s
        return length * 1e6 / (segment_us + 2 * short_us // waiting)

    def _junction(self, prev: Move, move: Move) -> float:
        """Largest speed (mm/s) through the corner between two blocks (junction deviation)."""
        cos_theta = -float(np.dot(prev.unit, move.unit))
        if cos_theta > 0.999999:  # a reversal
            return move.min_speed
        cos_theta = max(cos_theta, -0.999999)
        ju = move.unit - prev.unit
        norm = float(np.linalg.norm(ju))
        a = move.a
        if norm > 0:
            ju = np.abs(ju / norm)
            with np.errstate(divide="ignore"):
                a = min(a, float(np.min(np.where(ju > 0, self.amax / ju, np.inf))))
        sin_d2 = math.sqrt(0.5 * (1.0 - cos_theta))
        v2 = a * self.jd * sin_d2 / (1.0 - sin_d2)
        if move.length < 1 and cos_theta < -0.7071067812:  # JD_HANDLE_SMALL_SEGMENTS:
            v2 = min(v2, move.length * a / _acos_minus(cos_theta))  # the arc's curvature
        return max(math.sqrt(min(v2, move.v ** 2, prev.v ** 2)), move.min_speed)

    def _replan(self, safe_exit_sqr: float) -> None:
        """Marlin's recalculate(): the reverse pass from the newest block back, which never
        touches the first block not yet running and stops at the first block whose entry it
        cannot raise; then the forward kernel and the trapezoids of the flagged blocks (and
        of the one before them, whose exit changed) from the running block on."""
        todo = [m for m in self.queue if m.t0 is None]
        nxt: Move | None = None
        for m in reversed(todo[1:]):  # reverse_pass
            if not self._reverse_kernel(m, nxt, safe_exit_sqr):
                break
            nxt = m
        block: Move | None = None
        next_entry = 0.0  # mm/s; 0: a trapezoid keeps its initial rate
        for m in self.queue:  # recalculate_trapezoids
            if m.recalculate:
                if block is None:  # the first block after the queue ran dry
                    m.entry_sqr = m.min_entry_sqr
                    next_entry = math.sqrt(m.min_entry_sqr)
                elif block.t0 is not None:  # behind the running block: its final rate
                    m.entry_sqr = m.min_entry_sqr
                    if not m.calculated:
                        m.initial_rate = block.r2
                else:
                    if m.entry_sqr != m.min_entry_sqr:
                        self._forward_kernel(block, m)
                    entry, next_entry = next_entry, math.sqrt(m.entry_sqr)
                    block.trapezoid(entry, next_entry)
            block = m
        if block is not None and block.recalculate and block.t0 is None:
            block.trapezoid(next_entry, math.sqrt(safe_exit_sqr))

    @staticmethod
    def _reverse_kernel(m: Move, nxt: Move | None, safe_exit_sqr: float) -> bool:
        """Raise m's entry to what it can slow down from to the next block's entry (or the
        safe exit); True if it rose."""
        if (nxt is None or nxt.recalculate) and m.entry_sqr != m.max_entry_sqr:
            nes = nxt.entry_sqr if nxt is not None else safe_exit_sqr
            new = min(nes + 2 * m.a * m.length, m.max_entry_sqr)
            if m.entry_sqr != new:
                m.recalculate = True
                m.entry_sqr = new
                return True
        return False

    @staticmethod
    def _forward_kernel(prev: Move, m: Move) -> None:
        """Lower m's entry to what prev can reach from its own entry; that becomes m's
        floor."""
        if prev.entry_sqr < m.entry_sqr:
            new = prev.entry_sqr + 2 * prev.a * prev.length
            if new < m.entry_sqr:
                new = max(new, m.min_entry_sqr)
                m.entry_sqr = m.max_entry_sqr = new
        m.min_entry_sqr = m.entry_sqr

    def _start_time(self, m: Move) -> float:
        """When the head block starts (Marlin holds a lone block after idle)."""
        if not m.after_idle or self.prev_end >= m.added:
            return max(m.added, self.prev_end)
        t = m.added + BLOCK_DELAY_FOR_1ST_MOVE
        if len(self.queue) >= 3:
            t = min(t, max(m.added, self.queue[2].added))
        return t

    def update(self, now: float) -> None:
        """Advance execution to time `now` (s): finished blocks leave the queue."""
        while self.queue:
            m = self.queue[0]
            if m.t0 is None:
                start = self._start_time(m)
                if start > now:
                    return
                m.t0 = start
                self.history.append(m)
            if m.end > now:
                self.steps = m.start + m.steps_after(now - m.t0)
                return
            self.steps = m.target.copy()
            self.prev_end = m.end
            self.queue.pop(0)

    def busy_until(self, now: float) -> float:
        """Time (s) when the queued moves will all have finished, as planned now."""
        self.update(now)
        t = now
        for i, m in enumerate(self.queue):
            if m.t0 is not None:
                t = m.end
            elif i == 0:
                t = max(now, self._start_time(m)) + m.duration
            else:
                t += m.duration
        return t

    def quick_stop(self, now: float) -> None:
        """M410: stop where the steppers are and drop every queued block."""
        self.update(now)
        for m in self.queue:
            if m.t0 is not None:
                m.cut = now
        self.queue.clear()
        self.prev_end = now
        self.pos = self.steps.copy()  # quickstop_stepper(): sync_plan_position()

    def position(self) -> np.ndarray:
        """Where the carriage is, in mm and degrees."""
        return (self.steps - self.slip) / self.spu

    def count_position(self) -> np.ndarray:
        """The steppers' counts, in mm and degrees (what Marlin reports from the steppers)."""
        return self.steps / self.spu

    def _covering(self, t: float) -> Move | None:
        """The last block that started at or before t (s): the one running then, or the
        one whose end the carriage stood at."""
        for m in reversed(self.history):  # newest first: blocks run one after another
            if m.t0 is not None and m.t0 <= t:
                return m
        return None

    def position_at(self, t: float) -> np.ndarray:
        """Where the carriage was at time t (s), at most HISTORY blocks back (mm, deg); at
        a block's last step (its end) that step is taken."""
        m = self._covering(t)
        if m is None or (t >= m.end and m is self.history[-1]
                         and all(q is not m for q in self.queue)):
            return self.position()  # after the last block: where it is (homing sets that)
        return (m.start + m.steps_after(min(t, m.end) - m.t0) - m.slip) / self.spu

    def step_edges(self, axis: int, t_from: float, t_to: float) -> np.ndarray:
        """Times (s) of the STEP pulses of `axis` in (t_from, t_to], in order."""
        out = []
        for m in reversed(self.history):  # newest first, down to the window's start
            if m.t0 is None or m.t0 > t_to:
                continue
            if m.end <= t_from:
                break
            e = m.t0 + m.edges(axis)
            out.append(e[(e > t_from) & (e <= t_to) & (e < m.cut)])
        return np.concatenate(out[::-1]) if out else np.zeros(0)
