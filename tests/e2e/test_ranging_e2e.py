"""Ranging end to end in hil_sim: the stage as a ruler, then distances against the truth."""

import json
import subprocess
import sys

import numpy as np

from dmdsm.host.links.sensor import SensorClient
from dmdsm.host.links.stage import StageClient
from dmdsm.host.ranging.calibrate import gate_for, range_waveforms
from dmdsm.host.ranging.procedure import calibrate_range


def test_calibrated_ranging_reproduces_the_truth_within_the_papers_budget(emulator):
    emu = emulator(speed=3.0, scene="aluminium_block", seed=3)
    st, sc = StageClient(emu.stage), SensorClient(emu.sensor)
    st.home()
    st.move(x=235, y=266, z=20, wait=True)
    st.wait()
    d0 = emu.sim.truth()["distance_mm"]  # in the lab: a gauge block
    setup, report = calibrate_range(st, sc, {"X": 235, "Y": 266, "Z": 20}, d0, steps=21,
                                    step_mm=1.0, shots=4)
    c_true = emu.sim.model.c_mm_us * 1e6  # mm/s
    for m in ("oa", "us"):
        assert abs(setup.cals[m].c_mm_s / c_true - 1) < 0.02, report[m]
    errs = {"oa": [], "us": []}
    for y in (262.0, 264.3, 267.7):
        for z in (10, 25):
            st.move(x=230, y=y, z=z, wait=True)
            st.wait()
            truth = emu.sim.truth()["distance_mm"]
            got = sc.acquire(5)
            x = got.samples[got.received].astype(float) - 32768
            ph = got.trigger_phase[got.received] / sc.identity.tick_hz
            for m in errs:
                gate = gate_for(truth, m, setup.fs_hz, setup.cals[m].c_mm_s, 1024)
                d, _ = range_waveforms(x, ph, setup, m, gate=gate)
                errs[m] += list(d - truth)
    oa, us = np.abs(errs["oa"]), np.abs(errs["us"])
    assert np.isfinite(oa).all() and np.isfinite(us).all()
    assert oa.mean() < 0.12 and us.mean() < 0.26  # paper: 0.06 +/- 0.06, 0.15 +/- 0.11
    st.close()
    sc.close()


def test_glass_gives_no_oa_distance(emulator):
    from dmdsm.host.ranging.matched_filter import MatchedFilter, gaussian_pulse
    emu = emulator(speed=3.0, scene="glass_jar", seed=5)
    st, sc = StageClient(emu.stage), SensorClient(emu.sensor)
    st.home()
    st.move(x=235, y=240, z=40, wait=True)
    st.wait()
    truth = emu.sim.truth()
    assert truth["material"] == "glass"
    got = sc.acquire(4)
    x = got.samples[got.received].astype(float) - 32768
    fs = sc.identity.adc_rate_hz
    mf = MatchedFilter(gaussian_pulse(fs, 1.0e6, 0.6), 1024)
    oa = mf(x, gate=gate_for(truth["distance_mm"], "oa", fs, 343_000, 1024))
    us = mf(x, gate=gate_for(truth["distance_mm"], "us", fs, 343_000, 1024))
    assert np.isnan(oa.index).all() and oa.reason[0].startswith("no echo")
    assert np.isfinite(us.index).all()
    st.close()
    sc.close()


def test_calibrate_range_and_range_commands(emulator, tmp_path):
    emu = emulator(speed=3.0, scene="aluminium_block", seed=4)
    with StageClient(emu.stage) as st:
        st.home()
        st.move(x=235, y=266, z=20, wait=True)
        st.wait()
    d0 = emu.sim.truth()["distance_mm"]
    cal = tmp_path / "ranging.json"

    def dmdsm(*a):
        return subprocess.run([sys.executable, "-m", "dmdsm.host", *a], capture_output=True,
                              text=True, timeout=300)

    def calibrate(start_mm, *more):
        return dmdsm("calibrate-range", "--sensor", emu.sensor, "--stage", emu.stage, "-x",
                     "235", "-y", "266", "-z", "20", "--start-distance", f"{start_mm:.4f}",
                     "-o", str(cal), "--json", *more)

    # round 1's README: a gauge reading 0.76 mm too long, c from the air: t0 OA < 0 is
    # refused, not saved
    r = calibrate(d0 + 0.76, "--lateral", "5", "--fixed-c", "--temperature", "20")
    assert r.returncode == 2 and not cal.exists(), r.stderr
    assert "is too long by at least" in r.stderr and "t0 OA" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    r = calibrate(d0, "--steps", "11", "--step", "1", "--shots", "3")
    assert r.returncode == 0, r.stderr
    assert "c " in json.loads(r.stdout)["oa"]
    with StageClient(emu.stage) as st:
        st.move(x=235, y=264, z=20, wait=True)
        st.wait()
    truth = emu.sim.truth()["distance_mm"]
    h5 = tmp_path / "shots.h5"
    assert dmdsm("acquire", "--sensor", emu.sensor, "--shots", "6", "-o", str(h5)
                 ).returncode == 0
    before = h5.read_bytes()
    r = dmdsm("acquire", "--sensor", emu.sensor, "--shots", "2", "-o", str(h5))
    assert r.returncode == 2 and "--force" in r.stderr and h5.read_bytes() == before
    r = dmdsm("range", str(h5), "--calibration", str(cal), "--modality", "us", "--json")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    d = np.array([v for v in out["distance_mm"] if v is not None])
    sd = np.array([v for v in out["distance_std_mm"] if v is not None])
    assert len(d) >= 5 and len(sd) == len(d) and abs(np.median(d) - truth) < 0.5
    # each distance's own std: the surface scatter (~0.2 mm for US) and the noise at its SNR
    assert (sd > 0.05).all() and abs(np.median(d) - truth) < 4 * np.median(sd)
    r = dmdsm("range", str(h5), "--calibration", str(tmp_path / "none.json"))
    assert r.returncode == 2 and "calibrate-range" in r.stderr
