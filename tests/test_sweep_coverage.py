"""A sweep's coverage of its band from its own points (host/scan/sweep.py sweep_coverage): a
direction with no echo is not covered, a height the zigzag passed between is covered when a
point lies within the spacing, and each modality is counted by its own points."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from dmdsm.host.scan.sweep import beam_heights_mm, sweep_coverage


def cylinder(r_mm, phi_deg, z_mm):
    """Points on a cylinder about the axis at these azimuths (deg) and heights (mm)."""
    p, z = np.meshgrid(np.radians(phi_deg), z_mm)
    return np.column_stack([r_mm * np.cos(p.ravel()), r_mm * np.sin(p.ravel()), z.ravel()])


ALL = np.arange(0, 360, 1.0)


def test_a_whole_cylinder_is_covered_and_a_missing_quarter_is_not():
    pts = cylinder(20.0, ALL, np.arange(0, 40, 0.5))
    c = sweep_coverage({"oa": pts, "us": pts}, 30.0, 40.0, (10.0, 30.0), 2.0)
    assert c == {"oa": 1.0, "us": 1.0, "directions": 1.0}
    # no echo over 90 deg (OA) and over 180 deg (US): those directions are not covered
    oa = cylinder(20.0, ALL[ALL >= 90], np.arange(0, 40, 0.5))
    us = cylinder(20.0, ALL[ALL >= 180], np.arange(0, 40, 0.5))
    c = sweep_coverage({"oa": oa, "us": us}, 30.0, 40.0, (10.0, 30.0), 2.0)
    assert c["oa"] == c["directions"] == 0.75
    # US: its half, and the one 5 deg cell beside it whose middle is 0.9 mm from its points
    assert c["us"] == round(37 / 72, 4)


def test_heights_the_zigzag_passed_between_count_when_a_point_is_within_the_spacing():
    # points every 3 mm in height: every 2 mm row between is within 1.5 mm of one
    c = sweep_coverage({"oa": cylinder(20.0, ALL, np.arange(0.5, 40, 3.0))}, 30.0, 40.0,
                       (10.0, 30.0), 2.0)
    assert c["oa"] == 1.0
    # every 8 mm: the rows 3-5 mm from a point are not
    c = sweep_coverage({"oa": cylinder(20.0, ALL, np.arange(0.5, 40, 8.0))}, 30.0, 40.0,
                       (10.0, 30.0), 2.0)
    assert 0.3 < c["oa"] < 0.7 and c["directions"] == 1.0


def test_only_the_band_counts():
    pts = cylinder(20.0, ALL, np.arange(0, 20, 0.5))  # the lower half alone
    assert sweep_coverage({"oa": pts}, 30.0, 40.0, (2.0, 18.0), 2.0)["oa"] == 1.0
    assert sweep_coverage({"oa": pts}, 30.0, 40.0, (24.0, 38.0), 2.0)["oa"] == 0.0


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.floats(-40, 40), st.floats(-40, 40), st.floats(-5, 45)),
                max_size=300),
       st.floats(0, 40), st.floats(0, 40))
def test_shares_are_shares(raw, a, b):
    p = np.array(raw, float).reshape(-1, 3)
    c = sweep_coverage({"oa": p, "us": p[: len(p) // 2]}, 30.0, 40.0, (a, b), 2.0)
    assert 0.0 <= c["us"] <= c["oa"] <= 1.0 and 0.0 <= c["directions"] <= 1.0


def test_the_beam_meets_the_cylinder_above_the_axis_when_it_dips():
    v = np.array([0.0, np.cos(np.radians(4)), -np.sin(np.radians(4))])  # dips 4 deg
    n, X_R = np.array([0.0, 0.0, 1.0]), np.array([0.0, 50.0, 0.0])
    entry, axis = beam_heights_mm(np.array([0.0, 10.0, 20.0]), v, n, X_R, 30.0)
    assert np.isclose(axis, 20.0 - 40.0 * np.tan(np.radians(4)))
    assert np.isclose(entry, 20.0 - 10.0 * np.tan(np.radians(4)))
