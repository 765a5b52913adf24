"""3D model files (issue 33): the round trip, versions under concurrent writers, atomic writes,
hostile files and object ids refused by one line, staleness against the scans, and
`dmdsm db list --models`."""

import errno
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dmdsm.host.entry import main
from dmdsm.host.files import file_hash
from dmdsm.host.model import store
from dmdsm.host.model.store import (
    ARRAYS,
    ModelError,
    ObjectModel,
    list_models,
    load_object_model,
    read_model,
    staleness,
    write_model,
)
from dmdsm.host.scan.catalogue import connect, record
from dmdsm.host.scan.scanfile import PHASES, ScanWriter

HOSTILE_IDS = ["../x", "a/b", "\x00", "\x1b[31m", "", ".", "..", ".hidden", "a b", "a\\b",
               "x" * 101, "/etc", "cup\n"]


def tiny_model(object_id="cup", sources=None, n=6, seed=0, classes=("steel", "glass")):
    """A tetrahedron with n fused points from the given sources."""
    rng = np.random.default_rng(seed)
    sources = sources if sources is not None else [
        {"scan_id": "cup-1", "content_hash": "0" * 64, "material": "steel"}]
    v = np.array([[1.0, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]]) * 10
    prob = rng.uniform(0, 1, (4, len(classes))).astype(np.float32)
    if len(classes):
        prob[1] = np.nan
    return ObjectModel(
        object_id, sources=sources, params={"spacing_mm": 1.0}, summary={"median_sigma_mm": 0.1},
        points_mm=rng.normal(0, 10, (n, 3)),
        points_cov_mm2=np.broadcast_to(np.eye(3) * 0.01, (n, 3, 3)).copy(),
        points_modality=rng.integers(0, 2, n).astype(np.uint8),
        points_scan=np.zeros(n, np.int32), points_row=np.arange(n, dtype=np.int32),
        points_outlier=rng.random(n) < 0.2,
        vertices_mm=v, faces=np.array([[0, 1, 2], [0, 3, 1], [0, 2, 3], [1, 3, 2]], np.int32),
        normals=v / np.linalg.norm(v, axis=1, keepdims=True),
        sigma_mm=np.array([0.1, np.nan, 0.2, 0.3]), support=np.array([3, 0, 2, 1], np.int32),
        supported=np.array([True, False, True, True]), classes=list(classes),
        material_prob=prob)


def same(a: ObjectModel, b: ObjectModel) -> None:
    for name in ARRAYS:
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and x.shape == y.shape, name
        np.testing.assert_array_equal(x, y, err_msg=name)
    for key in ("object_id", "created", "sources", "params", "summary", "classes"):
        assert getattr(a, key) == getattr(b, key), key


def one_line_error(e: pytest.ExceptionInfo, path: object = None) -> str:
    text = str(e.value)
    assert not {"\n", "\x1b", "\x00"} & set(text) and "Traceback" not in text
    assert path is None or str(path) in text, text
    return text


# -- round trip and versions -----------------------------------------------------------------

def test_round_trip_keeps_every_array_and_versions_count_up(tmp_path):
    m = tiny_model()
    p1 = write_model(tmp_path, m)
    assert p1 == tmp_path / "models" / "cup" / "v1.h5" and m.version == 1
    back = read_model(p1)
    same(m, back)
    p = m.material_prob
    assert back.version == 1 and back.material[1] == ""  # a NaN row: no material
    assert [back.material[i] for i in (0, 2, 3)] == [["steel", "glass"][int(np.argmax(p[i]))]
                                                      for i in (0, 2, 3)]
    with h5py.File(p1) as f:
        assert f.attrs["format_name"] == "dmdsm-model" and f.attrs["format_version"] == "1"
        assert f["points_mm"].compression == "gzip"
    p2 = write_model(tmp_path, tiny_model(seed=1))
    assert p2.name == "v2.h5" and load_object_model(tmp_path, "cup").version == 2
    same(load_object_model(tmp_path, "cup", 1), m)
    with pytest.raises(ModelError, match="no version 7 .*versions: 1, 2"):
        load_object_model(tmp_path, "cup", 7)
    with pytest.raises(ModelError, match="no model of jug"):
        load_object_model(tmp_path, "jug")
    assert sorted(os.listdir(p1.parent)) == ["v1.h5", "v2.h5"]  # no temporary files left


