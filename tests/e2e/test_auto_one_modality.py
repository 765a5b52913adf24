"""An auto scan of an object that answers in one modality only, in hil_sim: steel gives a US
echo and no OA pulse, so a "both" plan's first look hears a lone pulse on its waveforms that
it cannot tell OA or US (host/ranging/point.py) and sees little or no surface. `dmdsm scan`
says to set modality = "us" (one line, not where to put the object, and not a traceback):
as its error where the first look saw nothing, as a note where it saw a little; the plan
changed so scans the can."""

import subprocess

import numpy as np
from fly_scan_helpers import ranged_then, scan_cmd, scan_in_process

from dmdsm.host.links.sensor import SensorClient
from dmdsm.host.scan.plan import ScanPlan
from dmdsm.host.scan.points import scan_points
from dmdsm.host.scan.scanfile import read_scan

PLAN = dict(radius_mm=38.0, height_mm=110.0, levels_mm=[15.0], angles_deg=[0.0],
            step_mm=2.0, average=12, mode="auto", first_look_step_mm=10.0, max_angles=2,
            rescan_budget_s=0.0)


def test_a_steel_can_in_a_both_plan_is_told_to_scan_us_and_then_scans(emulator, tmp_path):
    ranging, emu, cal, text = ranged_then(emulator, tmp_path, "steel_can", 41)
    (tmp_path / "plan.toml").write_text(ScanPlan("steel_can", "steel", **PLAN).to_toml())
    r = subprocess.run(scan_cmd(emu, tmp_path, "both", "--no-model"), capture_output=True,
                       text=True, timeout=900)
    err = r.stderr.strip().splitlines()
    assert "Traceback" not in r.stderr, r.stderr
    # where its far look read a few lone echoes of the can's flanks by the window (about
    # one run in two), the scan goes on and says the same in a note; else it stops
    if r.returncode == 0:
        assert 'auto: note: the first look ranged' in r.stdout and \
            'set modality = "us"' in r.stdout, r.stdout
    else:
        assert r.returncode == 2 and err[-1].startswith(
            "dmdsm: error: the first look saw no surface") and \
            'set modality = "us"' in err[-1], r.stderr
        assert "run the same command" not in r.stderr  # it would stop there again
    plan = ScanPlan("steel_can", "steel", modality="us", **PLAN)
    run = scan_in_process(emu, SensorClient(emu.sensor), plan, cal, text, ranging, tmp_path)
    assert run.status == "complete" and run.auto["lines"] > 0, run.auto
    a = run.auto
    assert a["outline_seen_share"] > 0.3 and a["coverage"]["us"] > 0.3, a
    # its US points lie on the true can
    P = scan_points(read_scan(run.path, waveforms=False))["us"]["P"]
    d = np.abs(emu.sim.truth_objects()[0].signed_distance(P))
    assert len(P) > 100 and np.median(d) < 0.3, (len(P), np.percentile(d, [50, 95]))


def test_a_labelled_cans_step_and_fly_scans_store_no_us_point_in_mid_air(emulator, tmp_path):
    """A US plan (steel) of a can with a paper label, step and shoot and fly, one level
    through the label: the label met 40 deg off head on ~18 mm away gives an OA pulse and no
    echo, which read as a US echo is a surface at ~9 mm, nearer than the bounding cylinder
    lets anything be. Each point's window (where its beam crosses the cylinder) rules it
    out (2026-12-06, none: 20 of 52 step points 7-8 mm off the can)."""
    ranging, emu, cal, text = ranged_then(emulator, tmp_path, "can_with_label", 43)
    for mode in ("step", "fly"):
        plan = ScanPlan("can", "steel", modality="us", radius_mm=38.0, height_mm=110.0,
                        levels_mm=[40.0], angles_deg=[0.0, 90.0], half_width_mm=25.9,
                        step_mm=2.0 if mode == "fly" else 4.0, average=12, mode=mode)
        run = scan_in_process(emu, SensorClient(emu.sensor), plan, cal, text, ranging,
                              tmp_path / mode)
        assert run.status == "complete", run.status
        P = scan_points(read_scan(run.path, waveforms=False))["us"]["P"]
        d = np.abs(emu.sim.truth_objects()[0].signed_distance(P))
        assert len(P) >= 4 and d.max() < 1.0, (mode, len(P), np.sort(d)[-5:])
