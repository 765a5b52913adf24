"""Placing shots by one input's counted steps across the bursts one slow-starting move may be
reported as (host/scan/sweep.py), against a model of the board's counting."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dmdsm.host.scan.sweep import counted_steps, place_on_move

QUIET = 20_000  # ticks (sync_quiet_ms at 1 MHz ticks, for the model)
PERIOD = 1_000  # ticks between laser shots


def board_counts(edges: np.ndarray, shots: np.ndarray) -> tuple[np.ndarray, list]:
    """What the board reports: per shot, the edges of the burst open then made up to the
    shot (0 with none open); and the bursts (first, last, edges), a gap >= QUIET ending one."""
    cut = np.nonzero(np.diff(edges) >= QUIET)[0] + 1
    groups = np.split(edges, cut) if len(edges) else []
    bursts = [(int(g[0]), int(g[-1]), len(g)) for g in groups]
    counts = np.zeros(len(shots), int)
    for i, t in enumerate(shots):
        for g in groups:
            if g[0] <= t < g[-1] + QUIET:
                counts[i] = int(np.sum(g <= t))
    return counts, bursts


@st.composite
def edge_trains(draw):
    """A few runs of steps, some apart by more than QUIET (a slow start splits a move)."""
    t, edges = 5_000, []
    for _ in range(draw(st.integers(1, 4))):
        n = draw(st.integers(1, 60))
        gap = draw(st.integers(300, 3_000))
        edges += [t + gap * i for i in range(n)]
        t = edges[-1] + draw(st.sampled_from([2_000, 15_000, 21_000, 60_000]))
    return np.array(edges, np.int64)


@settings(max_examples=200, deadline=None)
@given(edges=edge_trains(), n_avg=st.sampled_from([1, 4, 12]))
def test_counted_steps_are_the_steps_made_whatever_the_bursts(edges, n_avg):
    shots = np.arange(0, int(edges[-1]) + 3 * QUIET, PERIOD)
    counts, bursts = board_counts(edges, shots)
    n = len(shots) // n_avg
    ts = shots[:n * n_avg:n_avg]
    sums = counts[:n * n_avg].reshape(n, n_avg).sum(axis=1)
    got = counted_steps(ts, sums, n_avg, PERIOD, bursts, QUIET)
    made = np.array([np.sum(edges <= t) for t in shots[:n * n_avg]]).reshape(n, n_avg)
    want = made.mean(axis=1)
    ok = np.isfinite(got)
    assert np.allclose(got[ok], want[ok])
    # every waveform whose shots lie inside one burst, or all between two (the axis at
    # rest), is placed
    starts = [f for f, _, _ in bursts] + [np.inf]
    for i in range(n):
        lo, hi = ts[i], ts[i] + (n_avg - 1) * PERIOD
        if any(f <= lo and hi <= la for f, la, _ in bursts) or \
                any(la <= lo and hi < nxt for (_, la, _), nxt in zip(bursts, starts[1:])):
            assert ok[i], (i, lo, hi, bursts)
    # a sweep's (at_rest=False): the same counts, but none placed at rest between bursts
    # (Z steps to the next ring there), only within one or before the first
    moving = counted_steps(ts, sums, n_avg, PERIOD, bursts, QUIET, at_rest=False)
    placed = np.isfinite(moving)
    assert np.array_equal(moving[placed], got[placed]) and not np.any(placed & ~ok)
    for i in np.flatnonzero(placed):
        lo, hi = ts[i], ts[i] + (n_avg - 1) * PERIOD
        assert hi < bursts[0][0] or any(f <= lo and hi <= la + QUIET / 2
                                        for f, la, _ in bursts), (i, lo, hi, bursts)


def test_place_on_move_puts_every_axis_at_its_share():
    start, delta = np.array([200.0, 300.0, 20.0, 10.0]), np.array([2.0, 0.0, 1.5, 300.0])
    p = place_on_move(start, delta, np.array([0.0, 1333.5, 2667.0]), 2667)
    assert np.allclose(p[0], start) and np.allclose(p[2], start + delta)
    assert np.allclose(p[1], start + delta / 2)


def test_a_waveform_with_steps_but_no_burst_reported_is_not_placed():
    got = counted_steps(np.array([0, 100_000]), np.array([0, 5]), 1, PERIOD, [], QUIET)
    assert got[0] == 0 and np.isnan(got[1])


def test_a_sweeps_rings_slice_the_band_reverse_the_table_and_aim_at_the_axis():
    from dmdsm.host.scan.plan import ScanPlan, plan_for_size
    from dmdsm.host.scan.sweep import sweep_feed_mm_min, sweep_points, sweep_turns
    from dmdsm.marlin_patch import load_machine

    v = np.array([0.05, 0.99, 0.0])  # a level beam (a dipping one: below)
    X_R = np.array([200.0, 260.0, 30.0])
    plan = ScanPlan("can", radius_mm=34.0, levels_mm=[4.5, 6.5, 8.5, 10.5, 12.5], step_mm=2.0,
                    average=12, mode="sweep")
    plan.validate()
    turns = sweep_turns(plan, v, X_R)
    assert len(turns) == 4
    assert [(t.a0, t.a1) for t in turns] == [(0.0, 360.0), (360.0, 0.0)] * 2
    # flat rings at the middles of four 2 mm slices of the band: every height within 1 mm
    # of one (a helix that reverses leaves two turns 4 mm apart where it reverses)
    assert all(t.z0 == t.z1 and t.pitch == 2.0 for t in turns)
    assert [t.z0 - X_R[2] for t in turns] == pytest.approx([5.5, 7.5, 9.5, 11.5])
    # the beam from the sensor passes through the table axis, standoff_mm outside the
    # bounding cylinder
    S = np.array([turns[0].x, turns[0].y])
    u = v[:2] / np.linalg.norm(v[:2])
    off = X_R[:2] - S
    assert abs(u[0] * off[1] - u[1] * off[0]) < 1e-9
    assert np.linalg.norm(off) == pytest.approx(plan.radius_mm + plan.standoff_mm)
    # a ring at 90 deg/s: F is the table's speed (deg/min)
    assert sweep_feed_mm_min(turns[0], 90.0) == 90.0 * 60.0
    pts = sweep_points(plan, turns, 90.0)
    assert len(pts) == plan.n_points() == 4 * 333
    m = load_machine()
    assert plan_for_size("can", (66, 66, 122), True, mode="sweep").mode == "sweep"
    one = ScanPlan("can", radius_mm=34.0, levels_mm=[20.0], mode="sweep")
    (flat,) = sweep_turns(one, v, X_R)
    assert flat.z0 == flat.z1 and sweep_feed_mm_min(flat, 90.0) == 90.0 * 60.0
    assert m.max_feedrate[m.axis("A")] == 90
    # a beam dipping 0.02 (mm a mm) meets the cylinder's surface 0.16 mm below the sensor and
    # the axis 0.84 mm below: the rings' slices start 0.16 mm higher and end 0.84 mm higher,
    # so every surface between them is met over the whole band (here one more ring)
    dip = np.array([0.05, 0.99, -0.02])
    rise = dip[2] / np.linalg.norm(dip)
    turns = sweep_turns(plan, dip, X_R)
    bottom, top = turns[0].z0 - turns[0].pitch / 2, turns[-1].z1 + turns[-1].pitch / 2
    assert bottom == pytest.approx(X_R[2] + 4.5 - rise * plan.standoff_mm)
    assert top == pytest.approx(X_R[2] + 12.5 - rise * (plan.standoff_mm + 34.0))
    assert len(turns) == 5 and all(0 < t.pitch <= 2.0 for t in turns)
    assert np.allclose(np.diff([t.z0 for t in turns]), turns[0].pitch)
    for S_z in (bottom, top):  # the heights the beam meets at the two depths
        for d in (plan.standoff_mm, plan.standoff_mm + 34.0):
            h = S_z - X_R[2] + rise * d
            assert (h <= 4.5 + 1e-9) if S_z == bottom else (h >= 12.5 - 1e-9)


def test_a_sweep_in_passes_goes_up_down_and_up_offset_across_the_beam_outside_the_cylinder():
    """offsets_mm: one pass per offset; the second descends where the first ended, the
    table's direction alternating on through the passes (A within one revolution); the
    stage's path (turn ends and the moves across the beam) never inside the bounding
    cylinder, and the beam of each pass the offset from the axis."""
    from dmdsm.host.scan.plan import ScanPlan
    from dmdsm.host.scan.session import sweep_path
    from dmdsm.host.scan.sweep import passes, sweep_turns

    v = np.array([0.05, 0.99, 0.0])
    X_R = np.array([200.0, 260.0, 30.0])
    plan = ScanPlan("box", radius_mm=30.0, levels_mm=[4.5, 8.5], step_mm=2.0, average=12,
                    mode="sweep", offsets_mm=[0.0, 10.0, -10.0])
    plan.validate()
    turns = sweep_turns(plan, v, X_R)
    groups = passes(turns)
    assert [len(g) for g in groups] == [2, 2, 2] and [t.index for t in turns] == list(range(6))
    assert [t.z0 - X_R[2] for t in turns] == pytest.approx([5.5, 7.5, 7.5, 5.5, 5.5, 7.5])
    assert [(t.a0, t.a1) for t in turns] == [(0.0, 360.0), (360.0, 0.0)] * 3
    assert all(a.a1 == b.a0 for a, b in zip(turns, turns[1:]))
    u = v[:2] / np.linalg.norm(v[:2])
    for g, d in zip(groups, plan.offsets_mm):
        rel = X_R[:2] - np.array([g[0].x, g[0].y])
        assert u[0] * rel[1] - u[1] * rel[0] == pytest.approx(-d)  # the beam d off the axis
        assert rel @ u == pytest.approx(plan.radius_mm + plan.standoff_mm)
    targets, labels = sweep_path(turns)
    assert labels.count("turn 2's start") == 1 and labels.count("turn 4's start") == 1
    # each straight move between two targets stays outside the cylinder: its points all
    # lie radius + standoff along the beam's direction from the axis
    along = [(X_R[:2] - t[:2]) @ u for t in targets]
    assert np.allclose(along, plan.radius_mm + plan.standoff_mm)
