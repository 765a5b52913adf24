"""`dmdsm scan` against the stage under test: the Marlin emulator in `make test`, the real
Marlin under simavr in `make check-marlin` (DMDSM_STAGE_FIRMWARE). A step and shoot scan of
the block meets the paper; a fly scan places each waveform where the steppers were (by the X
steps the sensor counted) and is as accurate."""

import dataclasses
import json
import os
import subprocess

import numpy as np
from fly_scan_helpers import PAPER, record_poses, scan_cmd, setup

from dmdsm.host.scan.points import scan_points, validate_block
from dmdsm.host.scan.scanfile import read_scan

ELF = os.environ.get("DMDSM_STAGE_FIRMWARE", "")
SPEED = 1.0 if ELF else 4.0  # simavr runs Marlin at about twice real time at most
STEP_UM = 12.5  # one X step (80 steps/mm)


def _fits(scan):
    return validate_block(scan_points(scan), (50.0, 30.0))


def test_step_then_fly_both_meet_the_paper_and_fly_places_every_waveform(emulator, tmp_path):
    emu = emulator(speed=SPEED, scene="aluminium_block", seed=7, stage_firmware=ELF)
    ranging, cal, text, plan = setup(emu, tmp_path, angles=(0.0, 90.0, 180.0, 270.0))
    fly_plan = (tmp_path / "plan.toml").read_text()
    # step and shoot, two faces: 21 points on each, clear of their edges
    step = dataclasses.replace(plan, mode="step", half_width_mm=10.0, angles_deg=[0.0, 90.0])
    (tmp_path / "plan.toml").write_text(step.to_toml())
    r = subprocess.run(scan_cmd(emu, tmp_path, "step", "--json"), capture_output=True,
                       text=True, timeout=1800)
    assert r.returncode == 0, r.stderr
    scan = read_scan(tmp_path / "db" / "scans" / "step.h5", waveforms=False)
    assert scan.entry["status"] == "complete" and scan.n_points == 2 * 21
    step_fits = _fits(scan)
    for m, (mean, _) in PAPER.items():
        f = step_fits[m]
        assert f["n"] >= 36, (m, f)
        assert f["e_mean_mm"] <= mean + 3 * f["e_mean_se_mm"], (m, f)
        # (its std is the demo's to check, on more points: here each point's 12 shots
        # share one draw of the surface roughness, where a fly waveform's spread over 1 mm)
    # fly, four faces
    (tmp_path / "plan.toml").write_text(fly_plan)
    shots = record_poses(emu.sim)
    r = subprocess.run(scan_cmd(emu, tmp_path, "fly", "--json"), capture_output=True,
                       text=True, timeout=1800)
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout.splitlines()[-1])
    assert set(summary["clock_sync"]) >= {"drift_ppm", "drift_std_ppm", "residual_us"}
    scan = read_scan(tmp_path / "db" / "scans" / "fly.h5", waveforms=False)
    p = scan.points
    assert sorted(set(p["point_index"].tolist())) == [0, 1, 2, 3]  # four whole lines
    rec = np.array(shots)
    rec = rec[np.argsort(rec[:, 0])]
    err = []
    for ts, n, x in zip(p["timestamp"], p["n_average"], p["stage_position_mm"][:, 0]):
        i = np.searchsorted(rec[:, 0], int(ts))
        assert rec[i, 0] == int(ts)  # the waveform's first shot
        err.append(x - rec[i:i + int(n), 1].mean())
    err = np.array(err)
    # The frame: the truth's origin is the endstop switch, Marlin's is where its homing
    # stopped, 0-2 steps past the switch on the real Marlin by where it starts (the
    # emulator: on it).
    offset = np.median(err)
    assert abs(offset) * 1e3 <= 2 * STEP_UM + 2.0, offset
    # counted steps: the emulator's 2 um stage scatter and the steps' quantisation left
    assert np.abs(err - offset).max() < 0.008, np.abs(err - offset).max()
    for line in range(4):  # waveforms one step apart along each line, none missing
        x = p["stage_position_mm"][p["point_index"] == line, 0]
        assert np.allclose(np.abs(np.diff(x)), 1.0, atol=0.02)
        assert 60 <= len(x) <= 66
    fits = _fits(scan)
    for m, (mean, std) in PAPER.items():
        f, s = fits[m], step_fits[m]
        assert f["n"] > 140  # the faces in view on 4 lines (the rest of a line misses)
        # within the paper, or as accurate as step and shoot on the same stage (this
        # emulator's US channel sits ~0.02 mm above the paper's mean in both modes)
        both = 3 * np.hypot(f["e_mean_se_mm"], s["e_mean_se_mm"])
        assert f["e_mean_mm"] <= max(mean + 3 * f["e_mean_se_mm"], s["e_mean_mm"] + both), \
            (m, f, s)
        # the spread likewise: within the paper's, or step and shoot's on the same stage
        # (its own OA spread here is ~0.096 mm) within 3 standard errors of the two stds
        se_std = np.hypot(f["e_std_mm"] / np.sqrt(2 * f["n"]), s["e_std_mm"] / np.sqrt(2 * s["n"]))
        assert f["e_std_mm"] <= max(1.5 * std, s["e_std_mm"] + 3 * se_std), (m, f, s)
    print(f"\nfly placement: offset {offset * 1e3:.1f} um, spread "
          f"{np.abs(err - offset).max() * 1e3:.1f} um max; block e (mm) step / fly: OA "
          f"{step_fits['oa']['e_mean_mm']:.3f} +- {step_fits['oa']['e_std_mm']:.3f} / "
          f"{fits['oa']['e_mean_mm']:.3f} +- {fits['oa']['e_std_mm']:.3f}, US "
          f"{step_fits['us']['e_mean_mm']:.3f} +- {step_fits['us']['e_std_mm']:.3f} / "
          f"{fits['us']['e_mean_mm']:.3f} +- {fits['us']['e_std_mm']:.3f}")


