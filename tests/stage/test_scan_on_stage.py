"""`dmdsm scan` against the stage under test: the Marlin emulator in `make test`, the real
Marlin under simavr in `make check-marlin` (DMDSM_STAGE_FIRMWARE). A fly scan places each
waveform where the steppers were, by the X STEP wire, and the block meets the paper; a step
and shoot scan of the same block does too."""

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


def test_fly_places_every_waveform_where_the_stage_was_and_meets_the_paper(emulator,
                                                                          tmp_path):
    emu = emulator(speed=SPEED, scene="aluminium_block", seed=7, stage_firmware=ELF)
    setup(emu, tmp_path, angles=(0.0, 90.0, 180.0, 270.0))
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
    # stopped, at most one step past the switch (the emulator: on it).
    offset = np.median(err)
    assert abs(offset) * 1e3 <= STEP_UM + 2.0, offset
    # half a step (6.25 um) of stepper quantisation plus the emulator's 2 um stage scatter
    assert np.abs(err - offset).max() < 0.012, np.abs(err - offset).max()
    for line in range(4):  # waveforms one step apart along each line, none missing
        x = p["stage_position_mm"][p["point_index"] == line, 0]
        assert np.allclose(np.abs(np.diff(x)), 1.0, atol=0.02)
        assert 60 <= len(x) <= 66
    fits = validate_block(scan_points(scan), (50.0, 30.0))
    for m, (mean, std) in PAPER.items():
        f = fits[m]
        assert f["n"] > 140  # the faces in view on 4 lines (the rest of a line misses)
        assert f["e_mean_mm"] <= mean + 3 * f["e_mean_se_mm"], (m, f)
        assert f["e_std_mm"] <= 1.5 * std, (m, f)
    print(f"\nfly placement: offset {offset * 1e3:.1f} um, spread "
          f"{np.abs(err - offset).max() * 1e3:.1f} um max; block OA "
          f"{fits['oa']['e_mean_mm']:.3f} +- {fits['oa']['e_std_mm']:.3f} mm, US "
          f"{fits['us']['e_mean_mm']:.3f} +- {fits['us']['e_std_mm']:.3f} mm")


def test_step_and_shoot_meets_the_paper_on_the_same_stage(emulator, tmp_path):
    emu = emulator(speed=SPEED, scene="aluminium_block", seed=5, stage_firmware=ELF)
    ranging, cal, text, plan = setup(emu, tmp_path, angles=(0.0, 90.0))
    step = dataclasses.replace(plan, mode="step", half_width_mm=12.0)  # on both faces
    (tmp_path / "plan.toml").write_text(step.to_toml())
    r = subprocess.run(scan_cmd(emu, tmp_path, "step", "--json"), capture_output=True,
                       text=True, timeout=1800)
    assert r.returncode == 0, r.stderr
    scan = read_scan(tmp_path / "db" / "scans" / "step.h5", waveforms=False)
    assert scan.entry["status"] == "complete" and scan.n_points == 2 * 25
    fits = validate_block(scan_points(scan), (50.0, 30.0))
    for m, (mean, std) in PAPER.items():
        f = fits[m]
        assert f["n"] >= 40, (m, f)
        assert f["e_mean_mm"] <= mean + 3 * f["e_mean_se_mm"], (m, f)
        assert f["e_std_mm"] <= 1.5 * std, (m, f)
