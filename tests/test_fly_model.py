"""Fly scanning's pure part against the emulator's Marlin planner: the host's trajectory model
places a shot where the steppers were, and the swept path is checked with its ramps (the fly
executor's own tests: tests/test_fly_executor.py)."""

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from dmdsm.host.links.safety import UnsafeMove
from dmdsm.host.scan.fly import LineMotion, at_line_speed, counted_x, place_shots, ramp_mm
from dmdsm.host.scan.plan import PlanError, ScanPlan
from dmdsm.host.scan.session import checked_points
from dmdsm.marlin_patch import load_machine
from dmdsm.sim.boards.stage.motion import Planner
from dmdsm.sim.physics.scene import TABLE_I_N, TABLE_I_V, TABLE_I_XR

M = load_machine()
X = M.axis("X")
SPU = M.steps_per_unit[X]
ACCEL = min(M.default_acceleration, M.max_acceleration[X])


def emulated(x0: float, x1: float, v: float):
    """The emulator's planner running one X move from rest; (planner, its block)."""
    p = Planner(M)
    start = p.to_steps([x0, 0, 0, 0])
    p.steps = start.copy()
    block = p.add(0.0, start, p.to_steps([x1, 0, 0, 0]), v)
    p.update(10.0)
    return p, block


@settings(max_examples=60, deadline=None)
@given(x0=st.floats(0, 200), length=st.floats(2, 200), v=st.floats(5, 200),
       back=st.booleans(), frac=st.lists(st.floats(0, 1), min_size=5, max_size=20))
@example(0.0, 50.0, 5.0, False, [0.0, 1.0])  # the last step, at the block's end, still running
def test_the_host_model_puts_each_instant_within_a_step_of_the_emulated_marlin(x0, length, v,
                                                                             back, frac):
    x1 = x0 - length if back else x0 + length
    p, block = emulated(x0, x1, v)
    model = LineMotion(x0, x1, v, ACCEL, SPU)
    edges = p.step_edges(X, -1.0, 100.0)
    assert len(edges) == model.n  # one STEP pulse per step
    first = edges[0]
    assert model.last_step_s == pytest.approx(edges[-1] - first, abs=1e-6)
    t = np.asarray(frac) * (edges[-1] - first)
    truth = np.array([p.position_at(first + ti)[X] for ti in t])
    # the steppers hold whole steps; the model is their mean: within half a step, plus
    # rounding of the inverse at a step's very edge
    assert np.all(np.abs(model.x_at(t) - truth) <= 0.5 / SPU + 1e-6)


def test_the_emulated_planner_keeps_speed_through_collinear_blocks_and_stops_at_a_reversal():
    p = Planner(M)
    z = p.to_steps([100, 100, 10, 0])
    p.steps = z.copy()
    moves = [p.add(0.0, p.to_steps([100 + 20 * i, 100, 10, 0]),
                   p.to_steps([120 + 20 * i, 100, 10, 0]), 100.0) for i in range(3)]
    assert moves[0].exit == pytest.approx(moves[1].entry) and moves[1].entry > 50
    one = Planner(M)
    single = one.add(0.0, z, one.to_steps([160, 100, 10, 0]), 100.0)
    total = sum(m.duration for m in moves)
    assert total == pytest.approx(single.duration, rel=0.02)  # no stop between them
    back = p.add(0.0, p.to_steps([160, 100, 10, 0]), p.to_steps([150, 100, 10, 0]), 100.0)
    # a reversal goes through Marlin's slowest: one step's average speed from rest
    stop = np.sqrt(0.5 * ACCEL / SPU)
    assert back.entry == pytest.approx(stop) and moves[-1].exit == pytest.approx(stop)


def test_a_right_angle_corner_runs_at_the_junction_deviation_speed():
    p = Planner(M)
    a = p.add(0.0, p.to_steps([100, 100, 10, 0]), p.to_steps([150, 100, 10, 0]), 100.0)
    b = p.add(0.0, p.to_steps([150, 100, 10, 0]), p.to_steps([150, 150, 10, 0]), 100.0)
    s = np.sqrt(0.5 * (1 - 0.0))  # sin(theta/2) of a 90 degree turn
    want = np.sqrt(ACCEL * M.junction_deviation_mm * s / (1 - s))
    assert b.entry == pytest.approx(want, rel=1e-6) and a.exit == pytest.approx(want, rel=1e-6)


def test_the_first_block_after_idle_waits_unless_three_are_queued():
    p = Planner(M)
    z = np.zeros(4, np.int64)
    m = p.add(1.0, z, p.to_steps([10, 0, 0, 0]), 50.0)
    p.update(1.099)
    assert m.t0 is None
    p.update(1.2)
    assert m.t0 == pytest.approx(1.1)
    q = Planner(M)
    blocks = [q.add(2.0 + 0.01 * i, q.to_steps([10 * i, 0, 0, 0]),
                    q.to_steps([10 * i + 10, 0, 0, 0]), 50.0) for i in range(3)]
    q.update(2.03)
    assert blocks[0].t0 == pytest.approx(2.02)  # delivered when the third arrived


