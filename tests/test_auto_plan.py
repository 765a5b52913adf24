"""Auto scans' paths (issue 32), without boards: a follow line never comes nearer the outline
than the plan's standoff, X always advances, Marlin takes every junction at the line speed,
the table angles chosen see the outline within the plan's incidence, and every move of the
follow lines is checked against the outline's keep-out."""

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dmdsm.host.scan.auto import (
    beam_hits_y,
    choose_angles,
    follow_points,
    follow_y,
    incidence_cos,
)
from dmdsm.host.scan.first_look import first_look_plan
from dmdsm.host.scan.fly import LinePath, junction_speed_mm_s
from dmdsm.host.scan.fly_executor import fly_lines
from dmdsm.host.scan.outline import Outline, OutlineKeepOut
from dmdsm.host.scan.plan import ScanPlan
from dmdsm.marlin_patch import load_machine

V = np.array([0.0656, 0.9955, -0.0678]) / np.linalg.norm([0.0656, 0.9955, -0.0678])
N = np.array([-0.0007, 0.0022, 0.9999]) / np.linalg.norm([-0.0007, 0.0022, 0.9999])
X_R = np.array([235.21, 288.17, 0.0])
M = load_machine()


def box_outline(w=50.0, d=30.0, h=40.0, radius=31.0, phi_step=5.0, z_step=4.0):
    """The outline a perfect first look of a w x d box gives (radius per azimuth bin)."""
    phi = np.radians((np.arange(int(360 / phi_step)) + 0.5) * phi_step)
    r = np.minimum(w / 2 / np.maximum(np.abs(np.cos(phi)), 1e-9),
                   d / 2 / np.maximum(np.abs(np.sin(phi)), 1e-9))
    z = np.arange(0, h + 1e-9, z_step)
    return Outline(phi_step, z, np.repeat(r[:, None], len(z) - 1, axis=1), radius, h)


def bottle_outline(h=100.0, radius=36.0):
    """A round bottle: 35 mm radius up to 60 mm, a 12 mm neck above."""
    z = np.arange(0, h + 1e-9, 4.0)
    zc = (z[:-1] + z[1:]) / 2
    r = np.where(zc < 60, 35.0, 12.0)
    return Outline(5.0, z, np.tile(r, (72, 1)), radius, h)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-15, 15), min_size=5, max_size=40), st.floats(40, 170))
def test_a_follow_line_is_never_nearer_than_wanted_and_marlin_takes_it_at_speed(bumps, v):
    xs = 200.0 + 2.0 * np.arange(len(bumps))
    want = 270.0 + np.array(bumps)
    y = follow_y(xs, want, v, 350.0, M.junction_deviation_mm)
    assert np.all(y <= want + 1e-9)                     # never nearer the surface
    assert np.all(np.abs(np.diff(y)) <= 2.0 * 1.0 + 1e-9)  # slope <= 1: X advances fast
    keep = np.arange(len(xs)) % 3 == 0
    keep[[0, -1]] = True
    vx, vy = xs[keep], y[keep]
    seg = np.vstack([[1.0, 0.0], np.column_stack([np.diff(vx), np.diff(vy)]), [1.0, 0.0]])
    seg /= np.linalg.norm(seg, axis=1, keepdims=True)  # with the flat run-up and run-out
    for a, b in zip(seg[:-1], seg[1:]):
        assert junction_speed_mm_s(a, b, 350.0, M.junction_deviation_mm) >= v - 1e-6
    assert y.mean() >= want.min() - 1e-9  # never farther on the whole than the flat line


