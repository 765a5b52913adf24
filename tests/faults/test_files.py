"""Every command that reads a scan file or the catalogue, fed damaged and hostile input
(issue 19, items 3 and 7): one line naming the fix, exit 2, no traceback, bounded time."""

import random
import shutil
import sqlite3
import subprocess
import sys
import time

import h5py
import numpy as np
import pytest

from dmdsm.host.scan.catalogue import list_scans
from dmdsm.sim.data.dataset import make_database

LIMIT_S = 40  # a damaged file read in SWMR mode once hung for > 500 s


@pytest.fixture(scope="module")
def good(tmp_path_factory):
    db = tmp_path_factory.mktemp("db")
    (path,) = make_database(db, points=8, seed=1, objects=["soda_can"])
    return db, path


def damaged(kind: str, good_file, where):
    data = good_file.read_bytes()
    rng = random.Random(kind)
    out = where / f"{kind}.h5"
    if kind == "empty":
        out.write_bytes(b"")
    elif kind.startswith("cut"):
        out.write_bytes(data[:int(kind[3:])])
    elif kind == "flipped":
        b = bytearray(data)
        for _ in range(200):
            i = rng.randrange(len(b))
            b[i] ^= 1 << rng.randrange(8)
        out.write_bytes(bytes(b))
    elif kind == "text":
        out.write_text("[calibration]\nv = [0, 1, 0]\n")
    elif kind == "other_hdf5":
        with h5py.File(out, "w") as f:
            f["x"] = np.arange(3)
    elif kind == "wrong_shape":
        shutil.copy(good_file, out)
        with h5py.File(out, "r+") as f:
            del f["/entry/data/distance_oa_mm"]
            f["/entry/data/distance_oa_mm"] = np.zeros((2, 2))
    elif kind == "marked_open":  # a writer killed in SWMR mode, then damaged
        shutil.copy(good_file, out)
        subprocess.run([sys.executable, "-c", "import h5py, os, sys; f = h5py.File(sys.argv[1], "
                        "'r+', libver='latest'); f.swmr_mode = True; os._exit(0)", str(out)],
                       check=True)
        b = bytearray(out.read_bytes())
        for i in range(2000, len(b), 997):
            b[i] ^= 0xFF
        out.write_bytes(bytes(b))
    return out


KINDS = ["empty", "cut100", "cut3000", "cut40000", "flipped", "text", "other_hdf5",
         "wrong_shape", "marked_open"]


def run(*args, cwd=None):
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "dmdsm.host", *args], capture_output=True,
                       text=True, timeout=LIMIT_S + 60, cwd=cwd)
    return r, time.perf_counter() - t0


def one_line_error(r, took):
    assert took < LIMIT_S, took
    assert r.returncode == 2, (r.returncode, r.stderr[-500:])
    assert "Traceback" not in r.stderr, r.stderr[-2000:]
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("dmdsm: error:"), r.stderr


@pytest.mark.parametrize("kind", KINDS)
def test_reconstruct_and_predict_refuse_a_damaged_scan_file(good, tmp_path, kind):
    _, path = good
    bad = damaged(kind, path, tmp_path)
    one_line_error(*run("reconstruct", str(bad), "--json"))
    model = tmp_path / "none.model"
    model.write_bytes(b"")
    one_line_error(*run("classify", "predict", "--model", str(model), "--scan", str(bad)))


def test_db_rebuild_skips_damaged_files_and_names_them(good, tmp_path):
    db, path = good
    copy = tmp_path / "db"
    shutil.copytree(db, copy)
    for kind in ("cut3000", "flipped", "empty"):
        shutil.copy(damaged(kind, path, tmp_path), copy / "scans" / f"{kind}.h5")
    r, took = run("db", "rebuild", "--db", str(copy))
    assert r.returncode == 0 and took < LIMIT_S, r.stderr
    assert "indexed 1 scan files" in r.stdout and "3 left out" in r.stdout
    assert r.stderr.count("dmdsm: skipped") == 3 and "Traceback" not in r.stderr


@pytest.mark.parametrize("damage", ["garbage", "empty", "other_table"])
def test_a_damaged_catalogue_is_one_line_and_rebuild_replaces_it(good, tmp_path, damage):
    db, _ = good
    copy = tmp_path / "db"
    shutil.copytree(db, copy)
    cat = copy / "catalogue.sqlite"
    if damage == "garbage":
        cat.write_bytes(bytes(random.Random(1).randrange(256) for _ in range(5000)))
    elif damage == "empty":
        cat.write_bytes(b"")
    else:
        cat.unlink()
        with sqlite3.connect(cat) as con:
            con.execute("CREATE TABLE scans (x TEXT)")
        con.close()
    if damage != "empty":  # an empty file is a valid empty SQLite database
        for args in (("db", "list", "--db", str(copy)), ("db", "show", "x", "--db", str(copy)),
                     ("classify", "train", "--db", str(copy), "-o", str(tmp_path / "m"))):
            r, took = run(*args)
            one_line_error(r, took)
            assert "db rebuild" in r.stderr, r.stderr
    r, took = run("db", "rebuild", "--db", str(copy))
    assert r.returncode == 0, r.stderr
    rows = list_scans(copy)
    assert [x["status"] for x in rows] == ["complete"]


def test_a_recording_from_acquire_given_as_a_scan_is_named(tmp_path):
    """The two HDF5 files a user makes look alike; the error says which one was given."""
    rec = tmp_path / "shots.h5"
    with h5py.File(rec, "w") as f:
        f.attrs.update(format_name="dmdsm-shots", format_version="1")
        f["/entry/data/waveforms"] = np.zeros((2, 16), np.uint16)
    r, took = run("reconstruct", str(rec))
    one_line_error(r, took)
    assert "is a recording from `dmdsm acquire`, not a scan" in r.stderr


def test_a_catalogue_from_before_auto_scans_gains_the_coverage_column(good, tmp_path):
    """A catalogue written before scans had a coverage keeps its rows and opens; the column
    is added, empty, and `db list` shows no coverage for those scans."""
    db, _ = good
    copy = tmp_path / "db"
    shutil.copytree(db, copy)
    cat = copy / "catalogue.sqlite"
    with sqlite3.connect(cat) as con:
        con.execute("ALTER TABLE scans DROP COLUMN coverage")
    con.close()
    rows = list_scans(copy)
    assert [x["status"] for x in rows] == ["complete"] and rows[0]["coverage"] == ""
    r, took = run("db", "list", "--db", str(copy))
    assert r.returncode == 0 and "cov" not in r.stdout and "complete" in r.stdout, r.stderr