def test_a_shallow_corner_after_a_sub_millimetre_block_runs_at_the_arcs_speed():
    """JD_HANDLE_SMALL_SEGMENTS (on in the Chiron configuration): a block under 1 mm that
    turns by less than 45 degrees is taken as part of an arc, v^2 <= length x a / turn
    (Marlin's turn estimate is within 0.033 rad); from 1 mm on, junction deviation alone."""
    def corner(length_mm: float) -> tuple[float, float]:
        """(the junction's speed limit mm/s, the turn rad between the blocks' steps)."""
        p = Planner(M)
        p.steps = p.to_steps([100, 100, 10, 0])
        p.add(0.0, p.steps.copy(), p.to_steps([150, 100, 10, 0]), 150.0)
        turn = np.radians(5.0)
        end = np.array([150 + length_mm * np.cos(turn), 100 + length_mm * np.sin(turn), 10, 0])
        b = p.add(0.0, p.to_steps([150, 100, 10, 0]), p.to_steps(end), 150.0)
        return b.max_entry, float(np.arctan2(b.unit[1], b.unit[0]))  # whole steps' turn

    (short, turn_s), (long, turn_l) = corner(0.5), corner(1.5)
    ju = np.array([np.cos(turn_l) - 1, np.sin(turn_l)])  # the junction's direction
    a = min(ACCEL, *(M.max_acceleration[i] / abs(ju[i] / np.linalg.norm(ju))
                     for i in range(2)))
    s = np.cos(turn_l / 2)  # sin of half the angle between the first reversed and the second
    assert long == pytest.approx(np.sqrt(a * M.junction_deviation_mm * s / (1 - s)), rel=1e-6)
    assert 0.49 * a / (turn_s + 0.034) <= short ** 2 <= 0.51 * a / (turn_s - 0.034)
    assert short < 0.8 * long


