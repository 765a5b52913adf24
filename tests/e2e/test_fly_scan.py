"""Fly scanning in hil_sim: a line with a lost waveform measured again, Ctrl-C keeping whole
lines and the same command resuming, and a missing sync wire named. Each waveform's placement
and the block's error are checked in tests/stage/test_scan_on_stage.py, against the stage
under test (the Marlin emulator, or the real Marlin in `make check-marlin`)."""

import os
import signal
import subprocess
import time

import numpy as np
from fly_scan_helpers import scan_cmd, scan_in_process, setup

from dmdsm.host.links.sensor import SensorClient
from dmdsm.host.links.stage import StageClient
from dmdsm.host.scan.scanfile import read_scan


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
    run = scan_in_process(emu, sensor, plan, cal, text, ranging, tmp_path)
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
    emu = emulator(speed=4.0, scene="aluminium_block", seed=10, sync_wire="")
    setup(emu, tmp_path, angles=(0.0,))
    r = subprocess.run(scan_cmd(emu, tmp_path, "nowire"), capture_output=True, text=True,
                       timeout=900)
    assert r.returncode != 0
    last = r.stderr.strip().splitlines()[-1]
    assert "X STEP line" in last and "sync input" in last and "Traceback" not in r.stderr
