"""Unit tests of host/scan/fly_executor.py on in-process fakes (tests/client_fakes.py): a line
is kept only when its clock and its step count check out, a rejected line is measured again
and then refused, waveforms next to a depth edge are dropped, lines are grouped by level."""

import time
from types import SimpleNamespace

import numpy as np
import pytest
from client_fakes import FakeSensor, FakeStage

from dmdsm.host.links.sensor import SPEC
from dmdsm.host.scan.fly import LineMotion
from dmdsm.host.scan.fly_executor import (
    RETRIES,
    FlyLine,
    FlyRun,
    FlyScanError,
    LineRejected,
    fly_lines,
    fly_speed,
    line_ends,
    straddles,
)
from dmdsm.host.scan.plan import Point, ScanPlan
from dmdsm.marlin_patch import load_machine

M = load_machine()
X = M.axis("X")
SPU = M.steps_per_unit[X]
ACCEL = min(M.default_acceleration, M.max_acceleration[X])
LINE = FlyLine(0, [Point(0, 104.0, 0, 0, 0, 0, 0, 0), Point(1, 116.0, 0, 0, 0, 0, 12, 0)])


def fly_run(motion, jump_s=0.0, edges_off=0):
    """A FlyRun of one line on the fakes; measuring needs no file and no ranger."""
    sensor, stage = FakeSensor(motion, jump_s, edges_off), FakeStage(motion)
    plan = ScanPlan("b", step_mm=1.0, average=12, mode="fly")
    return FlyRun(stage, sensor, plan, LINE.points, writer=None, ranger=None, machine=M)


@pytest.mark.parametrize("jump_s, edges_off, why", [
    (0.0, 0, None),
    (-30.0, 0, "clock jumped"),            # the board reset: its clock restarted
    (0.0, -1, "one X step burst of"),      # a step lost on the wire, or another move
])
def test_a_fly_line_is_kept_only_when_its_clock_and_its_steps_check_out(jump_s, edges_off,
                                                                        why):
    motion = LineMotion(80.0, 140.0, 83.33, ACCEL, SPU)
    run = fly_run(motion, jump_s, edges_off)
    n_exchanges = len(run.exchanges)
    if why is None:
        rows = run.measure(LINE, motion)
        assert 0 < len(rows["x"]) and np.all(np.diff(rows["x"]) > 0)
        assert rows["x"].min() >= 103.5 and rows["x"].max() <= 116.5
    else:
        with pytest.raises(LineRejected, match=why):
            run.measure(LINE, motion)
    assert len(run.exchanges) == n_exchanges + 2  # one clock sync each side of the line


def test_a_line_rejected_every_time_is_refused_after_the_retries():
    motion = LineMotion(80.0, 140.0, 83.33, ACCEL, SPU)
    run = fly_run(motion, edges_off=-1)
    with pytest.raises(FlyScanError, match=f"line 0 .*failed {RETRIES} times: expected one X"):
        run.measure_line(LINE)
    assert run.stats.lost == RETRIES and run.pending is None
    assert len(run.stage.moves) == 2 * RETRIES  # to the run-up, then through the line
    run.store_pending()  # nothing measured: nothing to store


QUIET_S = SPEC.sync_quiet_ms / 1000  # the board ends a burst after this quiet time (s)


class BurstBoard(FakeSensor):
    """The fake sensor with the board's burst rule (firmware/stm32/core/sync.c): X steps
    are one burst unless the input was quiet QUIET_S between them, a burst reported once
    quiet that long; the stage's moves step X too (`runs`). The line's first step comes
    5 ms after the arm, as a joined line's, which Marlin starts once it is queued."""

    FIRST_STEP_S = 0.005

    def __init__(self, motion):
        super().__init__(motion)
        self.runs = []  # (first, last step s, steps) of every X move, the line's included
        self.streaming = False

    @property
    def motion_syncs(self):
        """The bursts reported by now."""
        bursts = []
        for first, last, n in sorted(self.runs):
            if bursts and first - bursts[-1][1] < QUIET_S:
                bursts[-1] = (bursts[-1][0], last, bursts[-1][2] + n)
            else:
                bursts.append((first, last, n))
        now = time.monotonic()
        return [SimpleNamespace(burst_id=i, first_edge=self.ticks(f), last_edge=self.ticks(la),
                                edges=n, input=0) for i, (f, la, n) in enumerate(bursts)
                if la + QUIET_S <= now]

    @motion_syncs.setter
    def motion_syncs(self, _):
        pass  # FakeSensor's one report per stream: the runs say it here

    def stream_start(self):
        super().stream_start()
        self.streaming = True
        start = self.t0 + self.FIRST_STEP_S
        self.runs.append((start, start + self.motion.last_step_s, self.motion.n))

    def stream_stop(self):
        self.streaming = False
        return super().stream_stop()


