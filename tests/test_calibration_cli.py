"""`dmdsm calibrate --from-data`: raw points to center points to Table I, with clear errors."""

import csv
import hashlib
import json
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
from test_calibration import XR, N, V, synth

from dmdsm.host.calibration.center_points import front_depth_mm
from dmdsm.host.calibration.rig_file import COLUMNS, append_rows, read_raw


def write_raw(path, data, radius=0.25, drop=None):
    """Raw raster points around each synthetic center point (symmetric, so exact centers);
    an edge sweep's depths are the spot-averaged front surface of the filament."""
    cols = ["step", "frame", "line", "theta_deg", "sx_mm", "sy_mm", "sz_mm", "d_mm",
            "amplitude", "modality", "extra"]
    if drop:
        cols.remove(drop)
    rows = []
    offs = np.linspace(-0.4, 0.4, 9)
    for c, (S, d) in enumerate(zip(data.tip_S, data.tip_d)):
        for ox in offs:
            for oz in offs:
                rows.append(dict(step="tip", frame=c, line=0, theta_deg=0.0,
                                 sx_mm=S[0] + ox, sy_mm=S[1], sz_mm=S[2] + oz, d_mm=d,
                                 amplitude=np.exp(-(ox ** 2 + oz ** 2) / 0.05),
                                 modality="oa", extra="x"))
    for j, (S, d, f) in enumerate(zip(data.edge_S, data.edge_d, data.edge_frame)):
        for ox in offs:
            front = front_depth_mm(ox, radius, 0.25)[0]
            rows.append(dict(step="edge", frame=10 + f, line=j, theta_deg=data.theta_deg[f],
                             sx_mm=S[0] + ox, sy_mm=S[1], sz_mm=S[2],
                             d_mm=d + radius - front,
                             amplitude=np.exp(-ox ** 2 / 0.02), modality="oa", extra="y"))
        rows.append(dict(step="edge", frame=10 + f, line=j, theta_deg=data.theta_deg[f],
                         sx_mm=S[0], sy_mm=S[1], sz_mm=S[2], d_mm="nan", amplitude=0.0,
                         modality="oa", extra="no echo"))
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=cols, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)


def dmdsm(*args):
    return subprocess.run([sys.executable, "-m", "dmdsm.host", *args], capture_output=True,
                          text=True, timeout=120)


def test_calibrate_from_data_recovers_table_i(tmp_path):
    raw = tmp_path / "rig.csv"
    write_raw(raw, synth(radius=0.25))
    out = tmp_path / "cal.toml"
    r = dmdsm("calibrate", "--from-data", str(raw), "--radius", "0.25", "-o", str(out),
              "--json")
    assert r.returncode == 0, r.stderr
    res = json.loads(r.stdout)
    assert np.allclose(res["v"], V, atol=1e-6) and np.allclose(res["n"], N, atol=1e-6)
    assert np.allclose(res["X_R"], XR, atol=1e-5)
    assert set(res["std"]) == {"v", "n", "X_R"} and "rms_residual_mm" in res
    assert len(res["residuals"]["edge_mm"]) == 14 and len(res["residuals"]["tip_mm"]) == 4
    text = out.read_text()
    assert text.startswith("# dmdsm scanner calibration") and "X_R_std" in text
    saved = tomllib.loads(text)["calibration"]
    assert saved["source"] == str(raw) and saved["software"].startswith("dmdsm ")
    assert saved["source_sha256"] == hashlib.sha256(raw.read_bytes()).hexdigest()
    assert np.allclose(saved["X_R"], res["X_R"]) and np.allclose(saved["v_std"], res["std"]["v"])
    r = dmdsm("calibrate", "--from-data", str(raw), "--radius", "0.25", "-o", str(out))
    assert r.returncode == 0 and r.stdout.startswith("v ")


