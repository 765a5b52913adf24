"""Hostile input files (issue 19, item 7): a ranging calibration of any JSON shape and rig data
with any cell changed either load or give one clear error; never another exception."""

import json

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from dmdsm.host.calibration.rig_file import COLUMNS, read_raw
from dmdsm.host.calibration.solver import CalibrationError
from dmdsm.host.ranging.calibrate import RangeCal, RangingSetup
from dmdsm.host.ranging.matched_filter import gaussian_pulse

FS = 240e6 / 72
GOOD = RangingSetup(FS, {"oa": gaussian_pulse(FS, 1e6, 0.8)}, {"oa": (0, 1024)},
                    {"oa": RangeCal("oa", 2e-6, 343e3, 1e-8, 0, 0.05, 21)}).to_json()

json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=5),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner,
                                                                max_size=4), max_leaves=20)


def mutate(obj, path, value):
    """obj with the item at path (keys/indices) replaced by value."""
    if not path:
        return value
    head, rest = path[0], path[1:]
    if isinstance(obj, dict) and head in obj:
        return {**obj, head: mutate(obj[head], rest, value)}
    if isinstance(obj, list) and isinstance(head, int) and head < len(obj):
        return obj[:head] + [mutate(obj[head], rest, value)] + obj[head + 1:]
    return obj


PATHS = [(), ("fs_hz",), ("modalities",), ("modalities", "oa"), ("modalities", "oa", "template"),
         ("modalities", "oa", "template", 3), ("modalities", "oa", "center"),
         ("modalities", "oa", "gate"), ("modalities", "oa", "calibration"),
         ("modalities", "oa", "calibration", "t0_s"), ("modalities", "oa", "calibration", "c_mm_s"),
         ("format",)]


def test_the_good_file_loads():
    assert RangingSetup.from_json(GOOD).cals["oa"].t0_s == 2e-6


@settings(max_examples=300)
@given(where=st.sampled_from(PATHS), value=json_values)
@example(where=("modalities", "oa", "calibration"), value={"\n": None})  # a key with a newline
@example(where=("modalities",), value={"\r\x1b[2J": 1})  # terminal control codes in a key
@example(where=("modalities", "oa", "gate"), value=[float("inf")])  # int(Infinity) overflows
def test_any_shape_of_ranging_json_loads_or_is_one_clear_error(where, value):
    text = json.dumps(mutate(json.loads(GOOD), where, value))
    try:
        setup = RangingSetup.from_json(text)
    except ValueError as e:
        assert str(e) and str(e).isprintable()
        return
    setup.check()  # what loads is usable


def rig_rows(tmp_path):
    rows = ["step,frame,line,theta_deg,sx_mm,sy_mm,sz_mm,d_mm,amplitude,modality"]
    for i in range(6):
        rows.append(f"tip,{i // 3},{i % 3},0.0,{235 + i * 0.1},266.0,20.0,6.5,1.0,oa")
    path = tmp_path / "rig.csv"
    path.write_text("\n".join(rows) + "\n")
    return path


@pytest.mark.parametrize("column, value, words", [
    ("sx_mm", "1e308", "sx_mm must be a stage position"),
    ("sy_mm", "inf", "sy_mm must be a stage position"),
    ("sz_mm", "nan", "sz_mm must be a stage position"),
    ("d_mm", "-3", "d_mm must be a distance"),
    ("step", "7", "step must be tip or edge"),
    ("frame", "1.5", "frame must be a whole number"),
    ("amplitude", "-inf", "amplitude must be a finite number"),
    ("sx_mm", "abc", "not a number"),
])
def test_a_bad_rig_row_is_named(tmp_path, column, value, words):
    path = rig_rows(tmp_path)
    lines = path.read_text().splitlines()
    cells = lines[3].split(",")
    cells[COLUMNS.index(column)] = value
    lines[3] = ",".join(cells)
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(CalibrationError, match=words):
        read_raw(path)
    with pytest.raises(CalibrationError, match="line 4"):  # every refusal names its line
        read_raw(path)


def test_good_rig_rows_load(tmp_path):
    raw = read_raw(rig_rows(tmp_path))
    assert len(raw["d_mm"]) == 6 and np.isfinite(raw["d_mm"]).all()
