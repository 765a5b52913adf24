"""A lone pulse in an auto scan's first look (issue 32): with no partner and no neighbour on
the line it was dropped as ambiguous (an OA pulse at d reads as a US echo at about d / 2), so
a first look of a rounded or hidden surface (past 15 deg the US echo is gone) saw nothing.
Where the beam crosses the bounding cylinder (near .. far mm) decides it: read as OA only if
its US reading is nearer than near (no echo from the object comes back that early), as US
only if its OA reading is beyond far. Such a rule never reads a US echo as OA (a surface
twice as far as it is), whatever the surface, and reads every OA pulse of the near half."""

import sys
from pathlib import Path

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from sensor_limits import cell_waveform  # noqa: E402

from dmdsm.host.ranging.calibrate import RangeCal, RangingSetup  # noqa: E402
from dmdsm.host.ranging.matched_filter import gaussian_pulse  # noqa: E402
from dmdsm.host.ranging.point import WINDOW_MARGIN_MM, PointRanger  # noqa: E402

FS = 240e6 / 72


def ranger(t0_oa_us: float, t0_us_us: float, c_mm_us: float) -> PointRanger:
    """A "both" ranger with these calibrations (the templates do not matter here)."""
    p = gaussian_pulse(FS, 1e6, 0.8)
    cals = {m: RangeCal(m, t0 * 1e-6, c_mm_us * 1e6, 1e-8, 0.0, 0.05, 21)
            for m, t0 in (("oa", t0_oa_us), ("us", t0_us_us))}
    setup = RangingSetup(FS, {"oa": p, "us": p}, {"oa": (0, 1024), "us": (0, 1024)}, cals)
    return PointRanger(setup, 1024, 1e8, "both", (0.5, 200.0))


calibrations = st.tuples(st.floats(0.0, 6.0), st.floats(0.0, 6.0), st.floats(0.32, 0.36))


@given(calibrations, st.floats(2.0, 60.0), st.floats(0.0, 120.0), st.floats(0.0, 1.0),
       st.sampled_from(["oa", "us"]), st.floats(-0.3, 0.3), st.booleans())
def test_a_lone_pulse_read_by_the_window_is_never_read_as_the_wrong_modality(
        cal, near, chord, where, truth, noise, other_seen):
    """A pulse from a surface inside the window (near..far), read as its own modality with
    up to 0.3 mm of error and as the other one at the same arrival (or not, outside its
    gate): the rule gives its modality or nothing, never the other."""
    r = ranger(*cal)
    far = near + chord
    d = near + where * chord
    other = "us" if truth == "oa" else "oa"
    wide = {truth: (d + noise, 30.0),
            other: (r.other_reading_mm(truth, d + noise) if other_seen else np.nan, 30.0)}
    assert r.lone_by_window(wide, (near, far)) in (truth, None)


@given(calibrations, st.floats(5.0, 60.0), st.floats(0.0, 1.0), st.floats(0.0, 150.0))
def test_every_oa_pulse_whose_us_reading_is_nearer_than_the_window_is_read(
        cal, near, where, chord):
    """An OA pulse from within the window whose arrival, read as a US echo, would lie nearer
    than the window's near end is read as OA: the near part of the volume, up to about
    2 near, is seen from the first look however obliquely the surface faces it."""
    r = ranger(*cal)
    far = near + chord
    d = near + where * chord
    us = r.other_reading_mm("oa", d)
    got = r.lone_by_window({"oa": (d, 30.0), "us": (us, 30.0)}, (near, far))
    assert got == ("oa" if us < near - WINDOW_MARGIN_MM else None)


def test_no_window_or_a_window_the_beam_misses_reads_nothing():
    r = ranger(2.0, 4.0, 0.343)
    wide = {"oa": (20.0, 30.0), "us": (r.other_reading_mm("oa", 20.0), 30.0)}
    assert r.lone_by_window(wide, (15.0, 60.0)) == "oa"
    assert r.lone_by_window(wide, (np.nan, np.nan)) is None
    assert r.lone_by_window(wide, (25.0, 60.0)) is None  # nearer than the volume