def test_the_same_data_in_hdf5_gives_the_same_result(tmp_path):
    raw, h5 = tmp_path / "rig.csv", tmp_path / "rig.h5"
    write_raw(raw, synth(radius=0.25, noise=(0.01, 0.02, 0.01), seed=4))
    cols = read_raw(raw)
    append_rows(h5, [{c: cols[c][i].item() for c in COLUMNS} for i in range(len(cols["step"]))])
    got = []
    for path in (raw, h5):
        r = dmdsm("calibrate", "--from-data", str(path), "-o", str(tmp_path / "c.toml"),
                  "--json")
        assert r.returncode == 0, r.stderr
        got.append(json.loads(r.stdout))
        assert f'source = "{path}"' in (tmp_path / "c.toml").read_text()
    # the second run kept the first result, renamed, instead of writing over it
    first, second = (g.pop("previous") for g in got)
    assert first is None and Path(second).name.startswith("c.") and \
        f'source = "{raw}"' in Path(second).read_text()
    assert got[0] == got[1]


def test_bad_files_give_one_line_errors(tmp_path):
    raw = tmp_path / "rig.csv"
    write_raw(raw, synth(), drop="d_mm")
    r = dmdsm("calibrate", "--from-data", str(raw))
    assert r.returncode == 2 and "lacks column(s) d_mm" in r.stderr
    d = synth(tip_depths=(5.0,))
    write_raw(raw, d)
    r = dmdsm("calibrate", "--from-data", str(raw))
    assert r.returncode == 2 and "tip frames at two or more depths" in r.stderr
    (tmp_path / "cal.toml").write_text("[calibration]\nv = [0, 1, 0]\n")
    r = dmdsm("calibrate", "--from-data", str(tmp_path / "cal.toml"))
    assert r.returncode == 2 and "cal.toml is not a calibration data file: it has none of " \
        "the columns step, frame" in r.stderr
    r = dmdsm("calibrate", "--from-data", str(tmp_path / "none.csv"))
    assert r.returncode == 2 and "cannot read" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    write_raw(raw, synth(thetas=(30.0, 390.5)))
    r = dmdsm("calibrate", "--from-data", str(raw))
    assert r.returncode == 2 and "edge frames 10 and 11 have the same turntable angle (30 deg)" \
        in r.stderr and "rotate the table" in r.stderr
    write_raw(raw, synth(heights=(20, 20.3, 20.6)))  # one height: no edge direction
    r = dmdsm("calibrate", "--from-data", str(raw))
    assert r.returncode == 2 and "edge frame 10: its center points span 0.6" in r.stderr \
        and "heights 1 mm or more apart" in r.stderr
    write_raw(raw, synth())
    with open(raw, newline="") as fh:
        rows = list(csv.DictReader(fh))
    for row in rows:
        if row["frame"] == "11":
            row["d_mm"] = "nan"  # no echo anywhere in that frame
    with open(raw, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    r = dmdsm("calibrate", "--from-data", str(raw))
    assert r.returncode == 2 and "edge frame 11: 0 of 7 scan lines" in r.stderr
    r = dmdsm("calibrate", "--from-data", str(raw), "--modality", "us")
    assert r.returncode == 2 and "no US raw points (modality column has: oa)" in r.stderr
    r = dmdsm("calibrate", "--from-data", str(raw), "--threshold", "1.01")
    assert r.returncode == 2 and "0 of 4 tip frame(s)" in r.stderr and "threshold" in r.stderr
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1


def test_a_step_that_could_not_be_solved_is_refused_before_the_stage_moves(tmp_path):
    common = ["--sensor", str(tmp_path / "no-sensor"), "--stage", str(tmp_path / "no-stage"),
              "--data", str(tmp_path / "rig.csv"), "--at", "230", "260", "20"]
    for step, flags, want in (
            ("tip", ["--tip-depths", "3", "3"], "two or more different --tip-depths"),
            ("tip", ["--tip-step", "0"], "--tip-half and --tip-step must be positive"),
            ("edge", ["--angles", "0", "360"], "two or more different --angles"),
            ("edge", ["--edge-levels", "20", "20.5"], "--edge-levels (mm) 1 mm or more apart"),
    ):
        r = dmdsm("calibrate", "--step", step, *common, *flags)
        assert r.returncode == 2 and want in r.stderr, r.stderr
        assert len(r.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "rig.csv").exists()
