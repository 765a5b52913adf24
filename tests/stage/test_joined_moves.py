"""Joined moves on the stage under test (the emulator, or the real Marlin under simavr with
DMDSM_STAGE_FIRMWARE, as `make check-marlin` runs it): what Marlin's planner must do with moves
queued back to back, read from the STEP pins: no stop where a line goes straight on, a corner
at the junction-deviation speed, a stop at a reversal, and the time a trapezoid gives."""

import math

import numpy as np
import pytest
from differential import HOME, SPU, Group, run_group
from pin_bench import PinBench, bench_fixture

from dmdsm.marlin_patch import load_machine

MACHINE = load_machine()
ACCEL = MACHINE.default_acceleration  # mm/s^2
JD = MACHINE.junction_deviation_mm
TIME_REL = 0.015  # a sequence's time against the trapezoid's (the ISR's step periods: the
TIME_S = 0.003    # emulator within 1.5 %, the real Marlin within 0.3 % once its ends are
# taken off: its first step comes one step period of the entry rate after the move starts, its
# last one that period before the end, 2 x 8.5 ms for X; the emulator steps at the start)


def span_bounds(expected: float, a: float, steps_per_mm: float) -> tuple[float, float]:
    """Where the first-to-last step time of a rest-to-rest sequence may be: the trapezoid's
    time, less up to two step periods at Marlin's lowest rate sqrt(a/2) (steps, steps/s^2)."""
    period = 1.0 / math.sqrt(0.5 * a * steps_per_mm)
    return (expected * (1 - TIME_REL) - TIME_S - 2 * period,
            expected * (1 + TIME_REL) + TIME_S)


class Bench(PinBench):
    """The stage under test (pin_bench.PinBench) with this module's moves."""

    def __init__(self) -> None:
        super().__init__()
        self.at = HOME.copy()

    def go(self, start: tuple[float, float, float, float]) -> None:
        """Stand at start (X Y Z A), idle."""
        self.send("G1 " + " ".join(f"{a}{v:.2f}" for a, v in zip("XYZA", start)) + " F6000")
        self.send("M400")
        self.at = np.array(start, float)

    def joined(self, steps: list[tuple[float, ...]], feed: int) -> tuple[Group, object]:
        """The moves by steps (dX dY dZ dA each) from where it stands, sent line by line as
        each ok comes, then M400; returns the group and the recording of its STEP edges."""
        g = Group("test", self.at.copy())
        for i, d in enumerate(steps):
            g.add(g.end + np.array(d, float), feed if i == 0 else None)
        rec, self.n, odd = run_group([self.stage], g, self.n)
        assert not odd, odd
        self.at = g.end
        return g, rec[0]


bench = bench_fixture(Bench)


def trapezoid_s(length: float, v: float, a: float, v0: float = 0.0, v1: float = 0.0) -> float:
    """Time (s) of a move of length from speed v0 to v1, at most v, accelerating at a."""
    d_acc, d_dec = (v * v - v0 * v0) / (2 * a), (v * v - v1 * v1) / (2 * a)
    if d_acc + d_dec > length:  # no cruise: the top speed where the two ramps meet
        v = math.sqrt((2 * a * length + v0 * v0 + v1 * v1) / 2)
        d_acc, d_dec = (v * v - v0 * v0) / (2 * a), (v * v - v1 * v1) / (2 * a)
    return (v - v0) / a + (v - v1) / a + (length - d_acc - d_dec) / v


def trapezoid_speed(s: float, length: float, v: float, a: float) -> float:
    """Speed (mm/s) s into a rest-to-rest move of length at most v, accelerating at a."""
    return min(v, math.sqrt(2 * a * s), math.sqrt(2 * a * (length - s)))


def jd_speed(u0: np.ndarray, u1: np.ndarray, a: float = ACCEL) -> float:
    """Marlin's junction-deviation limit (mm/s) between unit directions u0 and u1."""
    cos_theta = -float(np.dot(u0, u1))
    sin_d2 = math.sqrt(0.5 * (1.0 - cos_theta))
    return math.sqrt(a * JD * sin_d2 / (1.0 - sin_d2))


def span(rec: object) -> tuple[float, float]:
    """First and last STEP edge of any axis (s after the first line)."""
    edges = [rec.axis_edges(a) for a in range(4)]
    return (min(float(e[0]) for e in edges if len(e)), max(float(e[-1]) for e in edges if len(e)))


def speed_at(rec: object, axis: int, t: float, half: float) -> float:
    """An axis's mean speed (mm/s, deg/s) over (t - half, t + half], from its edges."""
    e = rec.axis_edges(axis)
    return float(np.count_nonzero((e > t - half) & (e <= t + half))) / (2 * half * SPU[axis])