def test_an_oblique_oa_pulse_is_read_by_the_window_and_a_steel_echo_as_us():
    """On the emulator's waveforms: plastic 30 mm away at 40 deg (no US echo) is dropped with
    no window and no neighbour, read as OA where the volume starts at 20 mm (its US reading,
    ~15 mm, is nearer), dropped where it starts at 10 mm (an echo from 15 mm could be it).
    Steel (no OA) head on at 20 mm: US where the volume ends before its OA reading (~40 mm),
    and never OA."""
    wave, phase, truth, r = cell_waveform("plastic", 30.0, 40.0)
    alone = r(wave, phase, 0, None)
    assert np.isnan(alone["oa"][0]) and np.isnan(alone["us"][0])
    seen = r(wave, phase, 0, None, window=(20.0, 60.0))
    assert abs(seen["oa"][0] - truth) < 0.5 and np.isnan(seen["us"][0])
    unsure = r(wave, phase, 0, None, window=(10.0, 60.0))
    assert np.isnan(unsure["oa"][0]) and np.isnan(unsure["us"][0])
    wave, phase, truth, r = cell_waveform("steel", 20.0, 0.0)
    seen = r(wave, phase, 0, None, window=(10.0, 30.0))
    assert abs(seen["us"][0] - truth) < 0.5 and np.isnan(seen["oa"][0])
    unsure = r(wave, phase, 0, None, window=(10.0, 60.0))
    assert np.isnan(unsure["oa"][0]) and np.isnan(unsure["us"][0])


def test_a_one_modality_plan_reads_its_lone_pulses_only_within_the_window():
    """A "us" plan reads a lone pulse as a US echo: a steel can's paper label gives an OA
    pulse (no US echo at 40 deg), which read as US lies at about half its distance, nearer
    than anything in the bounding volume. With the window the US echo is searched for only
    within it, so the OA pulse 30 mm away gives no US point (without it: one 15 mm off)."""
    wave, phase, truth, both = cell_waveform("plastic", 30.0, 40.0)
    us = PointRanger(both.setup, both.n, both.tick_hz, "us", (both.lo, both.hi))
    blind = us(wave, phase, 0, None)
    assert abs(blind["us"][0] - both.other_reading_mm("oa", truth)) < 1.0  # the misreading
    assert np.isnan(us(wave, phase, 0, None, window=(20.0, 60.0))["us"][0])
    wave, phase, truth, _ = cell_waveform("steel", 20.0, 0.0)  # a real echo in the window
    assert abs(us(wave, phase, 0, None, window=(10.0, 60.0))["us"][0] - truth) < 0.5


def test_a_sweep_of_a_material_that_answers_in_both_reads_a_lone_pulse_as_oa():
    """Plastic 30 mm away at 40 deg (an OA pulse, no echo) where the window starts at 10 mm
    cannot be read by the window (a US echo from 15 mm could be it: the pear's foot, 25-35
    mm behind an 8 mm standoff, gave 7 % coverage so); a sweep of plastic reads it as OA (a
    US echo only comes back head on, where plastic's OA pulse never fails), within the
    window only. Not an auto scan (its outline moves the keep-out), nor a material that
    may answer in US alone, nor no material: steel's echo would be read as OA at twice its
    distance."""
    from dmdsm.host.scan.plan import ScanPlan, point_ranger

    wave, phase, truth, both = cell_waveform("plastic", 30.0, 40.0)

    def plan(mode, material):
        return ScanPlan("x", material, radius_mm=40.0, height_mm=40.0, levels_mm=[10.0],
                        angles_deg=[0.0], mode=mode)

    r = point_ranger(plan("sweep", "Plastic"), both.setup, both.n, both.tick_hz)
    seen = r(wave, phase, 0, None, window=(10.0, 60.0))
    assert abs(seen["oa"][0] - truth) < 0.5 and np.isnan(seen["us"][0])
    beyond = r(wave, phase, 0, None, window=(32.0, 60.0))  # nearer than the window
    assert np.isnan(beyond["oa"][0]) and np.isnan(beyond["us"][0])
    assert np.isnan(r(wave, phase, 0, None)["oa"][0])  # no window: not read
    for mode, material in (("auto", "plastic"), ("fly", "plastic"), ("sweep", ""),
                           ("sweep", "steel"), ("sweep", "ceramic")):
        other = point_ranger(plan(mode, material), both.setup, both.n, both.tick_hz)
        assert not other.lone_is_oa, (mode, material)
    wave, phase, truth, _ = cell_waveform("steel", 20.0, 0.0)  # why: steel's lone echo
    misread = r(wave, phase, 0, None, window=(10.0, 60.0))["oa"][0]
    assert abs(misread - both.other_reading_mm("us", truth)) < 1.0