def test_short_blocks_queued_while_few_wait_are_slowed_as_marlins_slowdown_does():
    """Marlin's SLOWDOWN (planner.cpp, min_segment_time_us 20000): with 2 to 7 blocks
    waiting, a block shorter than 20 ms at its feed is stretched by twice the shortfall over
    that count; the real Marlin under simavr took 20 ms over 0.54 mm joined at 100 mm/s where
    the emulator took 12.6 (`make check-marlin`'s differential, short arcs)."""
    p = Planner(M)
    p.steps = p.to_steps([100, 100, 10, 0])
    blocks = [p.add(0.0, p.to_steps([100 + i, 100, 10, 0]), p.to_steps([101 + i, 100, 10, 0]),
                    100.0) for i in range(10)]  # 1 mm at 100 mm/s: 10 ms, 10 short
    want = [100.0, 100.0] + [1e6 / (10000 + 20000 // k) for k in range(2, 8)] + [100.0, 100.0]
    assert [b.v for b in blocks] == pytest.approx(want, rel=1e-9)
    long = p.add(0.0, p.to_steps([110, 100, 10, 0]), p.to_steps([112.5, 100, 10, 0]), 100.0)
    assert long.v == 100.0  # 25 ms: long enough
    q = Planner(M)
    q.steps = q.to_steps([100, 100, 10, 0])
    first = [q.add(0.0, q.to_steps([100 + 5 * i, 100, 10, 0]),
                   q.to_steps([105 + 5 * i, 100, 10, 0]), 100.0) for i in range(3)]
    q.update(0.001)  # the first one runs: it is no longer waiting
    assert first[0].t0 == 0.0
    b = q.add(0.001, q.to_steps([115, 100, 10, 0]), q.to_steps([116, 100, 10, 0]), 100.0)
    assert b.v == pytest.approx(1e6 / (10000 + 20000 // 2))


def test_a_block_too_short_to_slow_down_in_decelerates_over_its_whole_length():
    """Found by the auto scan's joined moves: a short block entered faster than it could
    leave had a zero duration, so its STEP pulses all fell on one instant the sync wire
    never saw (318 X steps lost on a 200 mm line)."""
    p = Planner(M)
    p.steps = p.to_steps([100, 100, 10, 0])
    run = p.add(0.0, p.steps.copy(), p.to_steps([150, 100, 10, 0]), 167.0)
    short = p.add(0.0, p.to_steps([150, 100, 10, 0]), p.to_steps([154, 98.99, 10, 0]), 167.0)
    run.t0 = 0.0  # running: its exit is fixed at what the queue allowed then
    short.entry, short.exit = 60.5, 5.0  # the planner's worst case: no room to slow
    short.profile()
    assert short.duration > 0
    e = short.edges(X)
    assert len(e) == 320 and np.all(np.diff(e) > 0) and e[-1] <= short.duration
    v_end = (short.r2 / (short.n / short.length))  # mm/s at its last step
    assert v_end < 60.5 and v_end == pytest.approx(
        np.sqrt(max(60.5 ** 2 - 2 * short.a * short.length, 0)), rel=0.02)


def test_every_x_step_of_joined_moves_reaches_the_sync_wire():
    """The X STEP wire over a line of 26 joined moves bending in Y (an auto scan's
    follow line), the third block arriving on the very instant of a delivery: the sensor
    board is given each of the 16000 edges once."""
    from dmdsm.sim.boards.sensor.core_board import SyncWire
    from dmdsm.sim.servers.runner import SimConfig, Simulation

    sim = Simulation(SimConfig(scene="empty"))
    wire = SyncWire(sim.x_step_edges)  # as the sensor board takes them
    pl = sim.stage.planner
    pl.steps = pl.to_steps([100, 100, 20, 0])
    got: list[np.ndarray] = []
    t = 0.0
    xs = np.linspace(150, 250, 26)
    pts = [(150.0, 100.0)] + [(x, 100 + 5 * np.sin(x / 15)) for x in xs[1:]] + [(300.0, 100.0)]
    here = pl.steps.copy()
    for i, (x, y) in enumerate(pts):
        if i == 2:  # the third block arrives on a delivery's instant: it starts then
            got.append(wire.take(0.0, t))
        nxt = pl.to_steps([x, y, 20, 0])
        pl.add(t, here, nxt, 166.7)
        here = nxt
        pl.update(t)
    while t < 5.0:
        t2 = t + 0.0137
        pl.update(t2)
        got.append(wire.take(t, t2))
        t = t2
    e = np.concatenate(got)
    assert len(e) == 16000 and np.all(np.diff(e) > 0)


def test_shots_are_placed_only_when_the_measured_duration_fits_the_model():
    model = LineMotion(100.0, 180.0, 80.0, ACCEL, SPU)
    tick_hz = 240e6
    first = 10_000_000
    last = first + round(model.last_step_s * tick_hz)
    ts = first + np.arange(0, round(model.last_step_s * 1e3), 12) * 240_000
    x, cruise, scale = place_shots(model, first, last, tick_hz, ts, 12, 1e-3)
    assert scale == pytest.approx(1.0, abs=1e-8)
    c0, c1 = model.cruise_s
    assert cruise.any() and not cruise.all()
    dx = np.diff(x[cruise])
    assert np.allclose(dx, 80.0 * 12e-3, atol=0.5 / SPU)  # one waveform apart at cruise
    with pytest.raises(ValueError, match="planner model"):
        place_shots(model, first, first + round(model.last_step_s * tick_hz * 1.05), tick_hz,
                    ts, 12, 1e-3)


@given(st.floats(-50, 300), st.floats(-60, 60).filter(lambda d: abs(d) > 1),
       st.lists(st.integers(0, 4096 * 12), min_size=1, max_size=20))
def test_counted_steps_give_the_position_whatever_the_ramps(x0, length, sums):
    motion = LineMotion(x0, x0 + length, 80.0, ACCEL, SPU)
    x = counted_x(motion, np.array(sums), 12)
    start = round(x0 * SPU) / SPU  # Marlin's position is a whole number of steps
    assert np.allclose((x - start) * np.sign(length) * SPU * 12, sums, atol=1e-6)


def test_only_waveforms_moving_at_the_line_speed_count_as_cruising():
    v, period = 80.0, 1e-3
    x = np.concatenate([[0.0, 0.1, 0.4], 0.4 + 0.96 * np.arange(1, 8), [7.5, 7.6]])
    ok = at_line_speed(x, v, 12, period)
    # 0.96 mm per 12 ms at 80 mm/s: the ramp's waveforms have no neighbour that far away
    assert ok.tolist() == [False, False, True] + [True] * 7 + [False, False]


def test_a_fly_plan_too_fast_for_the_x_axis_is_refused():
    with pytest.raises(PlanError, match="above the X axis"):
        ScanPlan("b", mode="fly", step_mm=4.0, average=8).validate()  # 500 mm/s
    ScanPlan("b", mode="fly", step_mm=1.0, average=12).validate()


def test_the_fly_path_is_checked_with_its_ramps():
    cal = {"v": TABLE_I_V, "n": TABLE_I_N, "X_R": TABLE_I_XR}
    half = 405.0 - TABLE_I_XR[0]  # the last column fits the bed, its run-out does not
    step = ScanPlan("b", levels_mm=[20.0], angles_deg=[0.0], half_width_mm=half,
                    step_mm=1.0, average=12)
    checked_points(step, cal)
    fly = ScanPlan("b", levels_mm=[20.0], angles_deg=[0.0], half_width_mm=half,
                   step_mm=1.0, average=12, mode="fly")
    assert ramp_mm(1000 / 12, ACCEL, 1.0) > 5
    with pytest.raises(UnsafeMove, match="line 0's run-out end .*machine envelope"):
        checked_points(fly, cal)
