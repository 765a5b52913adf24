"""A lone pulse on an auto follow line (issue 32): where the beam meets a surface too
obliquely for the US echo (past 15 deg), the OA pulse has no partner and, with no neighbour
on the line, was dropped as ambiguous; the distance the outline predicts (Point.expect_mm)
takes the neighbour's place, so it is read as OA, and a pulse far from it stays dropped."""

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from sensor_limits import cell_waveform  # noqa: E402

from dmdsm.host.scan.fly_executor import FlyLine, _expected  # noqa: E402
from dmdsm.host.scan.plan import Point  # noqa: E402


def test_a_lone_oa_pulse_is_read_where_the_outline_predicts_the_surface():
    wave, phase, truth, ranger = cell_waveform("plastic", 8.0, 40.0)
    alone = ranger(wave, phase, 0, None)
    assert np.isnan(alone["oa"][0]) and np.isnan(alone["us"][0])  # ambiguous: no partner
    hinted = ranger(wave, phase, 0, (8.0, {"oa": -np.inf, "us": -np.inf}))
    assert abs(hinted["oa"][0] - truth) < 0.5 and np.isnan(hinted["us"][0])
    wrong = ranger(wave, phase, 0, (20.0, {"oa": -np.inf, "us": -np.inf}))
    assert np.isnan(wrong["oa"][0]) and np.isnan(wrong["us"][0])


def test_the_expected_distance_is_the_lines_where_it_follows_and_none_beside():
    pts = [Point(i, 200.0 + 2 * i, 260.0, 20.0, 0.0, 0, i, 0, 5, e)
           for i, e in enumerate([np.nan, 8.0, 8.5, 9.0, np.nan])]
    got = _expected(FlyLine(5, pts), np.array([200.1, 202.0, 203.0, 206.0, 208.0]))
    assert np.isnan(got[0]) and np.isnan(got[-1])
    np.testing.assert_allclose(got[1:4], [8.0, 8.25, 9.0])