@st.composite
def models(draw):
    n, v = draw(st.integers(0, 12)), draw(st.integers(0, 8))
    c = draw(st.integers(0, 3))
    f = draw(st.integers(0, 6)) if v else 0
    fl = st.floats(-1e3, 1e3, allow_nan=False)
    arr = lambda shape, elems, dt: np.array(draw(st.lists(elems, min_size=int(np.prod(shape)),  # noqa: E731
                                                          max_size=int(np.prod(shape)))),
                                            dt).reshape(shape)
    normals = np.random.default_rng(draw(st.integers(0, 99))).normal(size=(v, 3)) + 1e-3
    prob = arr((v, c), st.floats(0, 1), "f4")
    if v and c and draw(st.booleans()):
        prob[0] = np.nan
    supported = arr((v,), st.booleans(), bool)
    sigma = np.where(supported, arr((v,), st.floats(0, 10), "f8"), np.nan)
    n_src = draw(st.integers(1, 3))
    return ObjectModel(
        draw(st.from_regex(r"[A-Za-z0-9][A-Za-z0-9._-]{0,20}", fullmatch=True)),
        sources=[{"scan_id": f"s{k}", "content_hash": draw(st.text(max_size=8)),
                  "material": draw(st.text(max_size=8))} for k in range(n_src)],
        params={"k": draw(st.integers())}, summary={"t": draw(st.text(max_size=20))},
        points_mm=arr((n, 3), fl, "f8"), points_cov_mm2=arr((n, 3, 3), fl, "f8"),
        points_modality=arr((n,), st.integers(0, 1), "u1"),
        points_scan=arr((n,), st.integers(0, n_src - 1), "i4"),
        points_row=arr((n,), st.integers(0, 2**31 - 1), "i4"),
        points_outlier=arr((n,), st.booleans(), bool), vertices_mm=arr((v, 3), fl, "f8"),
        faces=arr((f, 3), st.integers(0, max(v - 1, 0)), "i4"),
        normals=normals / np.linalg.norm(normals, axis=1, keepdims=True), sigma_mm=sigma,
        support=arr((v,), st.integers(0, 1000), "i4"), supported=supported,
        classes=[f"m{k}" for k in range(c)], material_prob=prob)


@settings(max_examples=30)
@given(models())
def test_any_valid_model_reads_back_as_written(m):
    with tempfile.TemporaryDirectory() as d:
        path = write_model(Path(d), m)
        same(read_model(path), m)


WRITER = """
import sys
from pathlib import Path
sys.path.insert(0, {tests!r})
from test_model_store import tiny_model
from dmdsm.host.model.store import write_model
for k in range(3):
    print(write_model(Path(sys.argv[1]), tiny_model(seed=k)).name, flush=True)
"""


def test_two_writers_at_once_get_distinct_versions(tmp_path):
    code = WRITER.format(tests=str(Path(__file__).parent))
    procs = [subprocess.Popen([sys.executable, "-c", code, str(tmp_path)],
                              stdout=subprocess.PIPE, text=True) for _ in range(2)]
    names = [line for p in procs for line in p.communicate(timeout=60)[0].split()]
    assert all(p.returncode == 0 for p in procs)
    assert sorted(names) == sorted(f"v{k}.h5" for k in range(1, 7))
    assert [load_object_model(tmp_path, "cup", k).version for k in range(1, 7)] == [*range(1, 7)]


def test_a_version_taken_between_choosing_and_linking_goes_to_the_next(tmp_path, monkeypatch):
    write_model(tmp_path, tiny_model())
    real = store._versions
    calls = []

    def stale_once(folder):  # the first look misses v1, as another writer's fresh file
        calls.append(folder)
        return {} if len(calls) == 1 else real(folder)

    monkeypatch.setattr(store, "_versions", stale_once)
    m = tiny_model(seed=3)
    assert write_model(tmp_path, m).name == "v2.h5" and m.version == 2
    assert read_model(tmp_path / "models/cup/v2.h5").version == 2
    same(read_model(tmp_path / "models/cup/v2.h5"), m)


