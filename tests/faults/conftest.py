"""Fixtures shared by the fault suites: inputs the file-writing commands run on."""

import pytest

from dmdsm.sim.data.dataset import make_database


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """A small database with one scan, and calibration raw points that solve."""
    from test_calibration import synth
    from test_calibration_cli import write_raw

    base = tmp_path_factory.mktemp("inputs")
    (scan,) = make_database(base / "db", points=8, seed=2, objects=["soda_can"])
    rig = base / "rig.csv"
    write_raw(rig, synth(radius=0.25))
    return {"db": base / "db", "scan": scan, "scan_id": scan.stem, "rig": rig}
