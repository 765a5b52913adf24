"""`dmdsm db export --format parquet` (issue 33): the Parquet file read back with pandas holds
every waveform of the database's scans, with poses, distances, points, labels and model links
equal to the HDF5 files; unfinished, damaged and other-layout scans are left out and named;
a changed file is named; every scan streams in its own row groups."""

import errno
import json
import os
import re
import shutil
import tempfile
from pathlib import Path

import h5py
import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dmdsm.host.commands.cli import main
from dmdsm.host.files import file_hash
from dmdsm.host.scan.catalogue import list_scans, record
from dmdsm.host.scan.parquet_export import ExportError, export_parquet, schema
from dmdsm.host.scan.points import MODS, scan_points
from dmdsm.host.scan.scanfile import PHASES, ScanWriter, read_scan
from dmdsm.sim.data.dataset import make_database, scan_object

ROOT = Path(__file__).resolve().parents[1]
COPIED = ("point_index", "level", "column", "angle_index", "theta_deg", "received",
          "attempts", "n_average", "timestamp", "trigger_phase", "distance_oa_mm",
          "distance_us_mm", "snr_oa_db", "snr_us_db", "host_time")


def write_scan(db, scan_id, like, rows, status="complete"):
    """A scan file written point by point as a fly scan does (point_index repeats along a
    line), with lost waveforms, into DB and its catalogue; `like` lends the setup."""
    src = read_scan(like, waveforms=False)
    rng = np.random.default_rng(len(scan_id))
    path = db / "scans" / f"{scan_id}.h5"
    w = ScanWriter.create(
        path, scan_id=scan_id, plan_text="# fly\n", plan_hash="fly", n_samples=1024,
        sensor={k: v for k, v in src.sensor.items() if k != "NX_class"},
        calibration={k: src.calibration[k] for k in ("v", "n", "X_R")},
        calibration_toml="", ranging_json=src.ranging_json,
        sample={"name": "mug", "material": "steel", "notes": "hand made"},
        program_version="test")
    for i in range(rows):
        lost = i % 5 == 3
        d = float(rng.uniform(5, 20))
        w.append(np.zeros(1024, np.uint16) if lost else rng.integers(0, 65535, 1024, np.uint16),
                 stage_position_mm=[200.0 + i, 250.0, 20.0 + i % 3], theta_deg=7.5 * i,
                 level=i % 3, column=i % 4, angle_index=i // 4, received=not lost,
                 attempts=2 if lost else 1, n_average=16, timestamp=10**12 + 1000 * i,
                 trigger_phase=i % 72, distance_oa_mm=np.nan if lost or i % 2 else d,
                 distance_us_mm=d + 0.5 if i % 7 == 6 else np.nan, snr_oa_db=30.0 + i,
                 snr_us_db=np.nan if lost else 20.0, phase_time_s=np.zeros(len(PHASES)),
                 host_time=1.7e9 + i, point_index=i // 4)
    w.close(status)
    record(db, scan_id, n_planned=rows,
           content_hash=file_hash(path) if status == "complete" else "")
    return path


@pytest.fixture(scope="module")
def db(tmp_path_factory):
    """Three household objects (both modalities, US only, OA only), a second scan of one,
    and a hand-written fly-like scan with lost waveforms."""
    db = tmp_path_factory.mktemp("pq") / "db"
    paths = make_database(db, points=24, seed=0, objects=["soda_can", "glass_jar", "foam_cup"])
    scan_object(db, "soda_can", 16, seed=10)
    record(db, "soda_can-s10", n_planned=16,
           content_hash=file_hash(db / "scans" / "soda_can-s10.h5"))
    write_scan(db, "mug-fly", paths[0], rows=23)
    return db


def in_order(db, scan_ids):
    """The scans in catalogue order (by start time, to the second, then id)."""
    return [r["scan_id"] for r in list_scans(db) if r["scan_id"] in scan_ids]


def copy_db(db, where):
    shutil.copytree(db, where)
    return where


def check_against_files(df, db, scan_ids):
    """Every column of every row against the scan files."""
    assert list(df["scan_id"].unique()) == scan_ids
    assert len(df) == sum(read_scan(db / "scans" / f"{s}.h5").n_points for s in scan_ids)
    for sid in scan_ids:
        path = db / "scans" / f"{sid}.h5"
        scan = read_scan(path)
        got = df[df["scan_id"] == sid].reset_index(drop=True)
        p = scan.points
        assert len(got) == scan.n_points
        wave = np.stack(got["waveform"].to_numpy())
        assert wave.dtype == scan.waveforms.dtype and wave.tobytes() == scan.waveforms.tobytes()
        for k in COPIED:
            assert got[k].dtype == p[k].dtype, k
            assert np.array_equal(got[k].to_numpy(), p[k], equal_nan=p[k].dtype.kind == "f"), k
        for i, a in enumerate("xyz"):
            assert np.array_equal(got[f"stage_{a}_mm"], p["stage_position_mm"][:, i])
        assert set(got["object_id"]) == {scan.sample["name"]}
        assert set(got["material"]) == {scan.sample["material"]}
        assert set(got["content_hash"]) == {file_hash(path)}
        pts = scan_points(scan)
        for m in MODS:
            has = got[f"point_{m}_x_mm"].notna().to_numpy()
            assert np.array_equal(has, np.isfinite(p[f"distance_{m}_mm"]) & p["received"])
            assert np.array_equal(got["point_index"][has], pts[m]["index"])
            xyz = got[[f"point_{m}_{a}_mm" for a in "xyz"]].to_numpy()
            assert np.array_equal(xyz[has], pts[m]["P"])
            assert np.isnan(xyz[~has]).all()
            std = got[f"distance_std_{m}_mm"].to_numpy()
            assert np.array_equal(std[has], pts[m]["d_std"], equal_nan=True)
            assert np.isnan(std[~has]).all()


def test_every_column_of_every_row_equals_the_scan_files(db, tmp_path):
    out = tmp_path / "all.parquet"
    s = export_parquet(db, out, model_links={"soda_can": "models/soda_can.glb"})
    ids = [r["scan_id"] for r in list_scans(db)]
    assert s["scan_ids"] == ids and s["scans"] == 5 and not s["skipped"] and not s["changed"]
    df = pd.read_parquet(out)
    assert s["rows"] == len(df) == 24 * 3 + 16 + 23 and s["bytes"] == out.stat().st_size
    check_against_files(df, db, ids)
    assert not df.loc[df["scan_id"] == "mug-fly", "received"].all()  # lost ones are rows too
    assert set(df.loc[df["object_id"] == "soda_can", "model"]) == {"models/soda_can.glb"}
    assert set(df.loc[df["object_id"] != "soda_can", "model"]) == {""}
    assert df["scan_id"].dtype == "category" and df["material"].dtype == "category"
    assert [f.name for f in pq.read_schema(out)] == list(df.columns)
    assert not list(tmp_path.glob(".*part*"))  # the temporary file was renamed


def test_the_schema_metadata_has_the_format_rate_and_each_scans_setup(db, tmp_path):
    out = tmp_path / "m.parquet"
    export_parquet(db, out, object_id="soda_can")
    meta = {k.decode(): v.decode() for k, v in pq.read_schema(out).metadata.items()}
    assert meta["format_name"] == "dmdsm-waveforms" and meta["format_version"] == "1"
    assert meta["n_samples"] == "1024" and meta["sample_dtype"] == "uint16"
    scans, setups = json.loads(meta["scans"]), json.loads(meta["ranging_setups"])
    assert list(scans) == in_order(db, ["soda_can-s0", "soda_can-s10"])
    for sid, m in scans.items():
        f = read_scan(db / "scans" / f"{sid}.h5", waveforms=False)
        assert float(meta["sample_rate_hz"]) == f.sensor["adc_rate_hz"]
        assert setups[m["ranging_setup"]] == json.loads(f.ranging_json)
        for k in ("v", "n", "X_R"):
            assert m["calibration"][k] == f.calibration[k]
        assert m["content_hash"] == file_hash(f.path) and m["material"] == "aluminium"
        assert m["rows"] == f.n_points and m["plan"] == f.entry["plan"]


def test_each_scan_streams_in_its_own_row_groups(db, tmp_path):
    out = tmp_path / "g.parquet"
    s = export_parquet(db, out, rows_per_group=10)
    f = pq.ParquetFile(out)
    groups = [f.read_row_group(i, columns=["scan_id"]).column(0).to_pylist()
              for i in range(f.num_row_groups)]
    assert all(len(set(g)) == 1 and len(g) <= 10 for g in groups)  # never two scans in one
    per_scan = {sid: sum(g[0] == sid for g in groups) for sid in s["scan_ids"]}
    assert per_scan == {"soda_can-s0": 3, "glass_jar-s1": 3, "foam_cup-s2": 3,
                        "soda_can-s10": 2, "mug-fly": 3}
    assert s["row_groups"] == f.num_row_groups == 14
    check_against_files(pd.read_parquet(out), db, s["scan_ids"])
    assert export_parquet(db, out)["row_groups"] == 5  # default: 16 MiB of waveforms a group


def test_unfinished_damaged_and_other_layout_scans_are_left_out_and_named(db, tmp_path):
    db = copy_db(db, tmp_path / "db")
    write_scan(db, "mug-cut", db / "scans" / "soda_can-s0.h5", rows=6, status="interrupted")
    scan_object(db, "paper_cup", 8, seed=4, n_samples=512)
    record(db, "paper_cup-s4", n_planned=8, content_hash=file_hash(db / "scans" /
                                                                  "paper_cup-s4.h5"))
    truncated = db / "scans" / "glass_jar-s1.h5"
    truncated.write_bytes(truncated.read_bytes()[:5000])
    with h5py.File(db / "scans" / "foam_cup-s2.h5", "r") as f:  # a waveform chunk, rotten
        info = f["/entry/data/waveforms"].id.get_chunk_info(0)
    with open(db / "scans" / "foam_cup-s2.h5", "r+b") as f:
        f.seek(info.byte_offset + 100)
        f.write(b"\xff" * 200)
    s = export_parquet(db, tmp_path / "x.parquet")
    why = {k["scan_id"]: k["reason"] for k in s["skipped"]}
    assert s["scan_ids"] == in_order(db, ["soda_can-s0", "soda_can-s10", "mug-fly"])
    assert set(why) == {"mug-cut", "paper_cup-s4", "glass_jar-s1", "foam_cup-s2"}
    assert why["mug-cut"].startswith("unfinished (status interrupted, 6 points")
    assert "512 uint16 samples" in why["paper_cup-s4"] and "1024" in why["paper_cup-s4"]
    assert why["glass_jar-s1"].startswith("damaged")
    assert why["foam_cup-s2"].startswith("damaged")
    assert all("\n" not in r for r in why.values())
    check_against_files(pd.read_parquet(tmp_path / "x.parquet"), db, s["scan_ids"])


def test_a_changed_file_is_exported_and_named(db, tmp_path):
    db = copy_db(db, tmp_path / "db")
    path = db / "scans" / "glass_jar-s1.h5"
    before = file_hash(path)
    with h5py.File(path, "r+") as f:
        f["/entry/sample"].attrs["notes"] = "edited"
    s = export_parquet(db, tmp_path / "c.parquet", object_id="glass_jar")
    assert s["changed"] == [{"scan_id": "glass_jar-s1", "catalogue_hash": before,
                             "file_hash": file_hash(path)}]
    df = pd.read_parquet(tmp_path / "c.parquet")
    check_against_files(df, db, ["glass_jar-s1"])  # the column holds the file's own hash


def test_nothing_to_export_is_one_line_and_writes_nothing(db, tmp_path):
    db = copy_db(db, tmp_path / "db")
    (db / "scans" / "foam_cup-s2.h5").write_bytes(b"not hdf5")
    out = tmp_path / "n.parquet"
    with pytest.raises(ExportError, match="nothing to export.*foam_cup-s2: damaged"):
        export_parquet(db, out, scan_ids=["foam_cup-s2"])
    with pytest.raises(ExportError, match=r"no scan 'nope' in .*known: .*soda_can-s0"):
        export_parquet(db, out, scan_ids=["nope"])
    with pytest.raises(ExportError, match="no scans of object 'cup'.*objects: foam_cup"):
        export_parquet(db, out, object_id="cup")
    assert sorted(os.listdir(tmp_path)) == ["db"]


def test_the_command_line_writes_the_file_and_names_what_it_left_out(db, tmp_path, capsys):
    db = copy_db(db, tmp_path / "db")
    (db / "scans" / "foam_cup-s2.h5").write_bytes(b"not hdf5")
    out = tmp_path / "cli.parquet"
    assert main(["db", "export", "--db", str(db), "--format", "parquet", "-o", str(out),
                 "soda_can-s0", "foam_cup-s2", "mug-fly", "--json"]) == 0
    cap = capsys.readouterr()
    s = json.loads(cap.out)
    assert s["scan_ids"] == in_order(db, ["soda_can-s0", "mug-fly"]) and s["rows"] == 24 + 23
    assert re.fullmatch(r"dmdsm: skipped foam_cup-s2: damaged: .*\n", cap.err)
    check_against_files(pd.read_parquet(out), db, s["scan_ids"])
    assert main(["db", "export", "--db", str(db), "--format", "parquet", "--output", str(out),
                 "--object", "soda_can"]) == 0
    assert capsys.readouterr().out.startswith("exported 40 waveforms of 2 scans to")
    assert set(pd.read_parquet(out, columns=["object_id"])["object_id"]) == {"soda_can"}


@pytest.mark.parametrize("argv, message", [
    (["--format", "parquet"], "db export --format parquet needs -o FILE"),
    (["--format", "parquet", "-o", "{out}", "--csv", "x.csv"], "--csv/--ply write one scan"),
    (["--format", "parquet", "-o", "{out}", "nope"], "no scan 'nope'"),
    (["--format", "parquet", "-o", "{out}", "--object", "soda_can", "mug-fly"],
     "scan 'mug-fly' is of object 'mug', not 'soda_can'"),
    (["soda_can-s0", "-o", "{out}"], "-o belongs to --format parquet"),
    (["soda_can-s0", "mug-fly", "--csv", "{out}"], "takes one SCAN_ID (got 2)"),
    (["--csv", "{out}"], "db export needs a SCAN_ID"),
    (["soda_can-s0"], "db export needs --csv FILE and/or --ply FILE"),
])
def test_a_wrong_export_command_is_one_line(db, tmp_path, capsys, argv, message):
    out = tmp_path / "o.parquet"
    rc = main(["db", "export", "--db", str(db), *[a.format(out=out) for a in argv]])
    err = capsys.readouterr().err
    assert rc == 2 and message in err and len(err.strip().splitlines()) == 1, err
    assert not out.exists()


def test_the_csv_export_of_one_scan_still_works(db, tmp_path, capsys):
    out = tmp_path / "p.csv"
    assert main(["db", "export", "soda_can-s0", "--db", str(db), "--csv", str(out)]) == 0
    assert out.read_text().startswith("point_index,modality")


def test_a_full_disk_keeps_the_earlier_file(db, tmp_path, capsys, monkeypatch):
    out = tmp_path / "d.parquet"
    out.write_bytes(b"earlier")

    def no_space(fd):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "fsync", no_space)
    assert main(["db", "export", "--db", str(db), "--format", "parquet", "-o", str(out)]) == 2
    assert f"no space left on the device holding {out}" in capsys.readouterr().err
    assert out.read_bytes() == b"earlier" and os.listdir(tmp_path) == ["d.parquet"]


def test_the_docs_name_every_column(tmp_path):
    text = (ROOT / "docs" / "formats.md").read_text()
    section = text.split("## Parquet export", 1)[1].split("\n## ", 1)[0]
    for f in schema(1024, "uint16"):
        assert f"`{f.name}`" in section, f.name


@settings(max_examples=8)
@given(st.data())
def test_any_selection_of_scans_round_trips(db, data):
    ids = [r["scan_id"] for r in list_scans(db)]
    chosen = data.draw(st.lists(st.sampled_from(ids), min_size=1, unique=True))
    step = data.draw(st.integers(1, 30))
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "s.parquet"
        s = export_parquet(db, out, scan_ids=chosen, rows_per_group=step)
        assert s["scan_ids"] == in_order(db, chosen)
        check_against_files(pd.read_parquet(out), db, s["scan_ids"])
