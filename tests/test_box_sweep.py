"""A box's sweep (reach.py): where a beam meets a turned face, and the passes and standoff
that see every face within each modality's incidence and reach. The bench checks the model
against the emulator (bench/scan_coverage.py --objects tissue_box aluminium_block)."""

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from dmdsm.host.scan.reach import (
    MIN_STANDOFF_MM,
    REACH_MM,
    box_passes,
    box_share,
    face_hit,
    strips,
)


@given(st.floats(5.0, 80.0), st.floats(-80.0, 80.0), st.floats(-60.0, 60.0))
def test_face_hit_is_where_the_beam_meets_the_turned_face(a, o, phi_deg):
    """The beam x = o, coming in along -y, against the face n . p = a (n turned phi from +y):
    the hit solved as a line and a plane agrees with face_hit's closed form."""
    phi = np.radians(phi_deg)
    n = np.array([np.sin(phi), np.cos(phi)])
    u = np.array([np.cos(phi), -np.sin(phi)])  # along the face
    start, direction = np.array([o, 500.0]), np.array([0.0, -1.0])
    s = (a - n @ start) / (n @ direction)
    p = start + s * direction
    t, out = face_hit(a, o, np.array([phi]))
    assert abs(t[0] - u @ p) < 1e-6 and abs(out[0] - p[1]) < 1e-6


boxes = st.tuples(st.floats(20.0, 140.0), st.floats(20.0, 140.0))


@given(boxes)
def test_a_box_is_swept_in_symmetric_strips_that_see_its_faces(size):
    """Offsets in order, symmetric about the axis, at most 9; the standoff 3..8 mm; the
    passes see as much of the faces as nine would (within half a per cent), in both."""
    w, d = size
    radius = float(np.hypot(w, d) / 2 + 1)
    offsets, standoff, shares = box_passes(w, d, radius, 8.0, ("oa", "us"), 2.0, 9)
    assert 1 <= len(offsets) <= 9 and offsets == sorted(offsets)
    assert np.allclose(offsets, [-x for x in reversed(offsets)], atol=0.11)
    assert MIN_STANDOFF_MM <= standoff <= 8.0
    for m in ("oa", "us"):
        most = box_share(w, d, radius + standoff, strips(max(w, d), 9, 0.9 * radius), m, 2.0)
        assert shares[m] >= most - 0.005 - 1e-12, (m, shares, most)


def test_a_deep_box_is_swept_from_closer_in_and_a_small_one_sees_all():
    """A 120 x 60 tissue box: its 60 mm-apart faces are 46 mm from a path 8 mm outside its
    cylinder, beyond US's reach; from 3 mm out eight passes see all of it. A 50 x 30 block
    from 8 mm in five. Foam (OA alone, seen to 30 deg) needs fewer."""
    radius = float(np.hypot(120, 60) / 2 + 1)
    assert 68.1 + 8 - 30 > REACH_MM["us"]
    offsets, standoff, shares = box_passes(120, 60, radius, 8.0, ("oa", "us"), 2.0, 9)
    assert standoff == MIN_STANDOFF_MM and len(offsets) == 8 and shares["us"] > 0.99
    assert box_share(120, 60, radius + 8.0, offsets, "us", 2.0) < 0.8  # from 8 mm: short
    offsets, standoff, shares = box_passes(50, 30, 30.2, 8.0, ("oa", "us"), 2.0, 9)
    assert standoff == 8.0 and len(offsets) == 5 and min(shares.values()) > 0.99
    assert len(box_passes(120, 60, radius, 8.0, ("oa",), 2.0, 9)[0]) < 8


@given(st.floats(10.0, 90.0), st.floats(-80.0, 80.0), st.sampled_from([4, 12, 24]))
def test_an_offset_pass_turns_slowly_enough_that_a_face_moves_little_in_a_waveform(
        radius, offset, average):
    """A pass offset o from the axis meets a flat face head on whose distance changes o mm
    per radian: over one waveform's shots at its table speed, by at most SWEEP_SMEAR_MM (an
    averaged pulse smeared over more depth ranges worse). Waveforms stay at most step_mm
    apart on the cylinder, and the table within its limit."""
    import math

    from dmdsm.host.scan.plan import SWEEP_SMEAR_MM, ScanPlan, table_speed_deg_s

    plan = ScanPlan("box", radius_mm=radius, mode="sweep", step_mm=2.0, average=average)
    w = table_speed_deg_s(plan, 90.0, offset)
    per_waveform = math.radians(w) * average / plan.laser_hz  # rad the table turns
    assert abs(offset) * per_waveform <= SWEEP_SMEAR_MM + 1e-9
    assert radius * per_waveform <= plan.step_mm + 1e-9 and w <= 90.0
    assert w == table_speed_deg_s(plan, 90.0, -offset)
    if abs(offset) * plan.step_mm / radius <= SWEEP_SMEAR_MM:  # slow enough already
        assert w == table_speed_deg_s(plan, 90.0)


def test_a_sweeps_planned_points_follow_each_pass_speed():
    """A box's passes far off the axis turn more slowly: more waveforms a turn, as many as
    plan.n_points counts."""
    from dmdsm.host.scan.plan import plan_for_size
    from dmdsm.host.scan.sweep import sweep_points, sweep_turns

    plan = plan_for_size("tissues", (120, 60, 20), False, "paper", "sweep")
    turns = sweep_turns(plan, np.array([0.0, 1.0, 0.0]), np.array([230.0, 290.0, 0.0]))
    pts = sweep_points(plan, turns, 90.0)
    assert len(pts) == plan.n_points()
    per = {t.offset: sum(p.level == t.index for p in pts) for t in turns}
    assert per[52.5] > 3 * per[7.5] and per[-52.5] == per[52.5]