def test_a_follow_line_bends_towards_a_surface_it_cannot_follow_exactly():
    """A box face seen head on, its sides 8 mm farther: at the fly speed (167 mm/s) Marlin
    turns only ~2 deg per joined move, so the line cannot drop at the corners, but it still
    bows towards the face (the flat line stayed 8 mm off all along it)."""
    xs = 200.0 + 2.0 * np.arange(38)
    want = np.where(np.abs(xs - 237.0) < 22.0, 270.0, 262.0)
    y = follow_y(xs, want, 166.7, 350.0, M.junction_deviation_mm)
    face = np.abs(xs - 237.0) < 22.0
    assert np.all(y <= want + 1e-9)
    assert np.ptp(y) > 1.0 and np.mean(want[face] - y[face]) < 7.5
    # a gentle wave (3 mm over 75 mm) is followed within a few mm all along
    wave = 270.0 + 3.0 * np.sin((xs - 200.0) / 12.0)
    assert np.max(wave - follow_y(xs, wave, 166.7, 350.0, M.junction_deviation_mm)) < 3.0


def test_marlins_junction_speed():
    """Straight on: no limit; a right angle: sqrt(a jd sin45 / (1 - sin45)) (Marlin's
    planner.cpp formula); a reversal: stop."""
    u = np.array([1.0, 0.0])
    assert junction_speed_mm_s(u, u, 350, 0.013) > 1e3
    right = junction_speed_mm_s(u, np.array([0.0, 1.0]), 350, 0.013)
    s = math.sqrt(0.5)
    assert math.isclose(right, math.sqrt(350 * 0.013 * s / (1 - s)), rel_tol=1e-9)
    assert junction_speed_mm_s(u, -u, 350, 0.013) == 0.0


def test_the_beam_meets_the_box_face_where_it_is():
    o = box_outline()
    xs = X_R[0] + np.array([-40.0, -10.0, 0.0, 10.0, 40.0])
    y = beam_hits_y(o, 0.0, 20.0, xs, X_R[1] - 30, V, N, X_R)
    assert np.isnan(y[0]) and np.isnan(y[-1])             # beside the box
    # the front face is 15 mm in front of the axis (n tilts it by < 0.1 mm)
    np.testing.assert_allclose(y[1:4], X_R[1] - 15.0, atol=0.15)
    y90 = beam_hits_y(o, 90.0, 20.0, xs[1:4], X_R[1] - 30, V, N, X_R)
    np.testing.assert_allclose(y90, X_R[1] - 25.0, atol=0.15)  # turned: the long side's end


def test_the_angles_chosen_see_a_box_and_face_it():
    o = box_outline()
    angles, share = choose_angles(o, [0.0, 90.0, 180.0, 270.0], V, N, 45.0, 16)
    assert share == 1.0 and {0.0, 90.0, 180.0, 270.0} <= set(angles)
    c = incidence_cos(o, 0.0, V, N)
    front = np.argmin(np.abs((np.arange(72) + 0.5) * 5.0 - 270.0))
    assert c[front, 0] > 0.99        # the front face, head on
    assert c[(front + 36) % 72, 0] < 0  # the back face, facing away


