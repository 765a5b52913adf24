"""Unit tests of host/scan/fly_executor.py on in-process fakes (tests/client_fakes.py): a line
is kept only when its clock and its step count check out, a rejected line is measured again
and then refused, waveforms next to a depth edge are dropped, lines are grouped by level."""

import numpy as np
import pytest
from client_fakes import FakeSensor, FakeStage

from dmdsm.host.scan.fly import LineMotion
from dmdsm.host.scan.fly_executor import (
    RETRIES,
    FlyLine,
    FlyRun,
    FlyScanError,
    LineRejected,
    fly_lines,
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
