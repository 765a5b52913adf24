"""Fly scanning in hil_sim: each waveform placed where the emulated Marlin's steppers were, the
block within the paper's error, a line with a lost waveform measured again, Ctrl-C keeping
whole lines and the same command resuming, and a missing sync wire named."""

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np

from dmdsm.host.links.sensor import SensorClient
from dmdsm.host.links.stage import StageClient
from dmdsm.host.ranging.procedure import calibrate_range
from dmdsm.host.scan.plan import ScanPlan
from dmdsm.host.scan.points import scan_points, validate_block
from dmdsm.host.scan.scanfile import read_scan
from dmdsm.host.scan.session import run_plan
from dmdsm.sim.boards.sensor import TICK_HZ

PAPER = {"oa": (0.06, 0.06), "us": (0.15, 0.11)}  # e mean, std (mm), paper §V-A2


def setup(emu, tmp_path, angles=(0.0, 90.0)):
    """Ranging calibration, the emulator's true v, n, X_R, and a fly plan of the block."""
    with StageClient(emu.stage) as st:
        st.home()
        st.move(x=235, y=266, z=20, wait=True)
        st.wait()
        sc = SensorClient(emu.sensor)
        try:
            ranging, _ = calibrate_range(st, sc, {"X": 235, "Y": 266, "Z": 20},
                                         emu.sim.truth()["distance_mm"], steps=6, step_mm=1.0,
                                         shots=2, fit_c=False, lateral=5)
        finally:
            sc.close()
        st.home()  # away from the object: the scan's approach starts outside its keep-out
    ranging.save(tmp_path / "ranging.json")
    s = emu.sim.scene
    cal = {"v": (s.v / np.linalg.norm(s.v)).tolist(), "n": (s.n / np.linalg.norm(s.n)).tolist(),
           "X_R": s.X_R.tolist()}
    text = "[calibration]\n" + "".join(f"{k} = {v}\n" for k, v in cal.items())
    (tmp_path / "cal.toml").write_text(text)
    plan = ScanPlan("aluminium_block", "aluminium", radius_mm=30.0, height_mm=40.0,
                    levels_mm=[20.0], angles_deg=list(angles), half_width_mm=32.0,
                    step_mm=1.0, average=12, mode="fly")
    (tmp_path / "plan.toml").write_text(plan.to_toml())
    return ranging, cal, text, plan


def record_poses(sim):
    """Every laser shot's true sensor position, by device tick."""
    shots = []
    pose = sim.pose

    def recording(t):
        S, theta = pose(t)
        shots.append((round(t * TICK_HZ), *S))
        return S, theta

    sim.sensor.pose = recording
    return shots


def scan_cmd(emu, tmp_path, scan_id, *extra):
    return [sys.executable, "-m", "dmdsm.host", "scan", "--sensor", emu.sensor, "--stage",
            emu.stage, "--calibration", str(tmp_path / "cal.toml"), "--ranging",
            str(tmp_path / "ranging.json"), "--plan", str(tmp_path / "plan.toml"), "--db",
            str(tmp_path / "db"), "--scan-id", scan_id, "--no-home", *extra]


def test_fly_places_every_waveform_where_the_stage_was_and_meets_the_paper(emulator,
                                                                          tmp_path):
    emu = emulator(speed=4.0, scene="aluminium_block", seed=7)
    setup(emu, tmp_path, angles=(0.0, 90.0, 180.0, 270.0))
    shots = record_poses(emu.sim)
    r = subprocess.run(scan_cmd(emu, tmp_path, "fly", "--json"), capture_output=True,
                       text=True, timeout=900)
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
    err = np.abs(err)
    # half a step (6.25 um) of stepper quantisation plus the emulator's 2 um stage scatter
    assert err.max() < 0.012, err.max()
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


def test_a_line_with_a_lost_waveform_is_measured_again_not_kept_with_a_hole(emulator,
                                                                           tmp_path):
    emu = emulator(speed=4.0, scene="aluminium_block", seed=8)
    ranging, cal, text, plan = setup(emu, tmp_path)
    sensor = SensorClient(emu.sensor)
    route = sensor._route
    seen = {"waveforms": 0}

    def lossy(m):  # the link loses the 10th waveform of the first line once
        if m.name == "waveform" and sensor.stream is not None:
            seen["waveforms"] += 1
            if seen["waveforms"] == 10:
                return
        route(m)

    sensor._route = lossy
    try:
        with StageClient(emu.stage) as st:
            run = run_plan(sensor, st, plan, cal, text, ranging, tmp_path / "db", home=False)
    finally:
        sensor.close()
    assert run.status == "complete" and run.stats.lost == 1
    p = read_scan(run.path, waveforms=False).points
    first = p["point_index"] == 0
    assert set(p["attempts"][first].tolist()) == {2}
    assert np.allclose(np.abs(np.diff(p["stage_position_mm"][first, 0])), 1.0, atol=0.02)


def test_ctrl_c_keeps_whole_lines_and_the_same_command_resumes(emulator, tmp_path):
    emu = emulator(speed=4.0, scene="aluminium_block", seed=9, frozen_noise=True)
    setup(emu, tmp_path, angles=(0.0, 90.0, 180.0))
    path = tmp_path / "db" / "scans" / "cut.h5"
    proc = subprocess.Popen(scan_cmd(emu, tmp_path, "cut"), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + 300

    def rows():
        try:
            return read_scan(path, waveforms=False).n_points
        except Exception:
            return 0

    while rows() == 0 and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.02)
    os.kill(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130 and "run the same command to continue" in err
    cut = read_scan(path)
    lines = sorted(set(cut.points["point_index"].tolist()))
    assert lines and lines == list(range(len(lines))) and len(lines) < 3
    for line in lines:  # only whole lines are in the file
        assert (cut.points["point_index"] == line).sum() >= 60
    with StageClient(emu.stage) as st:  # the stage was stopped and still answers
        st.where()
    r = subprocess.run(scan_cmd(emu, tmp_path, "cut"), capture_output=True, text=True,
                       timeout=900)
    assert r.returncode == 0, r.stderr
    assert f"resuming cut: {cut.n_points} of" in r.stdout
    done = read_scan(path)
    assert done.entry["status"] == "complete"
    assert sorted(set(done.points["point_index"].tolist())) == [0, 1, 2]
    np.testing.assert_array_equal(done.waveforms[:cut.n_points], cut.waveforms)


def test_a_fly_scan_without_the_sync_wire_says_what_to_wire(emulator, tmp_path):
    emu = emulator(speed=4.0, scene="aluminium_block", seed=10, sync_wire=False)
    setup(emu, tmp_path, angles=(0.0,))
    r = subprocess.run(scan_cmd(emu, tmp_path, "nowire"), capture_output=True, text=True,
                       timeout=900)
    assert r.returncode != 0
    last = r.stderr.strip().splitlines()[-1]
    assert "X STEP line" in last and "sync input" in last and "Traceback" not in r.stderr