def test_a_plan_of_a_material_that_answers_in_both_reads_no_lone_pulse_as_us():
    """An auto line's neighbour (the outline's prediction) at ~15 mm, and an OA pulse from
    plastic 30 mm away at 40 deg (no echo): read as US it continues the prediction, a
    surface at 15 mm where there is none (a bowl's auto lines stored 6 such points 13 mm off
    it, 2026-12-06). A plan of plastic reads no lone pulse as US in any mode (its OA pulse
    would be there); a plan of no declared material still may."""
    from dmdsm.host.scan.plan import ScanPlan, point_ranger

    wave, phase, truth, both = cell_waveform("plastic", 30.0, 40.0)
    us_reading = both.other_reading_mm("oa", truth)
    prediction = (us_reading + 0.5, {"oa": -np.inf, "us": -np.inf})
    misread = both(wave, phase, 0, prediction)
    assert abs(misread["us"][0] - us_reading) < 1.0 and np.isnan(misread["oa"][0])
    for mode in ("auto", "step", "fly", "sweep"):
        plan = ScanPlan("x", "plastic", radius_mm=40.0, height_mm=40.0, levels_mm=[10.0],
                        angles_deg=[0.0], mode=mode)
        r = point_ranger(plan, both.setup, both.n, both.tick_hz)
        assert r.answers_both and np.isnan(r(wave, phase, 0, prediction)["us"][0]), mode
    unknown = ScanPlan("x", "", radius_mm=40.0, height_mm=40.0, levels_mm=[10.0],
                       angles_deg=[0.0], mode="auto")
    assert not point_ranger(unknown, both.setup, both.n, both.tick_hz).answers_both


V = np.array([0.0656, 0.9955, -0.0678]) / np.linalg.norm([0.0656, 0.9955, -0.0678])
N = np.array([-0.0007, 0.0022, 0.9999]) / np.linalg.norm([-0.0007, 0.0022, 0.9999])
X_R = np.array([235.21, 288.17, 0.0])


@given(st.floats(5.0, 90.0), st.floats(20.0, 120.0), st.floats(-1.2, 1.2),
       st.floats(2.0, 60.0), st.floats(0.0, 60.0))
def test_the_window_is_where_the_beam_is_inside_the_bounding_cylinder(radius, height, u,
                                                                      z, back):
    """cylinder_window's (near, far) bound exactly the beam's stretch inside the cylinder
    (radius, from the table top .. height): sampled along the beam, every point inside
    lies between them and the ends are on its boundary."""
    from dmdsm.host.scan.first_look import TABLE_TOP_MM, cylinder_window
    from dmdsm.host.scan.reconstruct import table_frame

    S = X_R + np.array([u * radius, -(radius + back), z])
    near, far = (float(a[0]) for a in cylinder_window(S[None], V, N, X_R, radius, height))
    d = np.linspace(0.0, 400.0, 40001)
    rel = (S + d[:, None] * V - X_R) @ table_frame(N)
    inside = (np.hypot(rel[:, 0], rel[:, 1]) <= radius) & (rel[:, 2] >= TABLE_TOP_MM) & (
        rel[:, 2] <= height)
    if not inside.any():
        assert np.isnan(near) and np.isnan(far)
        return
    assert d[inside].min() >= near - 0.011 and d[inside].max() <= far + 0.011
    assert abs(d[inside].min() - near) < 0.02 + 1e-9 or inside.sum() < 3
    assert abs(d[inside].max() - far) < 0.02 + 1e-9 or inside.sum() < 3


def test_a_both_plan_looks_again_from_as_far_out_as_its_radius_where_the_outline_is_open():
    """The first look stands at the plan's standoff; where it leaves a row of the outline
    open, a "both" plan looks again from the cylinder's radius away (at most 48 mm), each
    beam with its window: a lone OA pulse is then told from a US echo from the cylinder's
    front to its axis. "oa" and "us" plans (a lone pulse is theirs) do not."""
    from dmdsm.host.scan.first_look import (
        far_look_levels,
        far_look_plan,
        first_look_plan,
        first_look_points,
    )
    from dmdsm.host.scan.outline import Outline
    from dmdsm.host.scan.plan import ScanPlan

    plan = ScanPlan("pear", radius_mm=37.3, height_mm=110.0, levels_mm=[20.0], step_mm=2.0,
                    average=24, mode="auto")
    assert first_look_plan(plan).standoff_mm == 8.0
    assert first_look_plan(plan).levels_mm == [14.0, 20.0, 26.0]
    assert far_look_plan(plan, [14.0]).standoff_mm == 37.3
    assert far_look_plan(ScanPlan("bowl", radius_mm=83.0, height_mm=64.0, mode="auto",
                                  levels_mm=[20.0]), [14.0]).standoff_mm == 48.0
    r = np.full((72, 19), np.nan)
    r[:, 4] = 20.0      # z 24..30 closed all round; 12..18 half open; 18..24 not seen
    r[:36, 2] = 20.0
    o = Outline(5.0, np.arange(0, 115.0, 6.0), r, 37.3, 110.0)
    assert far_look_levels(plan, o, V) == [14.0, 20.0]
    for m in ("oa", "us"):
        assert far_look_levels(ScanPlan("x", radius_mm=37.3, height_mm=110.0, mode="auto",
                                        levels_mm=[20.0], modality=m), o, V) == []
    look = first_look_points(plan, V, X_R, N)
    far = first_look_points(plan, V, X_R, N, [14.0], first_line=24, first_index=len(look))
    assert far[0].line == 24 and far[0].index == len(look) and {p.z for p in far} == {14.0}
    assert all(p.y < X_R[1] - (37.3 + 37.3) * V[1] + 1e-6 for p in far)
    mid = [p for p in far if abs(p.x - X_R[0]) < 1.0]
    assert mid and all(abs(p.window_mm[0] - 37.3) < 1.0 and p.window_mm[1] > 100.0
                       for p in mid)
    beside = [p for p in far if abs(p.x - X_R[0]) > 38.0 + 4.0]
    assert all(np.isnan(p.window_mm[0]) for p in beside)


