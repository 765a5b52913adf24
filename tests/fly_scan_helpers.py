"""Shared by the fly-scan tests (tests/e2e, and tests/stage against the stage under test):
the ranging calibration and plan on the emulator's block, every shot's true pose, the CLI."""

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
from dmdsm.host.scan.scanfile import read_scan
from dmdsm.host.scan.session import run_plan
from dmdsm.sim.boards.sensor.core_board import TICK_HZ

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


def ranged_then(emulator, tmp_path, scene, seed):
    """The ranging calibration on the gauge block (its own emulator, stopped after), then
    an emulator of `scene` and its true v, n, X_R as a calibration dict and TOML text
    (written to tmp_path/cal.toml): (ranging, emulator, cal, text)."""
    block = emulator(speed=20.0, scene="aluminium_block", seed=seed)
    ranging, _, _, _ = setup(block, tmp_path)
    block.stop()
    emu = emulator(speed=4.0, scene=scene, seed=seed)
    s = emu.sim.scene
    cal = {"v": (s.v / np.linalg.norm(s.v)).tolist(), "n": (s.n / np.linalg.norm(s.n)).tolist(),
           "X_R": s.X_R.tolist()}
    text = "[calibration]\n" + "".join(f"{k} = {v}\n" for k, v in cal.items())
    (tmp_path / "cal.toml").write_text(text)
    return ranging, emu, cal, text


def record_poses(sim):
    """Every laser shot's device tick, true sensor position (X, Y, Z) and table angle."""
    shots = []
    pose = sim.pose

    def recording(t):
        S, theta = pose(t)
        shots.append((round(t * TICK_HZ), *S, theta))
        return S, theta

    sim.sensor.pose = recording
    return shots


def scan_cmd(emu, tmp_path, scan_id, *extra):
    return [sys.executable, "-m", "dmdsm.host", "scan", "--sensor", emu.sensor, "--stage",
            emu.stage, "--calibration", str(tmp_path / "cal.toml"), "--ranging",
            str(tmp_path / "ranging.json"), "--plan", str(tmp_path / "plan.toml"), "--db",
            str(tmp_path / "db"), "--scan-id", scan_id, "--no-home", *extra]


def scan_in_process(emu, sensor, plan, cal, text, ranging, tmp_path):
    """run_plan of `plan` with an open sensor client (closed after) into tmp_path/db."""
    try:
        with StageClient(emu.stage) as st:
            return run_plan(sensor, st, plan, calibration=cal, calibration_toml=text,
                            setup=ranging, db=tmp_path / "db", home=False)
    finally:
        sensor.close()


def pose_errors(points, shots):
    """(n, 4) each stored waveform's X, Y, Z (mm) and table angle (deg) minus the mean of
    its shots' true pose (record_poses), in the file's order."""
    sh = np.array(shots)
    sh = sh[np.argsort(sh[:, 0], kind="stable")]
    err = []
    for t, k, S, th in zip(points["timestamp"], points["n_average"],
                           points["stage_position_mm"], points["theta_deg"]):
        i = np.searchsorted(sh[:, 0], t)
        err.append([*(S - sh[i:i + k, 1:4].mean(axis=0)), th - sh[i:i + k, 4].mean()])
    return np.array(err)


def ctrl_c_after(cmd, path, lines_more_than):
    """Run the scan command `cmd`, send it Ctrl-C once its file `path` holds more than
    lines_more_than lines (point indices), and return its stderr (the exit asserted 130)."""
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + 600

    def lines():
        try:
            return len(set(read_scan(path, waveforms=False).points["point_index"].tolist()))
        except Exception:
            return 0

    while lines() <= lines_more_than and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.05)
    os.kill(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130 and "run the same command to continue" in err, err
    return err
