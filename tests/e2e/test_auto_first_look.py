"""An auto scan's first look of a rounded surface in hil_sim (issue 32): low on the pear the
skin slopes away from a level beam, so the US echo is gone and no OA+US pair starts a line;
the scan stopped with "the first look saw no surface". Where the first look leaves the
outline open, a far look stands back by the bounding cylinder's radius and reads a lone
pulse by where the beam crosses the cylinder: it gets an outline there, on the true
surface, the follow lines run, and the sensor never comes within the keep-out margin of the
true pear."""

import time

import numpy as np
from fly_scan_helpers import ranged_then, record_poses, scan_in_process

from dmdsm.host.links.sensor import SensorClient
from dmdsm.host.scan.plan import ScanPlan
from dmdsm.host.scan.points import scan_points
from dmdsm.host.scan.reconstruct import object_points
from dmdsm.host.scan.scanfile import read_scan


def test_the_first_look_outlines_the_bottom_of_a_pear(emulator, tmp_path):
    ranging, emu, cal, text = ranged_then(emulator, tmp_path, "pear", 31)
    # one level 6 mm up, where the pear is 11-20 mm across in a 37 mm cylinder; the first
    # look at 10 mm (and 20 mm rows); the follow lines at two table angles at most, no rescans
    plan = ScanPlan("pear", "apple", radius_mm=37.3, height_mm=110.0, levels_mm=[6.0],
                    angles_deg=[0.0], step_mm=2.0, average=12, mode="auto",
                    first_look_step_mm=20.0, max_angles=2, rescan_budget_s=0.0)
    shots = record_poses(emu.sim)
    t0 = time.monotonic()
    run = scan_in_process(emu, SensorClient(emu.sensor), plan, cal, text, ranging, tmp_path)
    print(f"scan {time.monotonic() - t0:.1f} s")
    assert run.status == "complete"
    a = run.auto
    assert a["outline_closed_share"] > 0 and a["lines"] > 0, a
    assert a["far_look_lines"] > 0  # the first look from 8 mm left the bottom open
    data = read_scan(run.path, waveforms=False)
    pts = scan_points(data)
    look = pts["oa"]["index"] < a["first_look_lines"]
    assert look.sum() > 20  # the first look's OA points, lone pulses read by the window
    truth = emu.sim.truth_objects()[0]
    d = np.abs(truth.signed_distance(pts["oa"]["P"][look]))
    assert np.median(d) < 0.3 and d.max() < 1.5, np.percentile(d, [50, 95, 100])
    # the sensor never came within the keep-out margin (2 mm) of the true pear
    sh = np.array(shots)
    S_obj = object_points(sh[:, 1:4], sh[:, 4], np.asarray(cal["n"]), np.asarray(cal["X_R"]))
    assert truth.signed_distance(S_obj).max() < -2.0