class MovingStage(FakeStage):
    """A fake stage whose moves to a line step X (on the board's sync input) until its M400
    answers, the way there 50 ms long; the line's own moves are the board's to step."""

    def __init__(self, motion, board, x):
        super().__init__(motion)
        self.board, self.x, self.owed = board, x, 0

    def move(self, x=None, y=None, z=None, a=None, feed_mm_min=None, wait=False):
        super().move(x, y, z, a, feed_mm_min, wait)
        if x is not None and not self.board.streaming:
            self.owed += round(abs(x - self.x) * SPU)
        self.x = self.x if x is None else x

    def wait(self):
        if self.board.streaming or not self.owed:
            return super().wait()
        t = time.monotonic()
        time.sleep(0.05)
        self.board.runs.append((t, time.monotonic(), self.owed))  # its last step: now
        self.owed = 0


def test_a_line_armed_right_after_the_move_to_it_gets_an_x_burst_of_its_own():
    """The scan coverage bench's auto scan of the block ended "fly line N failed 3 times:
    expected one X step burst of K steps after the arm, got none": the line was armed and
    started as soon as the M400 of the move to its run-up start answered, within the
    board's 20 ms quiet time of that move's last X step, so both were one burst, begun
    before the arm; each retry went back along the line and merged again."""
    plan = ScanPlan("b", step_mm=1.0, average=12, mode="fly")
    xs, xe = line_ends(LINE, plan, M)
    v, a = fly_speed(plan, M)
    motion = LineMotion(xs, xe, v, a, SPU)
    board = BurstBoard(motion)
    stage = MovingStage(motion, board, x=xs - 30.0)
    run = FlyRun(stage, board, plan, LINE.points, writer=None, ranger=None, machine=M)
    m = run.measure_line(LINE)  # raised FlyScanError ("got none") before the fix
    assert m.attempts == 1 and run.stats.lost == 0 and len(m.rows["x"]) > 0
    way, line = board.motion_syncs  # the move to the line, and the line: bursts apart
    assert (way.edges, line.edges) == (round(30.0 * SPU), motion.n)
    assert (line.first_edge - way.last_edge) / 240e6 >= QUIET_S


def test_a_waveform_next_to_a_depth_edge_or_a_miss_is_dropped():
    x = np.arange(10.0)
    d = np.array([np.nan, 20.0, 20.1, 20.0, 20.1, 35.0, 35.1, 35.0, 35.1, 35.0])
    bad = straddles(d, x, 3.0)
    assert bad.tolist() == [False, True, False, False, True, True, False, False, False, False]


def test_the_plan_points_are_grouped_into_lines_of_one_angle_and_level():
    pts = [Point(i, float(i % 3), 0, 0, 0.0, lvl, i % 3, a)
           for i, (a, lvl) in enumerate([(0, 0)] * 3 + [(0, 1)] * 3 + [(1, 0)] * 3)]
    lines = fly_lines(pts)
    assert [ln.index for ln in lines] == [0, 1, 2]
    assert [[p.index for p in ln.points] for ln in lines] == [[0, 1, 2], [3, 4, 5], [6, 7, 8]]
    assert lines[0].direction == 1.0 and (lines[0].x_first, lines[0].x_last) == (0.0, 2.0)


def test_shots_the_board_skipped_on_a_line_are_counted_not_lost():
    """A board whose waveform slots all waited for the link skipped laser shots: the line
    has fewer waveforms, each placed (kept), and the run counts the shots in its summary."""
    motion = LineMotion(80.0, 140.0, 83.33, ACCEL, SPU)
    run = fly_run(motion)
    stop = run.sensor.stream_stop

    def skipping():  # every other average's 12 shots skipped: the ids stay consecutive
        waves, change = stop()
        kept = waves[::2]
        for i, w in enumerate(kept):
            w.shot_id, w.triggers_skipped = i, 12 * i  # the board's count, on each waveform
        return kept, {**change, "triggers_skipped": 12 * (len(waves) - len(kept))}

    run.sensor.stream_stop = skipping
    rows = run.measure(LINE, motion)
    full = fly_run(motion).measure(LINE, motion)  # the same line, no shot skipped
    # the waveforms left are at the line's speed (their counted advance spans the shots
    # skipped between them) and kept: about half of a line with none skipped
    assert 0.4 * len(full["x"]) <= len(rows["x"]) and run.stats.lost == 0
    assert run.stats.skipped > 0 and run.stats.skipped % 12 == 0