def test_a_bottle_is_followed_down_its_neck_and_every_move_is_clear():
    o = bottle_outline()
    plan = ScanPlan("bottle", radius_mm=36.0, height_mm=100.0, levels_mm=[30.0, 80.0],
                    angles_deg=[0.0, 90.0], step_mm=2.0, average=12, mode="auto")
    pts = follow_points(plan, o, [0.0, 90.0], V, N, X_R, 166.0, 350.0,
                        M.junction_deviation_mm, 0)
    keep = OutlineKeepOut(o, X_R, N)
    for line in fly_lines(pts):
        p = line.points
        S = np.array([[q.x, q.y, q.z] for q in p])
        assert not keep.inside(S, p[0].theta_deg).any()
        LinePath(S[:, 0], S[:, 1])  # X advances on every segment
        # the beam meets the surface the plan's standoff away where it meets it head on
        mid = S[len(S) // 2]
        r = 35.0 if p[0].level == 0 else 12.0
        assert abs((X_R[1] - r) - mid[1] - plan.standoff_mm * V[1]) < 1.0
    neck = [q for q in pts if q.level == 1]
    assert max(q.y for q in neck) > X_R[1] - 12 - plan.standoff_mm - 1  # close to the neck


def test_the_first_look_stays_outside_the_bounding_cylinder_and_covers_the_levels():
    plan = ScanPlan("b", radius_mm=31.0, height_mm=40.0, levels_mm=[20.0], step_mm=2.0,
                    average=12, mode="auto")
    look = first_look_plan(plan)
    assert look.mode == "fly" and len(look.angles_deg) == 8
    assert look.levels_mm == [14.0, 20.0, 26.0]  # one first-look step either side
    assert look.half_width_mm == plan.radius_mm
    full = first_look_plan(ScanPlan("b", radius_mm=31.0, height_mm=40.0, mode="auto",
                                    levels_mm=[4.5, 38.5], step_mm=2.0, average=12))
    assert full.levels_mm[0] == 3.0 and full.levels_mm[-1] == 39.0 and all(
        0 < z <= 40.0 for z in full.levels_mm)


def test_holes_are_scanned_again_from_angles_that_see_them_within_the_budget():
    from dmdsm.host.scan.auto import hole_lines

    o = box_outline()
    holes = np.zeros_like(o.closed())
    # the box's +x end (azimuth about 0 deg) at the 20 mm level was never covered
    phi = (np.arange(72) + 0.5) * 5.0
    holes[(phi < 20) | (phi > 340), 4] = True
    lines = hole_lines(o, [(holes, 45.0)], [0.0, 180.0], [10.0, 20.0, 30.0], 8.0, V, N,
                       line_s=2.0, budget_s=10.0)
    # the row's centre (18 mm) is 1.5 mm from the 20 mm level's beam: the line runs at the
    # centre's own height, numbered as the 20 mm level
    assert lines and all(li == 1 and h == pytest.approx(18.0 - 8.0 * V[2], abs=1e-3)
                         for _, li, h in lines), lines
    a, _, _ = lines[0]
    # the table turns the +x end to face the sensor (which looks along +y): the end's normal
    # R(a) (1, 0, 0) = (cos a, sin a, 0) must point at it, -y: a = 270 deg, head on
    assert a == 270.0, lines
    assert hole_lines(o, [(holes, 45.0)], [0.0, 180.0], [10.0, 20.0, 30.0], 8.0, V, N,
                      line_s=2.0, budget_s=1.0) == []  # no time for one line
    assert hole_lines(o, [(np.zeros_like(holes), 45.0)], [0.0], [20.0], 8.0, V, N, 2.0,
                      100.0) == []  # nothing to do


def test_a_hole_between_sparse_levels_is_scanned_at_its_own_height_none_beyond_them():
    """A hole row no plan level's beam meets within half the spacing is scanned again at the
    height where the beam meets its centre (a line at a level 3 mm off would leave the hole's
    centre uncovered); a row above the highest level is left as it is, reported."""
    from dmdsm.host.scan.auto import hole_lines

    o = box_outline()  # rows 4 mm tall: centres 2, 6, ..., 38 mm
    holes = np.zeros_like(o.closed())
    holes[:, 1] = True   # 4-8 mm, between the levels 4.5 and 30
    holes[:, 9] = True   # 36-40 mm, above the highest level
    lines = hole_lines(o, [(holes, 45.0)], [0.0, 180.0], [4.5, 30.0], 8.0, V, N,
                       line_s=2.0, budget_s=100.0)
    beam = 8.0 * V[2]  # the beam meets the surface this far above the sensor's height
    assert lines and {round(h + beam, 3) for _, _, h in lines} == {6.0}, lines
    assert {li for _, li, _ in lines} == {0}  # numbered as the nearest level, 4.5 mm
    # a level within 1 mm of the centre is used as it is
    near = hole_lines(o, [(holes, 45.0)], [0.0, 180.0], [6.5, 30.0], 8.0, V, N, 2.0, 100.0)
    assert near and {(li, h) for _, li, h in near} == {(0, 6.5)}


def test_a_us_hole_is_scanned_from_where_the_beam_meets_it_head_on():
    """US echoes come back within about 15 deg of head on: a place with OA points and no US
    echo is a hole of a "both" plan, and the line chosen for it meets it within 15 deg; an
    OA hole at 45 deg of the same line is met too, and one line serves both when it can."""
    from dmdsm.host.scan.auto import hole_lines, incidence_cos

    o = box_outline()
    phi = (np.arange(72) + 0.5) * 5.0
    us = np.zeros_like(o.closed())
    us[(phi < 10) | (phi > 350), 4] = True  # the +x end's middle: no US echo there yet
    oa = np.zeros_like(us)
    lines = hole_lines(o, [(oa, 45.0), (us, 15.0)], [0.0, 180.0], [10.0, 20.0, 30.0], 8.0,
                       V, N, line_s=2.0, budget_s=4.0)
    assert lines, lines
    for a, _, _ in lines:  # each line meets the US holes it was chosen for within 15 deg
        c = incidence_cos(o, a, V, N)[:, 4]
        assert (c[us[:, 4]] >= np.cos(np.radians(15.0))).any(), (a, lines)
    assert lines[0][0] == 270.0  # head on
    # with the head-on angle taken already, no line is left that meets them within 10 deg,
    # where 45 deg (OA's) takes an angle beside it
    levels = [10.0, 20.0, 30.0]
    assert hole_lines(o, [(us, 10.0)], [0.0, 180.0, 270.0], levels, 8.0, V, N, 2.0,
                      4.0) == []
    assert hole_lines(o, [(us, 45.0)], [0.0, 180.0, 270.0], levels, 8.0, V, N, 2.0,
                      4.0) != []


def test_a_line_no_checked_move_reaches_is_left_out_and_said_not_the_scan():
    """A line (or the way to it) the checks refuse is left out with its one-line reason;
    the lines after it are numbered on without a gap (resuming counts on that)."""
    from dmdsm.host.links.safety import KeepOut
    from dmdsm.host.scan.auto_executor import _safe_lines
    from dmdsm.host.scan.first_look import first_look_points

    o = bottle_outline()
    plan = ScanPlan("bottle", radius_mm=36.0, height_mm=100.0, levels_mm=[30.0, 80.0],
                    angles_deg=[0.0, 90.0], step_mm=2.0, average=24, mode="auto")
    look = first_look_points(plan, V, X_R)
    n_look = len(fly_lines(look))
    pts = follow_points(plan, o, [0.0, 90.0], V, N, X_R, 83.3, 350.0,
                        M.junction_deviation_mm, n_look)
    for i, p in enumerate(pts):
        p.index = len(look) + i
    shelf = KeepOut(X_R + 75.0 * N, N, 80.0, 10.0)  # something in the way at 80 mm
    here = (X_R[0] - 80.0, look[0].y, 20.0, 0.0)
    kept, via, skipped = _safe_lines(look, pts, here, plan, M,
                                     [OutlineKeepOut(o, X_R, N), shelf])
    assert len(skipped) == 2 and all("\n" not in s and "refused" in s for s in skipped)
    assert {p.level for p in kept} == {0}  # the 80 mm lines are gone, the 30 mm ones kept
    lines = fly_lines(look + kept)[n_look:]
    assert [ln.points[0].line for ln in lines] == list(range(n_look, n_look + len(lines)))
    assert [p.index for p in kept] == list(range(len(look), len(look) + len(kept)))
    assert lines[0].index in via  # the first follow line: a move of its own from `here`


def test_a_first_look_of_lone_pulses_names_the_modality_not_the_objects_place():
    """A "both" plan's first look of steel (no OA pulse) hears echoes it cannot read: the
    error says to set the modality; a first look that heard nothing asks where the object
    is; a one-modality plan never gets the modality advice."""
    from dmdsm.host.scan.first_look import no_surface_reason

    n = 400
    nan = np.full(n, np.nan)
    quiet = np.full(n, 9.0)
    loud = quiet.copy()
    loud[100:160] = 35.0  # 60 waveforms with a lone pulse, none ranged
    msg = no_surface_reason(loud, quiet, nan, nan, "both")
    assert 'modality = "us"' in msg and "60 of its 400 waveforms" in msg, msg
    assert "\n" not in msg and len(msg) < 400
    for snr_oa, snr_us, mod in ((quiet, quiet, "both"), (loud, quiet, "us"),
                                (quiet, np.where(np.arange(n) < 5, 35.0, 9.0), "both")):
        msg = no_surface_reason(snr_oa, snr_us, nan, nan, mod)
        assert "modality" not in msg and "on the table" in msg, msg
    # a first look that saw a few points (a steel can's flanks) but more lone pulses: the
    # scan goes on with a note that says the same; none where it ranged more than that
    from dmdsm.host.scan.first_look import one_modality_note

    few = nan.copy()
    few[:20] = 30.0
    assert 'modality = "us"' in one_modality_note(loud, quiet, nan, few, "both")
    many = nan.copy()
    many[:200] = 30.0
    assert one_modality_note(loud, quiet, many, many, "both") is None
    assert one_modality_note(loud, quiet, nan, few, "us") is None


def test_a_us_only_plan_follows_from_the_first_looks_distance():
    """US answers only head on, so the outline of a US-only first look may miss a handle
    beside what it saw (a steel mug's, in the emulator): its follow lines keep the first
    look's distance (standoff outside the bounding cylinder) at every azimuth; a plan that
    reads OA keeps out of the outline grown by its margin."""
    from dmdsm.host.scan.auto import follow_keep_out

    o = box_outline()
    X_R = np.array([235.0, 266.0, 0.0])
    both = ScanPlan("b", radius_mm=31.0, height_mm=40.0, levels_mm=[20.0], mode="auto")
    us = replace(both, modality="us")
    phi = np.radians(np.arange(0.0, 360.0, 15.0))

    def at(r):  # stage positions at radius r (mm) about the axis, 20 mm up
        return X_R + np.column_stack([r * np.cos(phi), r * np.sin(phi), np.full(len(phi), 20.0)])

    k_us, k_both = follow_keep_out(us, o, X_R, N), follow_keep_out(both, o, X_R, N)
    assert k_us.inside(at(31.0 + 8.0 - 1.5), 0.0).all()  # inside the first look's distance
    assert not k_us.inside(at(31.0 + 8.0 + 0.01), 0.0).any()
    assert not k_both.inside(at(31.0 + 2.5), 0.0).any()   # the outline (the box) + 2 mm
    assert k_both.inside(at(14.0), 0.0).all()             # the box's own half-depth is 15


def test_a_hole_lines_time_counts_the_table_turn_and_the_rise_to_its_row():
    """The rescan budget is spent by the lines' estimated time; each hole line is at its own
    table angle and row, so the estimate adds a move of the table (90 deg) and of Z (one
    outline row): a trapezoid at the axis' feed and acceleration, a triangle where the move
    is too short to reach the feed, the two equal where they meet."""
    from dmdsm.host.scan.auto_executor import move_s

    assert move_s(90.0, 90.0, 200.0) == pytest.approx(90 / 90 + 90 / 200)  # A: 1.45 s
    assert move_s(6.0, 25.0, 50.0) == pytest.approx(2 * math.sqrt(6 / 50))  # Z: a triangle
    assert move_s(25.0 ** 2 / 50.0, 25.0, 50.0) == pytest.approx(2 * 25.0 / 50.0)
    assert move_s(0.0, 25.0, 50.0) == 0.0
    d = np.linspace(0.01, 200.0, 500)
    t = np.array([move_s(x, 25.0, 50.0) for x in d])
    assert np.all(np.diff(t) > 0) and np.all(t >= d / 25.0)  # longer moves take longer
