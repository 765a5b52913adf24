"""The whole calibration chain in hil_sim through the `dmdsm` commands a user types: ranging
calibration on the block, tip frames (filament horizontal), edge frames (filament vertical,
0 and 180 deg), solved into Table I within the reported uncertainties."""

import json
import signal
import subprocess
import sys
import time

import numpy as np

from dmdsm.host.calibration.rig_file import read_raw
from dmdsm.host.links.stage import StageClient
from dmdsm.sim.physics.objects import rig_horizontal, rig_vertical
from dmdsm.sim.physics.scene import table_frame

CMD = [sys.executable, "-m", "dmdsm.host"]


def dmdsm(*args):
    r = subprocess.run(CMD + list(args), capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    return r.stdout


def test_calibration_procedure_recovers_table_i_end_to_end(emulator, tmp_path):
    emu = emulator(speed=5.0, scene="aluminium_block", seed=3)
    sim = emu.sim
    with StageClient(emu.stage) as st:
        st.home()
        st.move(x=235, y=266, z=20, wait=True)
        st.wait()
    ports = ["--sensor", emu.sensor, "--stage", emu.stage]
    ranging, data, out = tmp_path / "ranging.json", tmp_path / "rig.csv", tmp_path / "cal.toml"
    dmdsm("calibrate-range", *ports, "-x", "235", "-y", "266", "-z", "20", "--start-distance",
          f"{sim.truth()['distance_mm']:.4f}", "--steps", "21", "--step", "1", "--shots", "4",
          "-o", str(ranging))

    def mount(objects):  # the user re-mounts the rig between the two steps
        with emu.server.lock:
            sim.scene.objects = objects
            sim.sensor._hit_cache = None

    v = sim.scene.v / np.linalg.norm(sim.scene.v)
    frame = table_frame(sim.scene.n)
    mount(rig_horizontal())
    tip = sim.scene.X_R + frame @ np.array([0.0, -10.0, 20.0]) - 6 * v  # jogged to by hand
    out_tip = dmdsm("calibrate", "--step", "tip", *ports, "--ranging", str(ranging),
                    "--data", str(data), "--at", *(f"{c:.3f}" for c in tip), "--json")
    assert json.loads(out_tip)["step"] == "tip"
    again = subprocess.run(CMD + ["calibrate", "--step", "tip", *ports, "--ranging",
                                  str(ranging), "--data", str(data), "--at", "0", "0", "0"],
                           capture_output=True, text=True, timeout=60)
    assert again.returncode == 2 and "already holds tip raw points: add --replace" \
        in again.stderr
    mount(rig_vertical())
    fil = sim.scene.X_R + frame @ np.array([25.0, 0.0, 0.0]) - 6.25 * v
    edge = CMD + ["calibrate", "--step", "edge", *ports, "--ranging", str(ranging), "--data",
                  str(data), "--at", f"{fil[0]:.3f}", f"{fil[1]:.3f}", "0", "-o", str(out)]
    # Ctrl-C during the edge step: the points so far are on disk, the stage stopped
    proc = subprocess.Popen(edge, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + 300
    while data.read_text().count("\nedge,") < 20 and time.monotonic() < deadline \
            and proc.poll() is None:
        time.sleep(0.05)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    n_edge = int(np.sum(read_raw(data)["step"] == "edge"))
    assert 20 <= n_edge < 182 and f"edge step stopped after {n_edge} raw points" in err \
        and "--replace" in err
    assert not out.exists()
    with StageClient(emu.stage) as st:
        st.where()
    res = json.loads(dmdsm(*edge[3:], "--replace", "--json"))
    n_true = sim.scene.n / np.linalg.norm(sim.scene.n)
    assert np.degrees(np.arccos(np.clip(np.dot(res["v"], v), -1, 1))) < 2.0
    assert np.degrees(np.arccos(np.clip(np.dot(res["n"], n_true), -1, 1))) < 0.5
    assert np.linalg.norm(np.array(res["X_R"][:2]) - sim.scene.X_R[:2]) < 0.3
    # within the reported uncertainty: the first-order components (those across each unit
    # vector: v x, z; n x, y) and X_R x, y, each within 4 standard deviations
    for name, true, comps in (("v", v, (0, 2)), ("n", n_true, (0, 1)),
                              ("X_R", sim.scene.X_R, (0, 1))):
        for i in comps:
            err, sd = res[name][i] - true[i], res["std"][name][i]
            assert abs(err) <= 4 * sd, f"{name}[{i}] off by {err:.2e} = {err / sd:.1f} std"
    assert out.read_text().count("X_R") >= 2
    raw = read_raw(data)  # every raw point kept for re-solving, the interrupted ones dropped
    assert np.sum(raw["step"] == "tip") == 4 * 81 and np.sum(raw["step"] == "edge") == 2 * 7 * 13


def test_lost_sensor_stops_the_step_and_keeps_the_points(emulator, tmp_path):
    from dmdsm.host.ranging.calibrate import RangeCal, RangingSetup
    from dmdsm.host.ranging.matched_filter import gaussian_pulse

    emu = emulator(speed=5.0, scene="aluminium_block", seed=4)
    fs = 240e6 / 72
    ranging, data = tmp_path / "ranging.json", tmp_path / "rig.csv"
    RangingSetup(fs, {"oa": gaussian_pulse(fs, 1e6, 0.8)}, {"oa": (0, 1024)},
                 {"oa": RangeCal("oa", 2e-6, 343e3, 0, 0, 0, 3)}).save(ranging)
    with StageClient(emu.stage) as st:
        st.home()
    proc = subprocess.Popen(CMD + ["calibrate", "--step", "tip", "--sensor", emu.sensor,
                                   "--stage", emu.stage, "--ranging", str(ranging), "--data",
                                   str(data), "--at", "230", "260", "20"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while (not data.exists() or data.read_text().count("\ntip,") < 15) \
            and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.05)
    chan = emu.sim.channels[("sensor", "up")]
    with emu.server.lock:  # the sensor's USB cable is pulled
        chan.f.disconnect, chan.f.reconnect_s = 1e9, 0.5
    time.sleep(0.05)
    with emu.server.lock:
        chan.f.disconnect = 0.0
    _, err = proc.communicate(timeout=120)
    saved = int(np.sum(read_raw(data)["step"] == "tip"))
    assert proc.returncode == 2 and saved >= 15, err
    assert "lost the sensor board" in err and f"the tip step stopped after {saved} raw points, " \
        f"saved in {data}: run the step again with --replace" in err
    errors = [ln for ln in err.splitlines() if "error" in ln.lower()]  # besides the bar
    assert len(errors) == 1 and errors[0].startswith("dmdsm: error: ") \
        and "Traceback" not in err
    with StageClient(emu.stage) as st:  # the stage was stopped and still answers
        st.where()



def test_a_tip_step_with_no_echo_fails_at_once_and_keeps_nothing(emulator, tmp_path):
    """A guessed --at far from the tip ran 51 s, saved 324 rows with no echo and exited 0
    (issue 30): it fails after the first raster, says what to do, and leaves no rows."""
    emu = emulator(speed=5.0, scene="aluminium_block", seed=3)
    with StageClient(emu.stage) as st:
        st.home()
        st.move(x=235, y=266, z=20, wait=True)
        st.wait()
    dmdsm("calibrate-range", "--sensor", emu.sensor, "--stage", emu.stage, "-x", "235", "-y",
          "266", "-z", "20", "--start-distance", f"{emu.sim.truth()['distance_mm']:.4f}",
          "--steps", "6", "--step", "1", "--shots", "2", "--fixed-c", "-o",
          str(tmp_path / "ranging.json"))
    with emu.server.lock:
        emu.sim.scene.objects = rig_horizontal()
        emu.sim.sensor._hit_cache = None
    data = tmp_path / "rig.csv"
    r = subprocess.run(CMD + ["calibrate", "--step", "tip", "--sensor", emu.sensor,
                              "--stage", emu.stage, "--ranging", str(tmp_path / "ranging.json"),
                              "--data", str(data), "--at", "200", "250", "60",
                              "--tip-depths", "0", "3", "6"],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 2, r.stderr
    line = r.stderr.strip().splitlines()[-1]
    assert "no echo in tip frame 1" in line and "give that position as --at" in line
    assert "nothing of the tip step was kept" in line and "Traceback" not in r.stderr
    assert not data.exists()
    again = subprocess.run(CMD + ["calibrate", "--step", "tip", "--sensor", emu.sensor,
                                  "--stage", emu.stage, "--ranging",
                                  str(tmp_path / "ranging.json"), "--data", str(data), "--at",
                                  "0", "0", "0"], capture_output=True, text=True, timeout=60)
    assert "already holds" not in again.stderr  # the same command runs again after jogging
