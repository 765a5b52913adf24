"""Reported stds hold against the emulator's truth (light Monte Carlo; bench/uncertainty.py
runs 40 seeds): the ranging calibration's t0 and c, and each scanned distance's own std."""

import numpy as np
import pytest

from dmdsm.host.ranging.procedure import calibrate_range
from dmdsm.sim.data.rig_data import DirectRig
from dmdsm.sim.physics.objects import aluminium_block
from dmdsm.sim.physics.scene import Scene

START = {"X": 235.0, "Y": 266.0, "Z": 20.0}


def ranging_z(seed: int, fit_c: bool) -> dict[str, float]:
    """(estimate - truth) / reported std of t0 (and c) for one seed, physics in process."""
    rig = DirectRig(Scene(objects=aluminium_block()), seed)
    rig.move(START["X"], START["Y"], START["Z"])
    d0 = rig.scene.cast(*rig.pose()).d  # the feeler gauge's reading
    setup, _ = calibrate_range(rig, rig, START, d0, steps=21, step_mm=1.0, shots=2,
                               fit_c=fit_c, lateral=5)
    out = {}
    for m, t0 in (("oa", rig.model.t0_oa_us), ("us", rig.model.t0_us_us)):
        c = setup.cals[m]
        out[f"t0 {m}"] = (c.t0_s * 1e6 - t0) / (c.t0_std_s * 1e6)
        if fit_c:
            out[f"c {m}"] = (c.c_mm_s - rig.model.c_mm_us * 1e6) / c.c_std_mm_s
    return out


@pytest.mark.parametrize("fit_c", [False, True])
def test_ranging_calibration_stds_hold_over_seeds(fit_c):
    zs = [ranging_z(seed, fit_c) for seed in range(100, 106)]
    for key in zs[0]:
        z = np.array([r[key] for r in zs])
        assert np.abs(z).max() < 4, (key, z)
        assert 0.4 < np.sqrt(np.mean(z ** 2)) < 1.7, (key, z)


def test_each_scanned_distance_carries_a_std_that_holds():
    """The block plan (one level) ranged as `dmdsm scan` does: (d - true d) / d_std has an
    RMS near 1 in both modalities, so a point's ± is one a user can trust."""
    from dmdsm.sim.data.block_data import block_rig, ranging_calibration, scan_block

    rig = block_rig(7)
    rows = scan_block(rig, ranging_calibration(rig), [20.0], step_mm=2.0)
    for m, a in rows.items():
        a = a[np.isfinite(a[:, 2])]
        assert len(a) > 60, m
        z = (a[:, 0] - a[:, 2]) / a[:, 1]
        assert 0.75 < np.sqrt(np.mean(z ** 2)) < 1.3, (m, np.sqrt(np.mean(z ** 2)))
        assert np.mean(np.abs(z) > 4) < 0.02, m
