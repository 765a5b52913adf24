"""Fly scanning: each plan line is one constant-speed X move while the sensor streams, each
waveform placed at the position it was fired at; stored and resumed line by line.

Per line: move to the run-up start and stop (M400); wait until the sensor board's clock
shows the X STEP input quiet for sync_quiet_ms (the move's burst has ended there, so the
line's steps open a burst of their own); arm continuously; G1 through the line at the speed
that spaces the waveforms step_mm apart; M400; wait for the X STEP burst's motion_sync;
disarm. The line is kept only if every waveform arrived (no shot-id gap, no
device drop, overrun or integrity fault), exactly one X burst of the planned step count came
after the arm, its duration fits the planner model, and the waveforms' clock agrees with the
clock sync; otherwise it is measured again (at most RETRIES times). Its waveforms inside the
cruise and the planned span are ranged and written in one append, so a file never holds part
of a line: an interrupted scan resumes at the next line.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from dmdsm.marlin_patch import MachineLimits

from ..links.interfaces import Stage, StreamSensor
from ..links.sensor import CLOCK_SPACING_S, SPEC, fit_clock
from ..links.shots import LOSS_COUNTERS
from ..links.stage import StageStopped
from ..links.transport import LinkError
from ..ranging.point import PointRanger, surface
from .common import Progress, ScanStats, approach
from .fly import (
    LineMotion,
    LinePath,
    at_line_speed,
    counted_x,
    line_speed_mm_s,
    place_shots,
    ramp_mm,
)
from .plan import Point, ScanPlan
from .scanfile import PHASES, ScanWriter

SYNC_X = SPEC.enums["sync_input"]["x"]  # the X STEP line's motion-sync input

RETRIES = 3          # measurements of one line before the scan stops
SYNC_WAIT_S = 1.0    # after M400, how long the X burst's report may take
LASER_TOLERANCE = 0.02  # measured laser rate vs the plan's laser_hz
JUMP_STEPS = 3.0     # a neighbour's distance this many steps away: a depth edge (71 deg)


class FlyScanError(LinkError):
    """A fly line failed its checks RETRIES times, or the plan does not fit the hardware."""


class LineRejected(Exception):
    """This measurement of a line is not kept; str() says why."""


@dataclass
class FlyLine:
    """One raster line: its plan points (in execution order) and where it is. A line whose
    points differ in Y is a polyline (an auto scan's surface-following line): the stage
    runs it as joined G1 moves through `vertices`, X always advancing, so the counted X
    steps place every shot on it. `via`: waypoints (X, Y, Z mm, A deg) the stage passes
    before the run-up start (an auto scan's retreat around the object)."""

    index: int
    points: list[Point]
    via: list[tuple[float, float, float, float]] = field(default_factory=list)

    @property
    def x_first(self) -> float:
        """X of the first planned column (mm)."""
        return self.points[0].x

    @property
    def x_last(self) -> float:
        """X of the last planned column (mm)."""
        return self.points[-1].x

    @property
    def direction(self) -> float:
        """+1 if the line runs towards larger X."""
        return 1.0 if self.x_last >= self.x_first else -1.0

    @property
    def is_polyline(self) -> bool:
        """True if the line moves Y as well as X."""
        return len({round(p.y, 6) for p in self.points}) > 1

    @property
    def joined(self) -> bool:
        """True if the stage runs the line as joined moves (a polyline, or any line of an
        auto scan, whose lines are numbered): its run-up in pieces, so Marlin starts it at
        once (no lone-block hold) with the whole line in its queue."""
        return self.is_polyline or self.points[0].line >= 0

    def vertices(self, every: int = 1) -> list[tuple[float, float]]:
        """(X, Y) mm the line's joined moves go through, in execution order: the points of
        every `every`-th column (the columns follow_y checked the junctions of), the first
        and the last."""
        last = len(self.points) - 1
        return [(p.x, p.y) for i, p in enumerate(self.points)
                if i in (0, last) or p.column % every == 0]


def fly_lines(points: list[Point]) -> list[FlyLine]:
    """The plan's points grouped into lines (same line number, or same angle and level,
    consecutive)."""
    lines: list[FlyLine] = []
    for p in points:
        if lines and (lines[-1].points[0].angle_index, lines[-1].points[0].level,
                      lines[-1].points[0].line) == (p.angle_index, p.level, p.line):
            lines[-1].points.append(p)
        else:
            lines.append(FlyLine(len(lines), [p]))
    return lines


def fly_speed(plan: ScanPlan, machine: MachineLimits) -> tuple[float, float]:
    """(line speed mm/s as Marlin will run it, i.e. from the whole-number F in mm/min;
    acceleration mm/s^2 of an X move)."""
    f_mm_min = round(line_speed_mm_s(plan.step_mm, plan.laser_hz, plan.average) * 60)
    ax = machine.axis("X")
    accel = min(machine.default_acceleration, machine.max_acceleration[ax])
    return min(f_mm_min / 60.0, machine.max_feedrate[ax]), accel


TRANSITION_MM = 8.0  # an auto line's run-up starts with this much X over which the stage also
# moves to the line's Y and Z from where the previous line ended (no stop, no separate move)


def line_ends(line: FlyLine, plan: ScanPlan, machine: MachineLimits) -> tuple[float, float]:
    """X (mm) where the line's move starts and ends: the planned span plus the ramps (an
    auto line's also the transition's X, TRANSITION_MM)."""
    v, a = fly_speed(plan, machine)
    r = ramp_mm(v, a, plan.step_mm) + (TRANSITION_MM if line.points[0].line >= 0 else 0.0)
    return line.x_first - line.direction * r, line.x_last + line.direction * r


def joins_previous(prev: FlyLine | None, line: FlyLine, plan: ScanPlan,
                   machine: MachineLimits) -> bool:
    """True if an auto line can start from where `prev` ended (its run-out end): the same
    table angle, and that end at or beyond this line's run-up start, so X only advances
    from it. The stage then climbs to the line's level during the run-up's first
    TRANSITION_MM."""
    if prev is None or line.points[0].line < 0 or \
            prev.points[0].theta_deg != line.points[0].theta_deg:
        return False
    xs, _ = line_ends(line, plan, machine)
    _, xe_prev = line_ends(prev, plan, machine)
    return line.direction * (xs - xe_prev) >= -1e-9


VERTEX_EVERY = 3   # a polyline's vertices: every 3rd column (fewer G-code lines per second)
RUNUP_PIECE_MM = 8.0  # a polyline's run-up in pieces: Marlin starts the first block once 3
# are queued and cannot raise its exit speed after; the pieces after it are planned with
# the whole line in the queue, so the line reaches its speed before its first point


def line_path(line: FlyLine, plan: ScanPlan, machine: MachineLimits,
              start: tuple[float, float] | None = None) -> LinePath:
    """The line's XY path: run-up start, its vertices, run-out end (the run-up and the
    run-out along X at the first and last point's Y). An auto line's run-up begins with
    the transition (TRANSITION_MM of X, where Y and Z reach the line's) from `start`, the
    (X, Y) the stage stands at (None: the run-up start, at the line's Y)."""
    xs, xe = line_ends(line, plan, machine)
    y0 = line.points[0].y
    if not line.joined:  # a fly scan's line: one G1
        return LinePath(np.array([xs, xe]), np.array([y0, line.points[-1].y]))
    x_from, y_from = start if start is not None else (xs, y0)
    xt = xs + line.direction * TRANSITION_MM  # the transition ends here
    k = max(int(math.ceil(abs(line.x_first - xt) / RUNUP_PIECE_MM)), 1)
    run_up = [(x_from, y_from)] + [(xt + (line.x_first - xt) * i / k, y0) for i in range(k)]
    inner = line.vertices(VERTEX_EVERY) if line.is_polyline else [(line.x_first, y0)]
    vx = [*run_up, *inner, (xe, line.points[-1].y)]
    return LinePath(np.array([p[0] for p in vx]), np.array([p[1] for p in vx]))


def run_fly_scan(stage: Stage, sensor: StreamSensor, plan: ScanPlan, points: list[Point],
                 writer: ScanWriter, ranger: PointRanger, machine: MachineLimits,
                 progress: Progress | None = None,
                 via: dict[int, list[tuple[float, float, float, float]]] | None = None
                 ) -> ScanStats:
    """Measure the lines after the last one in the file; returns what this run did
    (progress: points in the file, planned, phase times s, after each stored line; via:
    waypoints before a line's run-up start, by line index)."""
    run = FlyRun(stage, sensor, plan, points, writer, ranger, machine, progress,
                 separate=set(via or {}))
    for i, w in (via or {}).items():
        run.lines[i].via = list(w)
    return run.run()


@dataclass
class MeasuredLine:
    """A kept measurement of a line, waiting to be ranged and stored."""

    rows: dict            # the kept waveforms and where they were (FlyRun.measure)
    line: FlyLine
    attempts: int         # measurements of the line it took
    timing: dict          # phase times (s) of the line, by PHASES


class FlyRun:
    """One run of a fly scan: the clock sync, the line measured and not yet stored, the
    statistics; each line is stored while the stage moves to the next one's run-up."""

    def __init__(self, stage: Stage, sensor: StreamSensor, plan: ScanPlan,
                 points: list[Point], writer: ScanWriter, ranger: PointRanger,
                 machine: MachineLimits, progress: Progress | None = None,
                 separate: set[int] | None = None) -> None:
        """Syncs the sensor's clock (16 exchanges); nothing moves until run(). separate:
        lines that must not start from where the previous one ended (their way there was
        checked as a move of its own)."""
        self.stage, self.sensor, self.plan, self.points = stage, sensor, plan, points
        self.separate = separate or set()
        self.at_end_of: FlyLine | None = None  # the line whose run-out end the stage is at
        self.writer, self.ranger, self.machine, self.progress = writer, ranger, machine, progress
        self.stats = ScanStats()
        self.t_start = time.monotonic()
        self.lines = fly_lines(points)
        self.exchanges: list[tuple[float, float, float]] = sensor.clock_exchanges(
            16, CLOCK_SPACING_S)  # (host s, device ticks, RTT s), the last 400 kept
        self.clock = fit_clock(self.exchanges)
        self.tick_hz = float(sensor.identity.tick_hz)
        self.unix_minus_monotonic = time.time() - time.monotonic()
        self.v, self.a = fly_speed(plan, machine)  # mm/s, mm/s^2
        self.spu = machine.steps_per_unit[machine.axis("X")]  # X steps/mm
        self.pending: MeasuredLine | None = None
        # device ticks of the stage's last X step, when known (a kept line's burst end, the
        # stage standing since); None after the executor moved it (M400: earlier than now)
        self.x_last_tick: int | None = None

    def todo(self) -> list[FlyLine]:
        """The lines after the last one in the file."""
        done = self.writer.data["point_index"][:self.writer.n_done]
        return self.lines[int(done.max()) + 1:] if len(done) else self.lines

    def run(self) -> ScanStats:
        """Approach, measure and store every line left; Ctrl-C stops the stage and keeps
        the line already measured. Returns the statistics, with the clock sync's."""
        todo = self.todo()
        if todo:  # approach: into the front plane along Y first, as the plan check assumed
            approach(self.stage, todo[0].points[0].y, self.plan.feed_mm_min)
        try:
            for line in todo:
                self.pending = self.measure_line(line)
        except (KeyboardInterrupt, StageStopped):  # stop, keep the line already measured
            if self.pending is not None:
                try:
                    self.stage.stop()
                except LinkError:
                    pass
                self.store_pending()
            raise
        self.store_pending()
        clock, tick_hz = self.clock, self.tick_hz
        self.stats.clock = {"drift_ppm": round((clock.ticks_per_s / tick_hz - 1) * 1e6, 3),
                            "drift_std_ppm": round(clock.rate_std / tick_hz * 1e6, 3),
                            "residual_us": round(clock.residual_s * 1e6, 3),
                            "rtt_ms": round(clock.rtt_s * 1e3, 3),
                            "exchanges": len(self.exchanges)}
        self.stats.wall_s = time.monotonic() - self.t_start
        return self.stats

    def store_pending(self) -> None:
        """Range and append the measured line waiting in self.pending, if any."""
        if self.pending is None:
            return
        m, self.pending = self.pending, None
        t2 = time.monotonic()
        values = _range(m.rows, m.line, self.ranger, m.attempts, self.unix_minus_monotonic,
                        JUMP_STEPS * self.plan.step_mm)
        m.timing["ranging"] = time.monotonic() - t2
        n = len(m.rows["samples"])
        values["phase_time_s"] = np.tile([m.timing[k] / n for k in PHASES], (n, 1))
        self.stats.store(lambda: self.writer.append_many(m.rows["samples"], **values), n,
                         m.timing, self.writer, len(self.points), self.progress)

    def measure_line(self, line: FlyLine) -> MeasuredLine:
        """Measure one line, up to RETRIES times, storing the pending line while the stage
        moves to this one's run-up; raises FlyScanError if no measurement is kept."""
        p0 = line.points[0]
        xs, xe = line_ends(line, self.plan, self.machine)
        prev, self.at_end_of = self.at_end_of, None
        joined = line.index not in self.separate and joins_previous(prev, line, self.plan,
                                                                    self.machine)
        reasons: list[str] = []
        attempts = 0
        while attempts < RETRIES:
            attempts += 1
            timing = dict.fromkeys(PHASES, 0.0)
            if joined and attempts == 1:  # on from the previous line's run-out end, at once
                _, x_from = line_ends(prev, self.plan, self.machine)
                start = (x_from, prev.points[-1].y)
                t1 = time.monotonic()
                try:
                    rows = self.measure(line, LineMotion(x_from, xe, self.v, self.a, self.spu),
                                        line_path(line, self.plan, self.machine, start),
                                        z_mm=p0.z)
                    self.at_end_of = line
                    return MeasuredLine(rows, line, attempts, timing)
                except LineRejected as e:
                    reasons.append(str(e))
                    self.stats.lost += 1
                    continue
                finally:
                    timing["acquire"] = time.monotonic() - t1
                    self.exchanges = self.exchanges[-400:]
                    self.clock = fit_clock(self.exchanges)
            self.x_last_tick = None  # the moves below step X at unknown device ticks
            if attempts > 1 and line.joined:  # back along the line itself (checked with
                back = line_path(line, self.plan, self.machine)  # the plan), to its start
                for bx, by in zip(back.x[-2::-1], back.y[-2::-1]):
                    self.stage.move(x=float(bx), y=float(by), feed_mm_min=self.plan.feed_mm_min)
            else:
                for wx, wy, wz, wa in line.via:  # around the object (checked with the plan)
                    self.stage.move(x=wx, y=wy, z=wz, a=wa, feed_mm_min=self.plan.feed_mm_min)
            self.stage.move(x=xs, y=p0.y, z=p0.z, a=p0.theta_deg,
                            feed_mm_min=self.plan.feed_mm_min)
            self.store_pending()  # the previous line, while the stage moves
            t0 = time.monotonic()
            self.stage.wait()
            t1 = time.monotonic()
            timing["move"] = t1 - t0
            try:
                rows = self.measure(line, LineMotion(xs, xe, self.v, self.a, self.spu),
                                    line_path(line, self.plan, self.machine))
                self.at_end_of = line
                return MeasuredLine(rows, line, attempts, timing)
            except LineRejected as e:
                reasons.append(str(e))
                self.stats.lost += 1
            finally:
                timing["acquire"] = time.monotonic() - t1
                self.exchanges = self.exchanges[-400:]  # a longer baseline: a better drift
                self.clock = fit_clock(self.exchanges)
        raise FlyScanError(f"fly line {line.index} (angle {p0.theta_deg:g} deg, level "
                           f"{p0.level}) failed {RETRIES} times: {reasons[-1]}")

    def x_quiet(self, exchange: list[tuple[float, float, float]]
                ) -> list[tuple[float, float, float]]:
        """A clock exchange (host s, device ticks, RTT s) made once the sensor board's X STEP
        input has been quiet for sync_quiet_ms since the stage's last X step, starting from
        `exchange` (made with the stage at rest). The board ends a burst only after that
        quiet time, so a line armed sooner merges its steps into the burst of the move that
        brought the stage there (one burst, begun before the arm: "got none"). The last step
        is self.x_last_tick if known, else at most the tick of `exchange` (the stage's M400
        answered before it was sent); the wait is on the board's clock, so it holds at any
        emulator speed, and it ends early (the line then checked as usual) if that clock
        goes back (a reset) or SYNC_WAIT_S passes."""
        quiet = SPEC.sync_quiet_ms * 1e-3 * self.tick_hz  # device ticks
        last = self.x_last_tick if self.x_last_tick is not None else exchange[0][1]
        end = time.monotonic() + SYNC_WAIT_S
        while last <= exchange[0][1] < last + quiet and time.monotonic() < end:
            left_s = (last + quiet - exchange[0][1]) / self.clock.ticks_per_s  # host s
            time.sleep(min(max(left_s, 1e-3), SYNC_WAIT_S))
            exchange = self.sensor.clock_exchanges(1)
        return exchange

    def measure(self, line: FlyLine, motion: LineMotion, path: LinePath | None = None,
                z_mm: float | None = None) -> dict:
        """One pass along the line (the stage at motion.x0, at rest), sweeping to motion.x1
        at motion.v (mm/s) along `path`: the kept waveforms and where they were, or
        LineRejected. A clock_sync exchange just before the arm (once the X STEP input is
        quiet: x_quiet) and one just after the disarm bracket the line in the device's
        clock (appended to self.exchanges for the drift fit). A polyline's shots are placed
        by their counted X on the path, and its timing is modelled along the path (the feed
        rate is the path's speed); no path: X alone at the line's Y."""
        if path is None:
            path = LinePath(np.array([motion.x0, motion.x1]), np.full(2, line.points[0].y))
        stage, sensor, plan, clock, v = self.stage, self.sensor, self.plan, self.clock, motion.v
        before = self.x_quiet(sensor.clock_exchanges(1))
        bursts_before = {m.burst_id for m in sensor.motion_syncs}
        self.x_last_tick = None  # the line's moves step X from here on

        def line_bursts() -> list:
            """The bursts reported since the arm that began after it (the line's own: a
            burst of the stage's earlier moves began before it, whatever its count)."""
            return [m for m in list(sensor.motion_syncs) if m.input == SYNC_X
                    and m.burst_id not in bursts_before and m.first_edge > before[0][1]]

        sensor.stream_start()
        try:
            feed = round(v * 60)
            for i, (vx, vy) in enumerate(zip(path.x[1:], path.y[1:])):  # joined by Marlin
                stage.move(x=float(vx), y=float(vy), z=z_mm if i == 0 else None,
                           feed_mm_min=feed, wait=False)
            self.store_pending()  # the previous line, while this one runs
            stage.wait()
            end = time.monotonic() + SYNC_WAIT_S
            while time.monotonic() < end:  # the burst is reported once X is quiet for 20 ms
                if any(m.edges == motion.n for m in line_bursts()):
                    break
                time.sleep(0.005)
        finally:
            waves, change = sensor.stream_stop()
            self.stats.skipped += change.get("triggers_skipped", 0)
        after = sensor.clock_exchanges(1)
        self.exchanges += before + after
        if not waves:
            raise LineRejected("no waveform arrived while the line ran")
        ids = np.array([w.shot_id for w in waves])
        if np.any(ids != np.arange(len(ids))) or any(change[k] for k in LOSS_COUNTERS):
            raise LineRejected(f"waveforms were lost (shot ids {ids[0]}..{ids[-1]} for "
                               f"{len(ids)} received; device counters {change})")
        ts = np.array([w.timestamp for w in waves], dtype=np.int64)
        host_t = clock.to_host_s(ts)
        if np.any(np.diff(ts) <= 0) or not before[0][1] <= ts[0] <= ts[-1] <= after[0][1]:
            raise LineRejected("the sensor clock jumped during the line (a board reset?): the "
                               "waveform times do not lie between the clock syncs around it")
        # the line's burst began after the arm (the exchange just before it), perhaps
        # before the first shot: a joined line's first block starts as soon as it is queued
        new = line_bursts()
        if len(new) != 1 or new[0].edges != motion.n:
            got = ", ".join(str(m.edges) for m in new) or "none"
            raise LineRejected(f"expected one X step burst of {motion.n} steps after the arm, got "
                               f"{got}: is the X STEP line wired to the sensor's sync input "
                               f"(docs/firmware.md)?")
        n_avg = int(waves[0].n_average)
        tick_hz = self.tick_hz
        # consecutive averages are n_avg shots apart, plus the shots the board skipped
        # between them (its slots all waiting for the link; each waveform carries the count)
        skipped = np.array([int(getattr(w, "triggers_skipped", 0)) for w in waves], np.int64)
        shots = n_avg + np.diff(skipped) % (1 << 32)
        period = float(np.median(np.diff(ts) / shots)) / tick_hz if len(ts) > 1 else \
            1.0 / plan.laser_hz
        if abs(period * plan.laser_hz - 1) > LASER_TOLERANCE:
            raise FlyScanError(f"the laser fires at {1 / period:.1f} Hz but the plan says "
                               f"laser_hz = {plan.laser_hz:g}: set laser_hz in the plan")
        # the model says which shots fell in the cruise (along the path: Marlin's feed rate
        # is the path's speed; the first and last X steps are at its ends); the counted
        # steps say where
        # A joined line's blocks are planned as the commands arrive, so no one-block
        # model says when it cruises: its waveforms' advance along the path does
        cruise = np.ones(len(waves), bool)
        if not line.joined:
            try:
                _, cruise, _ = place_shots(motion, int(new[0].first_edge),
                                           int(new[0].last_edge), tick_hz, ts, n_avg, period)
            except ValueError as e:
                raise LineRejected(str(e)) from None
        x = counted_x(motion, np.array([w.sync_steps for w in waves]), n_avg)
        cruise &= at_line_speed(path.s_at(x), v, n_avg, period, shots_apart=shots)
        lo = min(line.x_first, line.x_last) - plan.step_mm / 2
        hi = max(line.x_first, line.x_last) + plan.step_mm / 2
        keep = cruise & (x >= lo) & (x <= hi)
        if not keep.any():
            raise LineRejected("no waveform fell inside the line's cruise")
        self.x_last_tick = int(new[0].last_edge)  # kept: the stage stands at its end
        idx = np.nonzero(keep)[0]
        return {"samples": np.stack([waves[i].samples.astype(np.uint16) for i in idx]),
                "x": x[idx], "y": path.y_at(x[idx]), "timestamp": ts[idx],
                "host_t": host_t[idx],
                "trigger_phase": np.array([waves[i].trigger_phase for i in idx]),
                "n_average": np.array([waves[i].n_average for i in idx])}


def straddles(d_mm: np.ndarray, x_mm: np.ndarray, jump_mm: float) -> np.ndarray:
    """Waveforms whose footprint (the travel over their averaged shots) may take in two
    surfaces: a neighbour along the line with no distance, or one more than jump_mm away.
    Such an average mixes the returns of both (a block's edge and the side face behind it)
    into a distance that belongs to neither, so it is dropped, not kept with a wrong std."""
    ok = np.isfinite(d_mm)
    bad = np.zeros(len(d_mm), bool)
    for k in (1, -1):  # the previous and the next waveform
        nb = np.roll(d_mm, k)
        near = np.abs(np.roll(x_mm, k) - x_mm) < 1.5 * np.median(np.abs(np.diff(x_mm))) \
            if len(x_mm) > 1 else np.zeros(len(d_mm), bool)
        edge = ok & near & (~np.isfinite(nb) | (np.abs(nb - d_mm) > jump_mm))
        if k == 1:
            edge[0] = False
        else:
            edge[-1] = False
        bad |= edge
    return bad


def _expected(line: FlyLine, x_mm: np.ndarray) -> np.ndarray:
    """The beam distance (mm) the outline predicts at each X of an auto follow line (NaN
    elsewhere, and beside the surface)."""
    pts = sorted(line.points, key=lambda p: p.x)
    xs = np.array([p.x for p in pts])
    ex = np.array([p.expect_mm for p in pts])
    if not np.isfinite(ex).any():
        return np.full(len(x_mm), np.nan)
    near = np.abs(np.asarray(x_mm)[:, None] - xs[None, :]).argmin(axis=1)
    return np.where(np.isfinite(ex[near]), np.interp(x_mm, xs[np.isfinite(ex)],
                                                      ex[np.isfinite(ex)]), np.nan)


def _windows(line: FlyLine, x_mm: np.ndarray) -> np.ndarray:
    """(k, 2) the (near, far) beam distances (mm) where the object can be at each X of an
    auto line (Point.window_mm), NaN where unknown: between two columns the nearer near
    and the farther far of the pair (the window only widens, so the ranger's rule stays as
    strict), NaN if either is unknown."""
    pts = sorted(line.points, key=lambda p: p.x)
    xs = np.array([p.x for p in pts])
    w = np.array([p.window_mm for p in pts], float).reshape(-1, 2)
    x = np.asarray(x_mm, float)
    hi = np.clip(np.searchsorted(xs, x), 0, len(xs) - 1)
    lo = np.clip(np.searchsorted(xs, x, side="right") - 1, 0, len(xs) - 1)
    near = np.minimum(w[lo, 0], w[hi, 0])  # NaN if either is
    far = np.maximum(w[lo, 1], w[hi, 1])
    return np.column_stack([near, far])


def _range(rows: dict, line: FlyLine, ranger: PointRanger, attempts: int,
           unix_minus_monotonic: float, jump_mm: float) -> dict:
    """Distances and the file's per-row values for a kept line."""
    p0 = line.points[0]
    n = len(rows["x"])
    out: dict[str, list] = {k: [] for k in ("distance_oa_mm", "distance_us_mm", "snr_oa_db",
                                            "snr_us_db")}
    expect = _expected(line, rows["x"])
    window = _windows(line, rows["x"])
    previous = None
    for i in range(n):
        if (previous is None or not np.isfinite(previous[0])) and np.isfinite(expect[i]):
            # no neighbour yet: a lone pulse may continue the surface the outline predicts
            previous = (float(expect[i]), {"oa": -np.inf, "us": -np.inf})
        # an auto line's lone pulse: read first by where the object can be
        win = (float(window[i, 0]), float(window[i, 1])) if np.isfinite(window[i]).all() \
            else None
        r = ranger(rows["samples"][i], int(rows["trigger_phase"][i]), 0, previous, win)
        previous = surface(r)
        nan = (np.nan, 0.0)
        for m in ("oa", "us"):
            out[f"distance_{m}_mm"].append(r.get(m, nan)[0])
            out[f"snr_{m}_db"].append(r.get(m, nan)[1])
    for m in ("oa", "us"):
        d = np.asarray(out[f"distance_{m}_mm"], dtype=float)
        out[f"distance_{m}_mm"] = np.where(straddles(d, rows["x"], jump_mm), np.nan, d)
    pos = np.column_stack([rows["x"], rows["y"], np.full(n, p0.z)])
    return {"stage_position_mm": pos, "theta_deg": np.full(n, p0.theta_deg),
            "level": np.full(n, p0.level), "column": np.arange(n),
            "angle_index": np.full(n, p0.angle_index), "received": np.ones(n, bool),
            "attempts": np.full(n, attempts), "n_average": rows["n_average"],
            "timestamp": rows["timestamp"], "trigger_phase": rows["trigger_phase"],
            **{k: np.asarray(v) for k, v in out.items()},
            "host_time": rows["host_t"] + unix_minus_monotonic,
            "point_index": np.full(n, line.index)}
