"""Sweep scans' run: every turn queued at once, the stream armed throughout, each waveform
placed by the table's counted steps once its burst is reported, each turn stored as soon as the
table has left it; resumed after the last turn stored.

The table reverses between turns (0 -> 360 deg and back, Z climbing on), so Marlin's planner
joins them with a stop only at each reversal, where the laser keeps firing and the waveforms
stay placed: nothing waits for the host between turns. A waveform lost on the link is a
missing point (each carries its own count), counted in the statistics; Ctrl-C stops the stage
and keeps the turns already measured.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import numpy as np

from dmdsm.marlin_patch import MachineLimits

from ..links.interfaces import Stage, StreamSensor
from ..links.sensor import CLOCK_SPACING_S, SPEC, SensorError, fit_clock
from ..links.shots import LOSS_COUNTERS
from ..links.stage import StageStopped
from ..links.transport import LinkError
from ..ranging.point import PointRanger, surface
from .common import Progress, ScanStats, approach
from .fly_executor import SYNC_WAIT_S, FlyScanError, straddles
from .plan import ScanPlan, table_speed_deg_s
from .scanfile import PHASES, ScanWriter
from .sweep import Turn, counted_steps, passes, sweep_feed_mm_min

SYNC_A = SPEC.enums["sync_input"]["a"]  # the table's STEP line's motion-sync input
STALL_S = 3.0  # no table step counted for this long (s, device clock): the sweep stops
NO_WAVEFORM_S = 30.0  # no waveform for this long (s, host clock): the sweep stops
# sensor positions (k, 3, mm) -> (near, far) beam distances (mm, (k,) each, NaN: none)
WindowOf = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]


class SweepRun:
    """One run of a sweep: the clock sync, the stream, the turns measured and not yet stored,
    the statistics."""

    def __init__(self, stage: Stage, sensor: StreamSensor, plan: ScanPlan, turns: list[Turn],
                 n_planned: int, writer: ScanWriter, ranger: PointRanger,
                 machine: MachineLimits, progress: Progress | None = None,
                 window_of: WindowOf | None = None) -> None:
        """Syncs the sensor's clock (16 exchanges); nothing moves until run(). window_of:
        sensor positions (k, 3, mm) -> the (near, far) beam distances (mm, (k,) each, NaN
        where none) where their beams cross the bounding cylinder (the ranger reads a lone
        pulse by it)."""
        self.stage, self.sensor, self.plan, self.turns = stage, sensor, plan, turns
        self.window_of = window_of
        self.n_planned, self.writer, self.ranger, self.machine = n_planned, writer, ranger, \
            machine
        self.progress = progress
        self.stats = ScanStats()
        self.t_start = time.monotonic()
        self.exchanges = sensor.clock_exchanges(16, CLOCK_SPACING_S)
        self.clock = fit_clock(self.exchanges)
        self.tick_hz = float(sensor.identity.tick_hz)
        self.quiet_ticks = SPEC.sync_quiet_ms * 1e-3 * self.tick_hz
        self.unix_minus_monotonic = time.time() - time.monotonic()
        self.spu = list(machine.steps_per_unit)
        self.a_max = machine.max_feedrate[machine.axis("A")]  # deg/s
        self.finished: list[tuple[Turn, dict]] = []  # measured turns not stored yet

    def todo(self) -> list[Turn]:
        """The turns after the last one in the file."""
        done = self.writer.data["point_index"][:self.writer.n_done]
        return self.turns[int(done.max()) + 1:] if len(done) else self.turns

    def run(self) -> ScanStats:
        """Approach, sweep every turn left, pass by pass, storing each turn as soon as the
        table has left it; Ctrl-C stops the stage and keeps the turns already measured."""
        todo = self.todo()
        if todo:
            t = todo[0]  # into the front plane along Y, then to the first turn's start
            approach(self.stage, t.y, self.plan.feed_mm_min)
            try:
                for group in passes(todo):  # the next pass: across the beam (Z and A are
                    t = group[0]            # where the last one ended), outside the cylinder
                    self.stage.move(x=t.x, y=t.y, z=t.z0, a=t.a0,
                                    feed_mm_min=self.plan.feed_mm_min)
                    self.stage.wait()
                    self.sweep(group)
            except (KeyboardInterrupt, StageStopped):
                try:
                    self.stage.stop()
                except LinkError:
                    pass
                self.store_finished()
                raise
        c = self.clock
        self.stats.clock = {"drift_ppm": round((c.ticks_per_s / self.tick_hz - 1) * 1e6, 3),
                            "residual_us": round(c.residual_s * 1e6, 3),
                            "rtt_ms": round(c.rtt_s * 1e3, 3), "exchanges": len(self.exchanges)}
        self.stats.wall_s = time.monotonic() - self.t_start
        return self.stats

    def quiet_exchange(self) -> list[tuple[float, float, float]]:
        """A clock exchange made once the table's input has been quiet for sync_quiet_ms
        after the stage stopped (M400 answered): a sweep armed sooner would merge its steps
        into the burst of the move that brought the table there."""
        first = self.sensor.clock_exchanges(1)
        ex, end = first, time.monotonic() + SYNC_WAIT_S
        while first[0][1] <= ex[0][1] < first[0][1] + self.quiet_ticks and \
                time.monotonic() < end:
            left = (first[0][1] + self.quiet_ticks - ex[0][1]) / self.clock.ticks_per_s
            time.sleep(max(left, 1e-3))
            ex = self.sensor.clock_exchanges(1)
        return ex

    def sweep(self, todo: list[Turn]) -> None:
        """Every turn left queued at once (the table reverses between turns while Z steps
        to the next ring) with the stream armed throughout; each waveform placed once the
        table's burst it belongs to is reported, each turn stored once the table has left
        it (while the next runs)."""
        sensor = self.sensor
        n = todo[0].steps(self.spu)[1]  # table steps a turn (0 -> 360 and back: all alike)
        total = n * len(todo)
        before = self.quiet_exchange()
        t0 = time.monotonic()
        waves: list = []        # taken from the stream, not placed yet
        placed: list[tuple[float, object]] = []  # (table steps done, waveform), in order
        next_turn, last_id = 0, -1
        progress_at: tuple | None = None  # (table count seen, device ticks it was seen at)
        no_wave = time.monotonic() + NO_WAVEFORM_S
        sensor.stream_start()
        try:
            # Z steps to the next ring while the table reverses (the table at rest: no
            # waveform is placed there, _place); the pass's move brought Z to the first
            z = todo[0].z0
            for t in todo:
                if t.z0 != z:
                    self.stage.move(z=t.z0, feed_mm_min=self.plan.feed_mm_min)
                speed = table_speed_deg_s(self.plan, self.a_max, t.offset)
                self.stage.move(z=t.z1, a=t.a1, feed_mm_min=sweep_feed_mm_min(t, speed))
                z = t.z1
            while next_turn < len(todo):
                new = sensor.stream_take(0.05)
                for w in new:
                    self.stats.lost += max(int(w.shot_id) - last_id - 1, 0)
                    last_id = int(w.shot_id)
                waves += new
                bursts = [(int(m.first_edge), int(m.last_edge), int(m.edges))
                          for m in list(sensor.motion_syncs)
                          if m.input == SYNC_A and m.first_edge > before[0][1]]
                made = sum(b[2] for b in bursts)
                if new:  # the table's progress, on the board's clock (whatever the load)
                    no_wave = time.monotonic() + NO_WAVEFORM_S
                    seen = (made, int(new[-1].sync_steps_a))
                    if progress_at is None or seen != progress_at[0]:
                        progress_at = (seen, int(new[-1].timestamp))
                    elif made < total and int(new[-1].timestamp) - progress_at[1] > \
                            STALL_S * self.tick_hz:
                        raise FlyScanError(
                            f"the table stopped turning: {made} of its {total} steps "
                            f"counted, none for {STALL_S:g} s (is its STEP line wired to "
                            f"the sensor's PB10, docs/firmware.md?)")
                elif time.monotonic() > no_wave:
                    raise FlyScanError(f"no waveform arrived for {NO_WAVEFORM_S:g} s during "
                                       f"the sweep: is the laser firing?")
                if made > total:
                    raise FlyScanError(f"the table made {made} steps, {total} planned: "
                                       f"something else moved it during the sweep")
                # the waveforms whose burst has been reported (all once every step is in)
                horizon = math.inf if made == total else \
                    max((b[1] for b in bursts), default=-math.inf) + self.quiet_ticks / 2
                waves, ready = self._split(waves, horizon)
                placed += self._place(ready, bursts, total)
                done_to = total if made == total and not waves else \
                    max((c for c, _ in placed), default=0.0)
                if next_turn < len(todo) and (done_to >= (next_turn + 1) * n or
                                              (made == total and not waves)):
                    self._resync()  # a turn is done: the clock line over a longer baseline
                while next_turn < len(todo) and (done_to >= (next_turn + 1) * n or
                                                 (made == total and not waves)):
                    end = (next_turn + 1) * n  # placed holds no step count <= the turn's start
                    mine = [(c - next_turn * n, w) for c, w in placed if c <= end]
                    placed = [(c, w) for c, w in placed if c > end]
                    self.finished.append((todo[next_turn], self._rows(
                        todo[next_turn], [w for _, w in mine], [c for c, _ in mine], n)))
                    next_turn += 1
                timing = dict.fromkeys(PHASES, 0.0)
                timing["acquire"] = time.monotonic() - t0
                if self.finished and self.store_finished(timing):
                    t0 = time.monotonic()
        finally:
            rest, change = sensor.stream_stop()
            self.stats.skipped += change.get("triggers_skipped", 0)
            if any(change[k] for k in LOSS_COUNTERS):
                self.stats.lost += sum(change[k] for k in LOSS_COUNTERS)
        self.exchanges += before
        self._resync()

    def _resync(self) -> None:
        """One more clock_sync exchange and the clock line refitted (the last 400)."""
        try:
            self.exchanges = (self.exchanges + self.sensor.clock_exchanges(1))[-400:]
        except SensorError:
            return  # a reply lost: the line stays as it was
        self.clock = fit_clock(self.exchanges)

    def _split(self, waves: list, horizon: float) -> tuple[list, list]:
        """(waveforms whose last shot is after the horizon (ticks), those before it)."""
        if not waves:
            return [], []
        period = self.tick_hz / self.plan.laser_hz
        ends = np.array([float(w.timestamp) + (int(w.n_average) - 1) * period for w in waves])
        k = int(np.searchsorted(ends, horizon, side="right"))
        return waves[k:], waves[:k]

    def _place(self, ready: list, bursts: list, total: int) -> list[tuple[float, object]]:
        """(table steps done, waveform) of the waveforms on the move; the others (at rest
        before or after it or between turns, where Z steps to the next ring, or straddling a
        burst's start) left out."""
        if not ready:
            return []
        ts = np.array([w.timestamp for w in ready], dtype=np.int64)
        n_avg = int(ready[0].n_average)
        done = counted_steps(ts, np.array([w.sync_steps_a for w in ready]), n_avg,
                             self.tick_hz / self.plan.laser_hz, bursts, self.quiet_ticks,
                             at_rest=False)
        ok = np.isfinite(done) & (done > 0) & (done < total)
        return [(float(done[i]), ready[i]) for i in np.flatnonzero(ok)]

    def _rows(self, turn: Turn, waves: list, steps: list[float], n: int) -> dict:
        """A turn's waveforms and where each was (Z and the table from its share of the
        turn's steps)."""
        f = np.asarray(steps, float) / n
        ts = np.array([w.timestamp for w in waves], dtype=np.int64)
        return {"samples": np.stack([w.samples.astype(np.uint16) for w in waves])
                if waves else np.zeros((0, 0), np.uint16),
                "z": turn.z0 + f * (turn.z1 - turn.z0),
                "theta": turn.a0 + f * (turn.a1 - turn.a0),
                "timestamp": ts, "host_t": self.clock.to_host_s(ts),
                "trigger_phase": np.array([w.trigger_phase for w in waves]),
                "n_average": np.array([w.n_average for w in waves])}

    def store_finished(self, timing: dict | None = None) -> bool:
        """Range and append the measured turns waiting, in order; True if any was."""
        stored = False
        while self.finished:
            turn, rows = self.finished.pop(0)
            n = len(rows["z"])
            if not n:
                continue  # a turn with no waveform placed on it: nothing to store
            t = dict(timing or dict.fromkeys(PHASES, 0.0))
            t2 = time.monotonic()
            values = _range(rows, turn, self.ranger, 1, self.unix_minus_monotonic, self.plan,
                            self.window_of)
            t["ranging"] = time.monotonic() - t2
            values["phase_time_s"] = np.tile([t[k] / n for k in PHASES], (n, 1))
            self.stats.store(lambda r=rows, v=values: self.writer.append_many(r["samples"], **v),
                             n, t, self.writer, self.n_planned, self.progress)
            stored = True
        return stored


def _range(rows: dict, turn: Turn, ranger: PointRanger, attempts: int,
           unix_minus_monotonic: float, plan: ScanPlan,
           window_of: WindowOf | None = None) -> dict:
    """Distances and the file's per-row values of a kept turn; a lone pulse is read by the
    window where its own beam crosses the bounding cylinder (the first look's rule,
    host/scan/first_look.py), at the height of its shot (were Z to climb during a turn, a
    dipping beam's far end would move with it: ~15 mm over a 2 mm climb on a wide object,
    and an OA pulse from beyond a window taken at the turn's start, read as a US echo at
    half its distance, looked certain); else it continues the surface of the waveform
    before it (the object turns under the beam, never jumps)."""
    n = len(rows["z"])
    out: dict[str, list] = {k: [] for k in ("distance_oa_mm", "distance_us_mm", "snr_oa_db",
                                            "snr_us_db")}
    pos = np.column_stack([np.full(n, turn.x), np.full(n, turn.y), rows["z"]])
    near, far = window_of(pos) if window_of is not None else (np.full(n, np.nan),) * 2
    previous = None
    for i in range(n):
        window = (float(near[i]), float(far[i])) if np.isfinite([near[i], far[i]]).all() \
            else None
        r = ranger(rows["samples"][i], int(rows["trigger_phase"][i]), 0, previous, window)
        previous = surface(r)
        for m in ("oa", "us"):
            d, snr = r.get(m, (np.nan, 0.0))
            out[f"distance_{m}_mm"].append(d)
            out[f"snr_{m}_db"].append(snr)
    arc = np.radians(rows["theta"]) * plan.radius_mm  # along the bounding cylinder (mm)
    for m in ("oa", "us"):  # an average across a depth edge belongs to neither surface
        d = np.asarray(out[f"distance_{m}_mm"], dtype=float)
        out[f"distance_{m}_mm"] = np.where(straddles(d, arc, 3 * plan.step_mm), np.nan, d)
    return {"stage_position_mm": pos, "theta_deg": rows["theta"],
            "level": np.full(n, turn.index), "column": np.arange(n),
            "angle_index": np.zeros(n, int), "received": np.ones(n, bool),
            "attempts": np.full(n, attempts), "n_average": rows["n_average"],
            "timestamp": rows["timestamp"], "trigger_phase": rows["trigger_phase"],
            **{k: np.asarray(v) for k, v in out.items()},
            "host_time": rows["host_t"] + unix_minus_monotonic,
            "point_index": np.full(n, turn.index)}


def run_sweep_scan(stage: Stage, sensor: StreamSensor, plan: ScanPlan, turns: list[Turn],
                   n_planned: int, writer: ScanWriter, ranger: PointRanger,
                   machine: MachineLimits, progress: Progress | None = None,
                   window_of: WindowOf | None = None) -> ScanStats:
    """Measure the turns after the last one in the file; returns what this run did
    (progress: points in the file, n_planned, phase times s, after each stored turn;
    window_of: where the beams of sensors at given positions cross the bounding cylinder,
    for lone pulses)."""
    return SweepRun(stage, sensor, plan, turns, n_planned, writer, ranger, machine,
                    progress, window_of).run()
