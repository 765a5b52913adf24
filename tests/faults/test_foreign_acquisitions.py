"""`dmdsm range` on HDF5 files it did not write: any structure is one line naming what is
wrong, never a traceback (issue 30: a valid HDF5 file from another program was a
`ValueError: Field names only allowed for compound types`)."""

import subprocess
import sys

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dmdsm.host.commands.errors import CliError
from dmdsm.host.commands.range import read_acquisition

KINDS = ["plain", "compound", "group", "missing", "scalar", "strings", "2d"]


def _put(g, name, kind, n):
    if kind == "missing":
        return
    if kind == "group":
        g.create_group(name)
    elif kind == "compound":
        g[name] = np.zeros(n, dtype=[("a", "i4"), ("b", "f8")])
    elif kind == "scalar":
        g[name] = 1.0
    elif kind == "strings":
        g[name] = np.array([b"x"] * n)
    elif kind == "2d":
        g[name] = np.zeros((n, 3))
    else:
        g[name] = (np.ones(n, bool) if name == "received" else np.arange(n))


def _write(path, fmt, kinds, n, samples, tick):
    with h5py.File(path, "w") as f:
        if fmt is not None:
            f.attrs["format_name"] = fmt
        d = f.create_group("entry/data")
        s = f.create_group("entry/instrument/sensor")
        if tick is not None:
            s.attrs["tick_hz"] = tick
        if kinds[0] == "plain":
            d["waveforms"] = np.full((n, samples), 32768, np.uint16)
        else:
            _put(d, "waveforms", kinds[0], n)
        for name, kind in zip(("received", "trigger_phase", "shot_id"), kinds[1:]):
            _put(d, name, kind, n)


@settings(max_examples=80, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(fmt=st.sampled_from([None, "dmdsm-shots", "other", 3]),
       kinds=st.lists(st.sampled_from(KINDS), min_size=4, max_size=4),
       n=st.integers(0, 5), samples=st.integers(1, 64),
       tick=st.sampled_from([None, 1e6, 0.0, float("nan"), -5.0, "x"]))
def test_any_hdf5_layout_is_read_or_refused_in_one_line(tmp_path, fmt, kinds, n, samples,
                                                        tick):
    path = tmp_path / "f.h5"
    _write(path, fmt, kinds, n, samples, tick)
    try:
        x, phase, pre, ids = read_acquisition(path)
    except CliError as e:
        assert "\n" not in str(e) and str(path) in str(e)
        return
    assert fmt == "dmdsm-shots" and all(k == "plain" for k in kinds)
    assert x.shape == (n, samples) and len(phase) == len(ids) == n


@pytest.mark.parametrize("content", [b"", b"not hdf5 at all", b"\x89HDF\r\n\x1a\n" + b"\0" * 64])
def test_range_on_a_file_that_is_not_hdf5_is_one_line(tmp_path, content):
    path = tmp_path / "x.h5"
    path.write_bytes(content)
    (tmp_path / "ranging.json").write_text("{}")
    r = subprocess.run([sys.executable, "-m", "dmdsm.host", "range", str(path)], cwd=tmp_path,
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