def test_an_auto_scans_joined_moves_place_every_waveform_on_the_stage_under_test(emulator,
                                                                                tmp_path):
    """Issue 32: a follow line is a chain of G1 moves bending in Y that Marlin's planner
    joins. Every X step of it must reach the sensor's sync input (else the line is refused
    and measured again), and each waveform lands where the steppers were, X and Y: on the
    real Marlin (`make check-marlin`) as on the emulator."""
    from dmdsm.host.scan.plan import ScanPlan

    emu = emulator(speed=SPEED, scene="aluminium_block", seed=23, stage_firmware=ELF)
    setup(emu, tmp_path)
    plan = ScanPlan("aluminium_block", "aluminium", radius_mm=31.0, height_mm=40.0,
                    levels_mm=[20.0], angles_deg=[0.0, 90.0], step_mm=2.0, average=12,
                    mode="auto", first_look_step_mm=20.0)
    (tmp_path / "plan.toml").write_text(plan.to_toml())
    shots = record_poses(emu.sim)
    r = subprocess.run(scan_cmd(emu, tmp_path, "auto", "--json"), capture_output=True,
                       text=True, timeout=3600)
    assert r.returncode == 0, r.stderr
    auto = json.loads(r.stdout.splitlines()[-1])["auto"]
    p = read_scan(tmp_path / "db" / "scans" / "auto.h5", waveforms=False).points
    follow = p["point_index"] >= auto["first_look_lines"]
    assert auto["lines"] >= 4 and follow.sum() > 60
    rec = np.array(shots)
    rec = rec[np.argsort(rec[:, 0])]
    err = []
    for ts, n, S in zip(p["timestamp"], p["n_average"], p["stage_position_mm"]):
        i = np.searchsorted(rec[:, 0], int(ts))
        err.append(S[:2] - rec[i:i + int(n), 1:3].mean(axis=0))
    err = np.array(err)
    offset = np.median(err[:, 0])  # the homing's step past the switch, as above
    assert abs(offset) * 1e3 <= 2 * STEP_UM + 2.0, offset
    dx = np.abs(err[follow, 0] - offset)
    # Y from the counted X on the path: within a Y step (10 um) of where Y was, plus the
    # Y homing's offset, whatever the planner did at the junctions
    dy = np.abs(err[follow, 1] - np.median(err[follow, 1]))
    assert dx.max() < 0.008 and dy.max() < 0.015, (dx.max(), dy.max())
    print(f"\nauto placement on the follow lines: X {dx.max() * 1e3:.1f} um, Y "
          f"{dy.max() * 1e3:.1f} um max about the homing offsets")
