"""Files stay where the user named them (issue 19, item 5): a scan id is a name, never a path,
and a catalogue row that points outside the database is not opened."""

import sqlite3
import subprocess
import sys

import pytest

from dmdsm.host.ranging.calibrate import RangeCal, RangingSetup
from dmdsm.host.ranging.matched_filter import gaussian_pulse
from dmdsm.host.scan.catalogue import list_scans, verify
from dmdsm.sim.data.dataset import make_database

PLAN = """[sample]
object_id = "aluminium_block"
material = "aluminium"
[object]
radius_mm = 30.0
height_mm = 40.0
[scan]
levels_mm = [20.0]
"""


def dmdsm(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "dmdsm.host", *args], capture_output=True,
                          text=True, timeout=120, cwd=cwd)


@pytest.fixture
def inputs(tmp_path):
    cal = tmp_path / "cal.toml"
    cal.write_text("[calibration]\nv = [0.0656, 0.9955, -0.0678]\nn = [-0.0007, 0.0022, "
                   "0.9999]\nX_R = [235.21, 288.17, 0.0]\n")
    fs = 240e6 / 72
    ranging = tmp_path / "ranging.json"
    RangingSetup(fs, {"oa": gaussian_pulse(fs, 1e6, 0.8)}, {"oa": (0, 1024)},
                 {"oa": RangeCal("oa", 2e-6, 343e3, 0, 0, 0, 3)}).save(ranging)
    plan = tmp_path / "plan.toml"
    plan.write_text(PLAN)
    return cal, ranging, plan


@pytest.mark.parametrize("scan_id", ["../../x", "/tmp/abs", "a/b", "..", ".hidden", "x" * 101,
                                     "a b"])
def test_a_scan_id_that_is_a_path_is_refused_before_anything(tmp_path, inputs, scan_id):
    cal, ranging, plan = inputs
    work = tmp_path / "work"
    work.mkdir()
    r = dmdsm("scan", "--sensor", "/dev/null-sensor", "--stage", "/dev/null-stage",
              "--calibration", str(cal), "--ranging", str(ranging), "--plan", str(plan),
              "-o", str(work / "db"), "--scan-id", scan_id, cwd=work)
    assert r.returncode == 2, r.stderr
    assert "is not a name" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert "Traceback" not in r.stderr
    written = [p for p in tmp_path.rglob("*") if p.is_file()]
    assert sorted(p.name for p in written) == ["cal.toml", "plan.toml", "ranging.json"]


def test_a_catalogue_row_pointing_outside_the_database_is_not_opened(tmp_path):
    db = tmp_path / "db"
    make_database(db, points=8, seed=1, objects=["soda_can"])
    (scan_id,) = [r["scan_id"] for r in list_scans(db)]
    outside = tmp_path / "elsewhere.h5"
    outside.write_bytes(b"not for dmdsm")
    with sqlite3.connect(db / "catalogue.sqlite") as con:
        con.execute("UPDATE scans SET path = ?", (str(outside),))
    con.close()
    (row,) = list_scans(db)
    assert row["status"].startswith("refused") and verify(row) == "refused"
    assert not row["path"].startswith(str(outside))
    r = dmdsm("db", "show", scan_id, "--db", str(db))
    assert r.returncode == 2 and "refused" in r.stderr and "db rebuild" in r.stderr
    assert "Traceback" not in r.stderr
    r = dmdsm("db", "rebuild", "--db", str(db))  # re-indexes the files really in db/scans
    assert r.returncode == 0, r.stderr
    (row,) = list_scans(db)
    assert row["status"] == "complete" and verify(row) == "ok"


@pytest.mark.parametrize("command", [
    ["calibrate-range", "-x", "235", "-y", "266", "-z", "20", "--start-distance", "7.2",
     "--sensor", "/dev/null-s", "--stage", "/dev/null-p", "-o", "{missing}/r.json"],
    ["calibrate", "--from-data", "{rig}", "-o", "{missing}/c.toml"],
    ["reconstruct", "{scan}", "--plot", "{missing}/p.png"],
    ["reconstruct", "{scan}", "--ply", "{missing}/p.ply"],
    ["db", "export", "{scan_id}", "--db", "{db}", "--csv", "{missing}/p.csv"],
    ["classify", "train", "--db", "{db}", "-o", "{missing}/m.model"],
    ["scan", "--plan", "{plan}", "--calibration", "{cal}", "--ranging", "{ranging}",
     "--db", "{plain}"],
])
def test_an_output_that_cannot_be_written_is_refused_before_the_work(tmp_path, inputs,
                                                                      command):
    cal, ranging, plan = inputs
    db = tmp_path / "db"
    (scan,) = make_database(db, points=8, seed=2, objects=["soda_can"])
    rig = tmp_path / "rig.csv"
    rig.write_text("step,frame,line,theta_deg,sx_mm,sy_mm,sz_mm,d_mm,amplitude,modality\n")
    plain = tmp_path / "plain.txt"
    plain.write_text("a file, not a folder\n")
    names = {"missing": tmp_path / "no" / "such", "rig": rig, "scan": scan, "db": db,
             "scan_id": scan.stem, "plan": plan, "cal": cal, "ranging": ranging,
             "plain": plain}
    r = dmdsm(*[a.format(**names) for a in command])
    assert r.returncode == 2, r.stderr
    assert ("does not exist" in r.stderr or "is a file" in r.stderr), r.stderr
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1