def test_an_oa_pulse_twice_the_expected_distance_away_is_not_read_as_a_us_echo():
    """On an auto follow line the outline predicts the surface 8 mm away; where the surface
    is really 16 mm away (the outline is its outermost bound) at 40 deg, the lone OA pulse
    reads as a US echo at ~7.7 mm, within 3 mm of the prediction, and was kept as US: a
    point 8 mm off and the OA point lost. The line's window (the object lies behind the
    outline's keep-out, 9 mm away here) reads it as OA first."""
    wave, phase, truth, r = cell_waveform("plastic", 16.0, 40.0)
    seed = (8.0, {"oa": -np.inf, "us": -np.inf})
    misread = r(wave, phase, 0, seed)
    assert abs(misread["us"][0] - 7.7) < 1.0 and np.isnan(misread["oa"][0])
    got = r(wave, phase, 0, seed, window=(9.0, 80.0))
    assert abs(got["oa"][0] - truth) < 0.5 and np.isnan(got["us"][0])


def test_a_follow_lines_window_starts_at_the_outline_keep_out_and_ends_past_the_cylinder():
    """outline_window: a beam aimed at the axis of a round outline (radius 20 mm, cylinder
    31 mm) from 8 mm outside the outline meets its keep-out 8 mm away (the object cannot be
    nearer) and leaves the cylinder on the far side; a beam beside the cylinder has none."""
    from dmdsm.host.scan.auto import outline_window
    from dmdsm.host.scan.outline import Outline

    o = Outline(5.0, np.arange(0, 41.0, 4.0), np.full((72, 10), 20.0), 31.0, 40.0)
    S = np.array([X_R - 28.0 * V + [0, 0, 20.0], X_R + [60.0, -40.0, 20.0]])
    near, far = outline_window(S, np.zeros(2), o, V, N, X_R)
    assert abs(near[0] - 8.0) < 0.4 and 28.0 + 30.0 < far[0] < 28.0 + 31.5
    assert np.isnan(near[1]) and np.isnan(far[1])


def test_a_pulse_from_the_foot_of_the_object_is_not_read_as_an_echo_in_mid_air():
    """The first look's lowest beams, 3 mm above the table and dipping 3.9 deg (v), meet the
    block's foot 42 mm away, 0.2 mm above the table. The window stopped 1 mm above the table
    (29 mm away), so that OA pulse was "beyond the far end" and read as a US echo at 21 mm:
    a point 14 mm in front of the block, in every first look beside its corners. The window
    reaches the table top: the pulse can be OA, and as US it is not taken."""
    from dmdsm.host.scan.first_look import cylinder_window

    r = ranger(2.0, 4.0, 0.343)
    S = X_R + np.array([10.0, -(30.2 + 15.0), 3.0])
    near, far = (float(a[0]) for a in cylinder_window(S[None], V, N, X_R, 30.2, 40.0))
    assert far > 42.0 + WINDOW_MARGIN_MM  # where the beam meets the table: 44 mm
    oa = 41.78
    wide = {"oa": (oa, 31.0), "us": (r.other_reading_mm("oa", oa), 30.0)}
    assert r.lone_by_window(wide, (near, far)) != "us"
    # with the window stopping 1 mm above the table, it was
    near1, far1 = (float(a[0]) for a in cylinder_window(S[None], V, N, X_R, 30.2, 40.0, 1.0))
    assert far1 < 30.0 and r.lone_by_window(wide, (near1, far1)) == "us"
