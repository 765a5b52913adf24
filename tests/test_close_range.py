"""A surface 3-8 mm from the sensor (a box's sweep passes its corners 4 mm away): its OA pulse
read as a US echo lies at about half the distance, within pair_mm of the OA reading, so the
ranger took one pulse for a pair (132 US points 2.6 mm off a tissue box's corners), and a
paper face 4 mm away head on, whose echo is over twice its OA pulse, had its echo read as the
OA pulse (OA 8.4 mm for 4.0). Every reading now is the surface's or none."""

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from sensor_limits import cell_waveform  # noqa: E402

from dmdsm.host.ranging.point import PointRanger  # noqa: E402


@pytest.mark.parametrize("material", ["paper", "plastic", "aluminium"])
def test_a_surface_a_few_mm_away_is_ranged_in_both_or_not_at_all(material):
    """At 3-8 mm, head on to 25 deg (a sweep's ranger: lone pulses as OA, none as US): OA is
    always found and every reading is within 0.4 mm of the truth."""
    for d in (3.0, 4.0, 4.5, 5.0, 6.0, 7.0, 8.0):
        for incidence in (0.0, 10.0, 25.0):
            wave, phase, truth, r = cell_waveform(material, d, incidence, average=12)
            sweep = PointRanger(r.setup, r.n, r.tick_hz, "both", (0.5, 200.0),
                                answers_both=True, lone_is_oa=True)
            got = sweep(wave, phase, 0, None, window=(0.5, d + 60.0))
            where = (material, d, incidence)
            assert abs(got["oa"][0] - truth) < 0.4, (where, got)
            assert np.isnan(got["us"][0]) or abs(got["us"][0] - truth) < 0.4, (where, got)


def test_one_pulse_read_twice_is_not_a_pair_and_a_true_pair_is():
    """same_arrival: an OA reading and the US reading of the same arrival (about half the
    distance) are one pulse; an OA and a US reading of the same surface are two, d apart."""
    wave, phase, truth, r = cell_waveform("paper", 20.0, 0.0, average=12)
    for d in (3.0, 5.0, 20.0, 40.0):
        assert r.same_arrival(d, r.other_reading_mm("oa", d))
        assert r.same_arrival(d, r.other_reading_mm("oa", d) + 0.5)
        assert not r.same_arrival(d, d)