# -- atomic writes ------------------------------------------------------------------------

@pytest.mark.parametrize("where", ["writing", "linking"])
def test_a_failed_write_leaves_no_partial_file_and_earlier_versions_intact(tmp_path, monkeypatch,
                                                                          where):
    first = write_model(tmp_path, tiny_model())
    before = file_hash(first)

    def full(*args):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    if where == "writing":
        real = store._write_file

        def half(path, model, version):  # the file is half written when the disk fills
            real(path, model, version)
            with open(path, "r+b") as f:
                f.truncate(os.path.getsize(path) // 2)
            full()

        monkeypatch.setattr(store, "_write_file", half)
    else:
        monkeypatch.setattr(store.os, "link", full)
    with pytest.raises(ModelError) as e:
        write_model(tmp_path, tiny_model(seed=2))
    assert "no space left" in one_line_error(e)
    assert os.listdir(first.parent) == ["v1.h5"] and file_hash(first) == before
    monkeypatch.undo()
    assert write_model(tmp_path, tiny_model(seed=2)).name == "v2.h5"


def test_an_invalid_model_is_refused_before_anything_is_written(tmp_path):
    bad = {"faces": np.array([[0, 1, 9]]), "normals": np.ones((4, 3)),
           "material_prob": np.full((4, 2), 1.5, np.float32), "points_scan": np.full(6, 3),
           "points_mm": np.full((6, 3), np.nan)}
    for name, value in bad.items():
        m = tiny_model()
        setattr(m, name, value)
        with pytest.raises(ModelError, match=name):
            write_model(tmp_path, m)
    m = tiny_model()
    m.points_row = m.points_row.astype(float)  # floats as indices: refused, not cast
    with pytest.raises(ModelError, match="points_row must hold int32"):
        m.validate()
    assert not (tmp_path / "models" / "cup").exists() or not os.listdir(tmp_path / "models/cup")


# -- hostile files and ids ----------------------------------------------------------------

def hostile(kind: str, good: Path, out: Path) -> Path:
    data = good.read_bytes()
    if kind == "truncated":
        out.write_bytes(data[:len(data) // 2])
        return out
    if kind == "text":
        out.write_text("hello")
        return out
    out.write_bytes(data)
    with h5py.File(out, "r+") as f:
        if kind == "format_name":
            f.attrs["format_name"] = "dmdsm-scan"
        elif kind == "format_version":
            f.attrs["format_version"] = "2"
        elif kind == "huge_shape":
            del f["vertices_mm"]
            f.create_dataset("vertices_mm", shape=(6_000_000, 3), dtype="f8", chunks=(1024, 3),
                             compression="gzip")  # declared, never written: a few bytes
        elif kind == "faces_out_of_range":
            f["faces"][0] = [0, 1, 99]
        elif kind == "non_json":
            f.attrs["params"] = "{not json"
        elif kind == "deep_json":
            f.attrs["summary"] = "[" * 200_000 + "]" * 200_000
        elif kind == "json_array_attr":
            f.attrs["sources"] = np.arange(5)
        elif kind == "wrong_dtype":
            del f["faces"]
            f["faces"] = np.zeros((4, 3), "f8")
        elif kind == "external_link":
            del f["normals"]
            f["normals"] = h5py.ExternalLink("/etc/passwd", "/x")
        elif kind == "missing":
            del f["sigma_mm"]
        elif kind == "mismatched_rows":
            del f["support"]
            f["support"] = np.zeros(5, "i4")
    return out


KINDS = ["truncated", "text", "format_name", "format_version", "huge_shape",
         "faces_out_of_range", "non_json", "deep_json", "json_array_attr", "wrong_dtype",
         "external_link", "missing", "mismatched_rows"]


@pytest.mark.parametrize("kind", KINDS)
def test_a_hostile_model_file_is_refused_by_one_line(tmp_path, kind):
    (tmp_path / "db").mkdir()
    good = write_model(tmp_path / "db", tiny_model())
    path = hostile(kind, good, tmp_path / f"{kind}.h5")
    t0 = time.monotonic()
    with pytest.raises(ModelError) as e:
        read_model(path)
    assert time.monotonic() - t0 < 5
    text = one_line_error(e, path)
    assert {"format_name": "not a dmdsm model file", "format_version": "another dmdsm version",
            "huge_shape": "more than 5000000", "faces_out_of_range": "vertex index below 4",
            "non_json": "params is not valid JSON", "wrong_dtype": "faces holds float64",
            "external_link": "normals is missing or not a dataset stored in the file",
            "mismatched_rows": "but other arrays have V = 4"}.get(kind, "") in text


def test_a_fifo_or_folder_given_as_a_model_file_is_named(tmp_path):
    os.mkfifo(tmp_path / "fifo")
    for p in (tmp_path / "fifo", tmp_path, tmp_path / "nothing.h5"):
        with pytest.raises(ModelError) as e:
            read_model(p)
        one_line_error(e, p)


@pytest.mark.parametrize("object_id", HOSTILE_IDS, ids=repr)
def test_object_ids_that_would_leave_the_folder_are_refused(tmp_path, object_id):
    for call in (lambda: write_model(tmp_path, tiny_model(object_id)),
                 lambda: load_object_model(tmp_path, object_id)):
        with pytest.raises(ModelError, match="object id") as e:
            call()
        one_line_error(e)
    assert not (tmp_path / "models").exists() or os.listdir(tmp_path / "models") == []
    assert not (tmp_path.parent / "x").exists()


def test_symbolic_links_out_of_the_models_folder_are_refused(tmp_path):
    db, outside = tmp_path / "db", tmp_path / "outside"
    outside.mkdir()
    good = write_model(outside, tiny_model())  # a model folder elsewhere
    (db / "models").mkdir(parents=True)
    (db / "models" / "cup").symlink_to(good.parent)
    with pytest.raises(ModelError, match="symbolic link") as e:
        load_object_model(db, "cup")
    one_line_error(e)
    with pytest.raises(ModelError, match="symbolic link"):
        write_model(db, tiny_model())
    (db / "models" / "jug").mkdir()
    (db / "models" / "jug" / "v1.h5").symlink_to(good)
    with pytest.raises(ModelError, match="symbolic link"):
        load_object_model(db, "jug")
    connect(db).close()
    status = {r["object_id"]: r["status"] for r in list_models(db)}
    assert status["cup"].startswith("damaged: ") and status["jug"].startswith("damaged: ")


# -- staleness ----------------------------------------------------------------------------

def make_scan(db: Path, scan_id: str, object_id: str, end: str) -> dict:
    """A finished two-point scan in the catalogue, finished at `end` (ISO 8601)."""
    path = db / "scans" / f"{scan_id}.h5"
    w = ScanWriter.create(path, scan_id=scan_id, plan_text="", plan_hash="h", n_samples=8,
                          sensor={"board": "test"}, calibration={"v": [0.0, 1.0, 0.0]},
                          calibration_toml="", ranging_json="{}",
                          sample={"name": object_id, "material": "steel", "notes": ""},
                          program_version="test")
    for i in range(2):
        w.append(np.zeros(8, np.uint16), stage_position_mm=[0.0, 0.0, 0.0], theta_deg=0.0,
                 level=0, column=i, angle_index=0, received=True, attempts=1, n_average=1,
                 timestamp=i, trigger_phase=0, distance_oa_mm=1.0, distance_us_mm=1.0,
                 snr_oa_db=1.0, snr_us_db=1.0, phase_time_s=np.zeros(len(PHASES)),
                 host_time=0.0, point_index=i)
    w.close("complete")
    with h5py.File(path, "r+") as f:
        f["/entry"].attrs.update(start_time=end, end_time=end)
    record(db, scan_id, n_planned=2, content_hash=file_hash(path))
    return {"scan_id": scan_id, "content_hash": file_hash(path), "material": "steel"}


@pytest.fixture
def scanned(tmp_path):
    db = tmp_path / "db"
    connect(db, create=True).close()
    src = [make_scan(db, "cup-a", "cup", "2026-01-01T10:00:00+0000"),
           make_scan(db, "cup-b", "cup", "2026-01-01T12:00:00+0100")]  # 11:00 UTC
    make_scan(db, "jug-a", "jug", "2026-06-01T10:00:00+0000")  # another object
    model = tiny_model(sources=src)
    write_model(db, model)
    return db, model


def test_a_model_of_unchanged_scans_is_ok(scanned):
    db, model = scanned
    assert staleness(db, model) == ["ok"]
    (row,) = list_models(db)
    assert row["status"] == "ok" and staleness(db, row) == ["ok"]
    assert row["n_vertices"] == 4 and row["n_points"] == 6 and row["supported"] == 0.75


def test_a_changed_scan_file_makes_the_model_stale(scanned):
    db, model = scanned
    with h5py.File(db / "scans" / "cup-a.h5", "r+") as f:
        f["/entry/sample"].attrs["notes"] = "edited"
    assert staleness(db, model) == [
        "stale: scan cup-a changed (its file differs from the catalogue's hash)"]
    record(db, "cup-a", n_planned=2, content_hash=file_hash(db / "scans" / "cup-a.h5"))
    assert staleness(db, model) == [
        "stale: scan cup-a changed (the catalogue holds another content hash)"]


def test_a_deleted_scan_makes_the_model_stale(scanned):
    db, model = scanned
    (db / "scans" / "cup-b.h5").unlink()
    assert staleness(db, model) == ["stale: scan cup-b's file is missing"]
    with connect(db) as con:
        con.execute("DELETE FROM scans WHERE scan_id = 'cup-b'")
    assert staleness(db, model) == ["stale: scan cup-b is not in the catalogue"]


def test_a_newer_scan_of_the_object_makes_the_model_stale(scanned):
    db, model = scanned
    make_scan(db, "cup-old", "cup", "2026-01-01T10:30:00+0000")  # before cup-b: left out
    assert staleness(db, model) == ["ok"]
    make_scan(db, "cup-c", "cup", "2026-01-02T09:00:00+0000")
    make_scan(db, "jug-b", "jug", "2026-02-01T09:00:00+0000")
    assert staleness(db, model) == ["stale: scan cup-c is newer"]
    assert list_models(db)[0]["status"] == "stale: scan cup-c is newer"


# -- the listing --------------------------------------------------------------------------

def test_db_list_models_prints_a_line_per_model_and_damaged_ones_too(scanned, capsys):
    db, model = scanned
    hostile_src = [*model.sources, {"scan_id": "gone\x1b[31m\x07", "content_hash": "",
                                    "material": ""}]
    write_model(db, tiny_model(sources=hostile_src))
    (db / "models" / "cup" / "v3.h5").write_bytes(b"\x89HDF\r\n\x1a\n" + b"\0" * 100)
    write_model(db, tiny_model("jug", sources=[], n=0, classes=()))
    assert main(["db", "list", "--db", str(db), "--models"]) == 0
    out = capsys.readouterr().out
    assert "\x1b" not in out and "\x07" not in out
    lines = out.splitlines()
    assert len(lines) == 4, out
    assert lines[0].split()[:2] == ["cup", "v1"] and lines[0].endswith(" ok")
    assert "4 vtx" in lines[0] and "6 pts" in lines[0] and "75.0% supported" in lines[0]
    assert "stale: scan gone\\x1b[31m\\x07 is not in the catalogue" in lines[1]
    assert lines[2].split()[:2] == ["cup", "v3"] and "damaged: " in lines[2]
    assert lines[3].split()[:2] == ["jug", "v1"] and " - " in lines[3] and lines[3].endswith("ok")
    assert main(["db", "list", "--db", str(db), "--models", "--json", "--object", "jug"]) == 0
    (row,) = json.loads(capsys.readouterr().out)
    assert row["object_id"] == "jug" and row["n_points"] == 0 and row["material"] == ""
    assert main(["db", "list", "--db", str(db / "nothing"), "--models"]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1


def test_an_empty_database_lists_no_models(tmp_path, capsys):
    connect(tmp_path, create=True).close()
    assert main(["db", "list", "--db", str(tmp_path), "--models"]) == 0
    assert capsys.readouterr().out.strip() == f"{tmp_path}: no models"