def test_a_line_cut_into_pieces_runs_through_as_one_move(bench):
    """A run-up of five 8 mm pieces along X at 100 mm/s: no slowing at the joins (each at
    the speed of one trapezoid over the 40 mm there), and that trapezoid's time."""
    bench.go((20.0, 100.0, 10.0, 0.0))
    g, rec = bench.joined([(8, 0, 0, 0)] * 5, 6000)
    ends = rec.block_ends(g.block_steps())
    for k, t in enumerate(ends[:-1]):
        v = trapezoid_speed(8.0 * (k + 1), 40.0, 100.0, ACCEL)
        assert speed_at(rec, 0, t, 0.002) == pytest.approx(v, rel=0.05)
    t0, t1 = span(rec)
    lo, hi = span_bounds(trapezoid_s(40.0, 100.0, ACCEL), ACCEL, SPU[0])
    assert lo < t1 - t0 < hi


def test_a_joined_multi_axis_line_keeps_the_slowest_axis_limits(bench):
    """Pieces moving X Z and A together in a straight line: Z's limits (25 mm/s, 50 mm/s^2)
    set the speed and acceleration along the path, through every join."""
    bench.go((20.0, 100.0, 10.0, 0.0))
    piece = np.array([8.0, 0.0, 4.0, 3.0])
    length = float(np.linalg.norm(piece[:3]))
    uz = piece[2] / length
    v = MACHINE.max_feedrate[2] / uz
    a = min(ACCEL, MACHINE.max_acceleration[2] / uz)
    g, rec = bench.joined([tuple(piece)] * 4, 6000)
    ends = rec.block_ends(g.block_steps())
    for k, t in enumerate(ends[:-1]):
        vk = trapezoid_speed(length * (k + 1), 4 * length, v, a)
        assert speed_at(rec, 2, t, 0.004) == pytest.approx(vk * uz, rel=0.05)
    t0, t1 = span(rec)
    lo, hi = span_bounds(trapezoid_s(4 * length, v, a), a, SPU[2] * uz)
    assert lo < t1 - t0 < hi


def test_a_corner_is_taken_at_the_junction_deviation_speed(bench):
    """X then a 20 degree turn in X Y at 100 mm/s: through the corner at the speed junction
    deviation allows (17 mm/s), and in the time of the two trapezoids that meet there."""
    bench.go((20.0, 100.0, 10.0, 0.0))
    turn = math.radians(20)
    u0, u1 = np.array([1.0, 0, 0]), np.array([math.cos(turn), math.sin(turn), 0])
    vj = jd_speed(u0, u1)
    g, rec = bench.joined([(30, 0, 0, 0), tuple(np.append(30 * u1, 0.0))], 6000)
    corner = rec.block_ends(g.block_steps())[0]
    assert step_speed(rec, 0, corner, 6, after=False) == pytest.approx(vj, rel=0.1)
    assert step_speed(rec, 0, corner, 6, after=True) == pytest.approx(vj * u1[0], rel=0.1)
    t0, t1 = span(rec)
    expected = trapezoid_s(30, 100, ACCEL, 0, vj) + trapezoid_s(30, 100, ACCEL, vj, 0)
    lo, hi = span_bounds(expected, ACCEL, SPU[0])
    assert lo < t1 - t0 < hi


def step_speed(rec: object, axis: int, t: float, n: int, after: bool) -> float:
    """An axis's speed (mm/s) over its n steps just before t, or just after."""
    e = rec.axis_edges(axis)
    e = e[e > t + 1e-9][:n] if after else e[e <= t + 1e-9][-n:]
    return (len(e) - 1) / (SPU[axis] * float(e[-1] - e[0]))


def test_a_right_angle_slows_to_a_crawl_and_a_reversal_stops(bench):
    """At a right angle junction deviation allows 3.3 mm/s, at a reversal nothing: the axis
    that stops there steps slowly around the junction (Marlin's ISR ends a deceleration a
    little fast, taking the rate of each step from the step before: its last step before the
    right angle runs at 6.6 mm/s, so the bound is 2.5 x the junction speed, against 100 mm/s
    for a planner that ignored the corner)."""
    bench.go((20.0, 100.0, 10.0, 0.0))
    vj = jd_speed(np.array([1.0, 0, 0]), np.array([0, 1.0, 0]))
    g, rec = bench.joined([(20, 0, 0, 0), (0, 20, 0, 0), (-20, 0, 0, 0), (20, 0, 0, 0)], 6000)
    ends = rec.block_ends(g.block_steps())
    x, y = rec.axis_edges(0), rec.axis_edges(1)
    last_x = x[x <= ends[0] + 1e-9][-2:]  # X's last two steps before the corner
    first_y = y[y > ends[0]][:2]
    assert 1 / (SPU[0] * np.diff(last_x)[0]) < 2.5 * vj
    assert 1 / (SPU[1] * np.diff(first_y)[0]) < 2.5 * vj
    gap = x[np.searchsorted(x, ends[2]) + 1] - x[np.searchsorted(x, ends[2]) - 1]
    assert 2 / (SPU[0] * gap) < 3.0  # mm/s over the reversal's two steps either side
