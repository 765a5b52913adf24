"""Calibration raw-point files: CSV and HDF5 hold the same rows, bad files get one-line errors."""

import subprocess
import sys

import h5py
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dmdsm.host.calibration.rig_file import (
    COLUMNS,
    RawWriter,
    append_rows,
    drop_step,
    read_raw,
    steps_in,
)
from dmdsm.host.calibration.solver import CalibrationError

finite = st.floats(-9999, 9999, allow_nan=False, allow_infinity=False)
row = st.fixed_dictionaries({
    "step": st.sampled_from(["tip", "edge"]), "frame": st.integers(0, 50),
    "line": st.integers(0, 50), "theta_deg": finite, "sx_mm": finite, "sy_mm": finite,
    "sz_mm": finite, "d_mm": st.one_of(st.floats(0, 9999), st.just(float("nan"))),
    "amplitude": st.floats(0, 1e6), "modality": st.sampled_from(["oa", "us"])})


def same(raw, rows):
    """read_raw's arrays hold exactly the rows written (NaN where written as NaN)."""
    assert len(raw["step"]) == len(rows)
    for c in COLUMNS:
        want = [r[c] for r in rows]
        if c in ("step", "modality"):
            assert raw[c].tolist() == want
        else:
            np.testing.assert_array_equal(raw[c], np.array(want, float), err_msg=c)


@settings(max_examples=40, deadline=None)
@given(rows=st.lists(row, min_size=1, max_size=30), split=st.integers(0, 30),
       suffix=st.sampled_from([".csv", ".h5"]))
def test_rows_round_trip_through_both_formats(tmp_path_factory, rows, split, suffix):
    path = tmp_path_factory.mktemp("raw") / ("rig" + suffix)
    append_rows(path, rows[:split])  # appended in two goes, as the two steps do
    append_rows(path, rows[split:])
    same(read_raw(path), rows)


def example_rows(step, n, frame=0):
    return [{"step": step, "frame": frame, "line": i, "theta_deg": 0.0, "sx_mm": 1.0 * i,
             "sy_mm": 2.0, "sz_mm": 3.0, "d_mm": 6.0 + 0.01 * i, "amplitude": 0.5,
             "modality": "oa"} for i in range(n)]


@pytest.mark.parametrize("suffix", [".csv", ".h5"])
def test_each_row_is_on_disk_before_the_next_is_measured(tmp_path, suffix):
    path = tmp_path / ("rig" + suffix)
    w = RawWriter(path)
    w.write(example_rows("tip", 3))
    # what another process sees while the scan goes on (the file still open here)
    look = ("import sys, h5py; f = h5py.File(sys.argv[1], 'r', locking=False); "
            "print(len(f['raw/d_mm']))" if suffix == ".h5" else
            "import sys; print(open(sys.argv[1]).read().count(chr(10)) - 1)")
    seen = subprocess.run([sys.executable, "-c", look, str(path)], capture_output=True,
                          text=True, timeout=60)
    assert seen.stdout.strip() == "3", seen.stderr
    w.close()
    w.close()
    assert steps_in(path) == {"tip"}


@pytest.mark.parametrize("suffix", [".csv", ".h5"])
def test_replace_drops_one_step_and_keeps_the_other(tmp_path, suffix):
    path = tmp_path / ("rig" + suffix)
    append_rows(path, example_rows("tip", 4) + example_rows("edge", 5, frame=1))
    assert drop_step(path, "edge") == 5
    raw = read_raw(path)
    assert raw["step"].tolist() == ["tip"] * 4 and steps_in(path) == {"tip"}
    assert drop_step(path, "edge") == 0
    assert drop_step(path, "tip") == 4 and not path.exists()
    assert steps_in(path) == set()


def test_extra_hdf5_datasets_are_ignored_and_bad_files_named(tmp_path):
    path = tmp_path / "rig.h5"
    append_rows(path, example_rows("tip", 2))
    with h5py.File(path, "a") as f:
        f["raw"].create_dataset("operator_note", data=np.array([b"a", b"b"]))
    assert read_raw(path)["d_mm"].tolist() == [6.0, 6.01]
    with h5py.File(path, "a") as f:
        del f["raw/amplitude"]
    with pytest.raises(CalibrationError, match="lacks column.s. amplitude"):
        read_raw(path)
    with h5py.File(path, "a") as f:
        f["raw"].create_dataset("amplitude", data=np.ones(5))
    with pytest.raises(CalibrationError, match="differ in length"):
        read_raw(path)
    other = tmp_path / "scan.h5"
    with h5py.File(other, "w") as f:
        f.create_group("entry")
    with pytest.raises(CalibrationError, match="not a dmdsm calibration data file"):
        read_raw(other)
    text = tmp_path / "notes.h5"
    text.write_text("step,frame\n")
    with pytest.raises(CalibrationError, match="is not an HDF5 file"):
        read_raw(text)
    with pytest.raises(CalibrationError, match="cannot read .*missing.h5"):
        read_raw(tmp_path / "missing.h5")
    with pytest.raises(CalibrationError, match="not a dmdsm calibration data file"):
        RawWriter(other)


def test_a_csv_with_a_byte_order_mark_reads_and_utf16_is_named(tmp_path):
    """Issue 30: a spreadsheet's UTF-8 BOM gave a false "lacks column(s) step"; a UTF-16 file
    was "not a calibration CSV" with no word of its encoding."""
    path = tmp_path / "rig.csv"
    append_rows(path, example_rows("tip", 2))
    text = path.read_text()
    bom = tmp_path / "bom.csv"
    bom.write_bytes(b"\xef\xbb\xbf" + text.encode())
    assert read_raw(bom)["d_mm"].tolist() == [6.0, 6.01]
    wide = tmp_path / "wide.csv"
    wide.write_bytes(text.encode("utf-16"))
    with pytest.raises(CalibrationError, match="is UTF-16 text: save the CSV as UTF-8"):
        read_raw(wide)


def test_a_value_that_is_not_a_number_is_named_with_its_row(tmp_path):
    """Issue 30: "column sx_mm has a value that is not a number" gave no row."""
    path = tmp_path / "rig.csv"
    append_rows(path, example_rows("tip", 3))
    lines = path.read_text().splitlines()
    header = lines[0].split(",")
    cells = lines[2].split(",")
    cells[header.index("sx_mm")] = "12,5".replace(",", ";")
    lines[2] = ",".join(cells)
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(CalibrationError, match=r"row 2 \(line 3\): column sx_mm has '12;5', "
                                               r"which is not a number"):
        read_raw(path)
