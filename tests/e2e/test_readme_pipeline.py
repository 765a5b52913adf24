"""README's "The same pipeline by hand" runs as written, line by line in bash, against the
emulator that `dmdsm sim --link-dir /tmp/dmdsm` would start (issue 30: it did not)."""

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dmdsm.sim.servers.emulator import Emulator
from dmdsm.sim.servers.runner import SimConfig

ROOT = Path(__file__).resolve().parents[2]
BIN = Path(sys.executable).parent


def hand_pipeline() -> str:
    text = (ROOT / "README.md").read_text()
    part = text[text.index("**The same pipeline by hand.**"):]
    return re.search(r"```sh\n(.*?)```", part, re.S).group(1)


def test_the_readme_positions_are_the_emulators():
    """The numbers the README gives are what `dmdsm sim --positions` prints (they cannot go
    stale when the emulator's truth changes)."""
    script = hand_pipeline()
    out = subprocess.run([str(BIN / "dmdsm"), "sim", "--positions"], capture_output=True,
                         text=True, check=True).stdout
    start = re.search(r"--start-distance ([\d.]+)\)", out).group(1)
    tip = re.search(r"tip: +--at ([\d. -]+) \(", out).group(1).strip()
    edge = re.search(r"edge: +--at ([\d. -]+) \(", out).group(1).strip()
    assert f"--start-distance {start}" in script and f"face {start} mm" in script
    assert f"--at {tip}\n" in script and f"--at {edge} -o" in script


@pytest.mark.realtime
def test_the_readme_hand_pipeline_runs_as_written(tmp_path):
    link = tmp_path / "dmdsm"  # the README's /tmp/dmdsm, one per test run
    script = hand_pipeline().replace("/tmp/dmdsm", str(link))
    work = tmp_path / "work"
    work.mkdir()
    env = {**os.environ, "PATH": f"{BIN}:{os.environ['PATH']}"}
    with Emulator(SimConfig(), speed=5.0, link_dir=str(link)):
        r = subprocess.run(["bash", "-e", "-c", script], cwd=work, env=env, text=True,
                           capture_output=True, timeout=3000)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    cal = (work / "calibration.toml").read_text()
    assert "v = " in cal and "X_R = " in cal
    # the block's contour meets the paper's scale of error with the hand calibration
    rec = subprocess.run([str(BIN / "dmdsm"), "reconstruct", "validation/scans/block.h5",
                          "--box-mm", "50", "30", "--json"], cwd=work, env=env, text=True,
                         capture_output=True, check=True)
    fits = json.loads(rec.stdout)["validation"]
    assert fits["oa"]["e_mean_mm"] < 0.3 and fits["us"]["e_mean_mm"] < 0.5, fits
    assert (work / "block.png").stat().st_size > 0 and (work / "block.ply").exists()
    rows = json.loads(subprocess.run([str(BIN / "dmdsm"), "db", "list", "--db", "db", "--json"],
                                     cwd=work, env=env, text=True, capture_output=True,
                                     check=True).stdout)
    assert sorted(x["object_id"] for x in rows) == ["paper_cup", "soda_can"]
    assert all(x["status"] == "complete" for x in rows)
    assert list((work / "classify").glob("confusion_*.csv"))
    assert np.isfinite(fits["oa"]["e_std_mm"])
