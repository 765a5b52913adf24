"""The motion differential (differential.py) catches a planner that differs: the emulator with
junction deviation off, acceleration 30 % low, or a look-ahead of one block runs the same
joined moves as the stage under test (the real Marlin under simavr with DMDSM_STAGE_FIRMWARE,
as `make check-marlin` runs it, else the unchanged emulator) and falls outside the tolerance,
while the unchanged emulator stays within it."""

import dataclasses
import math
import os

import numpy as np
import pytest
from differential import HOME, Group, Stage, Tolerance, motion

ELF = os.environ.get("DMDSM_STAGE_FIRMWARE", "")


def groups() -> list[Group]:
    """An auto scan's run-up with a Z climb into its line, a line following an outline (Y a
    little per 8 mm of X), and scan lines joined by right angles and a reversal."""
    runup = Group("run-up", HOME.copy())
    runup.add(np.array([20.0, 100.0, 10.0, 0.0]), 6000)
    for dz in (0.0, 1.0, 1.5, 1.0, 0.0):
        runup.add(runup.end + np.array([8.0, 0.0, dz, 0.0]))
    runup.add(runup.end + np.array([60.0, 0.0, 0.0, 0.0]))
    line = Group("xy-line", runup.end)
    for k in range(10):
        line.add(line.end + np.array([-8.0, 0.3 * math.sin(k), 0.0, 0.0]), 9000 if k == 0 else None)
    scan = Group("back-forth", line.end)
    for dx, dy in ((40, 0), (0, 5), (-40, 0), (40, 0), (0, 5)):
        scan.add(scan.end + np.array([dx, dy, 0.0, 0.0]), 9000 if dy == 0 else None)
    return [runup, line, scan]


def no_junction_deviation(planner: object) -> None:
    """Exact stop at every join."""
    planner.jd = 0.0


def slow_acceleration(planner: object) -> None:
    """Acceleration 30 % below the configured one, on every axis."""
    planner.limits = dataclasses.replace(
        planner.limits, default_acceleration=0.7 * planner.limits.default_acceleration)
    planner.amax = 0.7 * planner.amax


def one_block_lookahead(planner: object) -> None:
    """Each block planned against the next one only (Marlin's reverse pass runs over the
    whole queue): a block may not be faster at its end than the next can stop from."""
    def replan(safe_exit_sqr: float) -> None:
        todo = [m for m in planner.queue if m.t0 is None]
        running = [m for m in planner.queue if m.t0 is not None]
        prev_exit = running[-1].exit if running else 0.0
        for i, m in enumerate(todo):
            nxt = todo[i + 1] if i + 1 < len(todo) else None
            m.exit = m.min_speed if nxt is None else min(
                nxt.max_entry, math.sqrt(nxt.min_speed ** 2 + 2 * nxt.a * nxt.length))
            m.entry = min(m.max_entry, math.sqrt(m.exit ** 2 + 2 * m.a * m.length), prev_exit)
            m.exit = min(m.exit, math.sqrt(m.entry ** 2 + 2 * m.a * m.length))
            prev_exit = m.exit
            m.initial_rate = None
            m.profile()
    planner._replan = replan


def run(perturb: object) -> list:
    """The groups on the (perturbed) emulator and the stage under test; their figures."""
    stages = [Stage(""), Stage(ELF)]
    try:
        if perturb is not None:
            perturb(stages[0].sim.stage.planner)
        return motion(stages, groups(), Tolerance(), verbose=False)
    finally:
        for s in stages:
            s.close()


def test_the_emulator_stays_within_the_tolerance_on_joined_moves():
    figs = run(None)
    assert [f.failures for f in figs] == [[], [], []]
    if not ELF:  # the emulator against itself: the same steps at the same instants
        assert all(np.all(f.block_diff == 0) and np.all(f.pos_raw == 0) for f in figs)


@pytest.mark.parametrize("perturb", [no_junction_deviation, slow_acceleration,
                                     one_block_lookahead])
def test_a_planner_that_differs_is_caught(perturb):
    figs = run(perturb)
    assert any(f.failures for f in figs), "a different planner within the tolerance"


def test_the_comparison_sees_block_times_ends_and_positions():
    """The figures a different acceleration gives: every kind of check fails, not one."""
    figs = run(slow_acceleration)
    text = " ".join(" ".join(f.failures) for f in figs)
    assert "takes" in text and "ends" in text and "apart by" in text
