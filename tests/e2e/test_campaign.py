"""`dmdsm campaign` against `dmdsm sim --link-dir` (issue 33): two objects mounted through the
emulator's scene file, auto scanned over one level, modelled, the table printed; Ctrl-C in
the second object's scan and the same command resuming that scan; a third run finding both
done before and scanning nothing; the operator's prompt (s, q) where no emulator mounts."""

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from fly_scan_helpers import setup

from dmdsm.host.model.store import load_object_model
from dmdsm.host.ranging.calibrate import RangingSetup
from dmdsm.host.scan.campaign_file import load_campaign
from dmdsm.host.scan.scanfile import read_scan
from dmdsm.host.scan.session import scan_path
from dmdsm.sim.servers.emulator import Emulator
from dmdsm.sim.servers.runner import SimConfig

# one level each (a narrow band: the first look scans 3 levels about it), the can first; the
# block declared steel, so that the database holds two materials to train a classifier on
OBJECTS = """
[[object]]
id = "can"
material = "aluminium"
size_mm = [67.0, 67.0, 123.0]
round = true
notes = "emptied"
scene = "soda_can"
levels_mm = [20.0]

[[object]]
id = "aluminium_block"
material = "steel"
size_mm = [51.0, 31.0, 41.0]
levels_mm = [20.0]
"""
CAMPAIGN = '[campaign]\nmode = "auto"\n' + OBJECTS


def campaign_cmd(tmp_path, sensor, stage, *extra, toml="campaign.toml"):
    return [sys.executable, "-m", "dmdsm.host", "campaign", str(tmp_path / toml), "--db",
            str(tmp_path / "db"), "--sensor", str(sensor), "--stage", str(stage),
            "--calibration", str(tmp_path / "cal.toml"), "--ranging",
            str(tmp_path / "ranging.json"), *extra]


def points_in(pattern: Path) -> int:
    try:
        return read_scan(next(pattern.parent.glob(pattern.name)), waveforms=False).n_points
    except Exception:
        return 0


def radial_mm(db: Path, object_id: str) -> float:
    """The median distance of the model's supported vertices from the table's axis."""
    m = load_object_model(db, object_id)
    v = m.vertices_mm[m.supported]
    return float(np.median(np.hypot(v[:, 0], v[:, 1])))


@pytest.mark.realtime
def test_a_campaign_mounts_scans_models_stops_and_resumes(tmp_path):
    link = tmp_path / "link"
    (tmp_path / "campaign.toml").write_text(CAMPAIGN)
    times = {}
    with Emulator(SimConfig(scene="aluminium_block", seed=33), speed=4.0,
                  link_dir=str(link)) as emu:
        setup(emu, tmp_path)  # ranging on the block, the emulator's true v, n, X_R
        # a user's own link to the link dir's port: the scene file is found through it
        (tmp_path / "my_sensor").symlink_to(link / "sensor")
        cmd = campaign_cmd(tmp_path, tmp_path / "my_sensor", link / "stage", "--yes")
        block = tmp_path / "db" / "scans" / "aluminium_block-*.h5"
        t0 = time.monotonic()
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
        deadline = time.monotonic() + 400
        while points_in(block) < 100 and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.1)
        os.kill(proc.pid, signal.SIGINT)
        out, err = proc.communicate(timeout=120)
        times["first run (can, part of the block)"] = time.monotonic() - t0
        assert proc.returncode == 130, err[-2000:]
        assert "can: mounted scene soda_can" in out and "aluminium_block: mounted scene " \
            "aluminium_block" in out, out
        assert "campaign stopped at object 2 of 2 (aluminium_block)" in err, err[-2000:]
        assert "run the same command to resume there" in err
        times.update(re.findall(r"^(\S+): done in (\d+) s", out, re.M))
        cut = points_in(block)
        assert cut >= 100
        assert (link / "scene").read_text().strip() == "aluminium_block"
        # the can was scanned and modelled: its model is a cylinder of radius 33 mm
        assert abs(radial_mm(tmp_path / "db", "can") - 33.0) < 2.0
        assert (tmp_path / "db" / "models" / "can").is_dir()
        assert not (tmp_path / "db" / "models" / "aluminium_block").exists()

        t0 = time.monotonic()
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
        times["second run (the rest of the block)"] = time.monotonic() - t0
        assert r.returncode == 0, r.stderr[-2000:]
        assert "can: done before" in r.stdout and "mounted scene soda_can" not in r.stdout
        assert "aluminium_block: resuming aluminium_block-" in r.stdout, r.stdout
        times.update({f"{k} (resumed)": v for k, v in
                      re.findall(r"^(\S+): done in (\d+) s", r.stdout, re.M)})
        assert [o.name for o in emu.sim.truth_objects()] == ["aluminium_block"]
        whole = read_scan(next(block.parent.glob(block.name)), waveforms=False)
        assert whole.entry["status"] == "complete" and whole.n_points > cut
        table = r.stdout[r.stdout.index("object "):].splitlines()
        assert table[0].split()[:3] == ["object", "material", "status"]
        rows = {line.split()[0]: line for line in table[2:4]}
        assert "done before" in rows["can"] and "scanned" in rows["aluminium_block"]
        assert "OA " in rows["aluminium_block"] and "no classifier" in rows["aluminium_block"]
        # the block's model: its faces 15 and 25 mm from the axis (corners further)
        assert 14.0 < radial_mm(tmp_path / "db", "aluminium_block") < 26.0

        # a third run: both done before, nothing scanned, no port needed
        stamps = {p: p.stat().st_mtime_ns for p in (tmp_path / "db" / "scans").glob("*.h5")}
        t0 = time.monotonic()
        r = subprocess.run(cmd + ["--json"], capture_output=True, text=True, timeout=300)
        times["third run (done before)"] = time.monotonic() - t0
        assert r.returncode == 0, r.stderr[-2000:]
        res = json.loads(r.stdout)
        assert [o["status"] for o in res["objects"]] == ["done before", "done before"]
        assert all(o["points"] > 0 and o["vertices"] > 0 and o["model_version"] == 1 and
                   o["coverage"]["oa"] > 0.2 for o in res["objects"]), res
        assert res["objects"][0]["coverage"]["oa"] > 0.7  # the can's outline, at one level
        assert "mounted" not in r.stderr and "resuming" not in r.stderr
        assert stamps == {p: p.stat().st_mtime_ns
                          for p in (tmp_path / "db" / "scans").glob("*.h5")}

        # a classifier (trained on these two scans) named in the file, beside it: the
        # verdicts of objects done before
        r = subprocess.run([sys.executable, "-m", "dmdsm.host", "classify", "train", "--db",
                            str(tmp_path / "db"), "-o", str(tmp_path / "clf.model")],
                           capture_output=True, text=True, timeout=300)
        assert r.returncode == 0, r.stderr[-2000:]
        (tmp_path / "with_classifier.toml").write_text(
            '[campaign]\nclassifier = "clf.model"\n' + OBJECTS)
        r = subprocess.run(campaign_cmd(tmp_path, "x", "y", toml="with_classifier.toml"),
                           capture_output=True, text=True, timeout=300)
        assert r.returncode == 0, r.stderr[-2000:]
        rows = {line.split()[0]: line for line in r.stdout.splitlines()
                if line.startswith(("can ", "aluminium_block "))}
        assert " right" in rows["can"] and " right" in rows["aluminium_block"], r.stdout
        assert "aluminium" in rows["can"].split("done before")[1]
        assert "steel" in rows["aluminium_block"].split("done before")[1]

        # one object failing (its scan file is damaged) is a row with its reason, and the
        # campaign goes on to the next
        jar = '[[object]]\nid = "jar"\nmaterial = "glass"\nsize_mm = [81.0, 81.0, 101.0]\n'
        (tmp_path / "damaged.toml").write_text(jar + OBJECTS)
        plan = load_campaign(tmp_path / "damaged.toml").plan(
            load_campaign(tmp_path / "damaged.toml").objects[0])
        _, damaged = scan_path(plan, (tmp_path / "cal.toml").read_text(),
                               RangingSetup.load(tmp_path / "ranging.json"), tmp_path / "db")
        damaged.write_bytes(b"not a scan" * 100)
        r = subprocess.run(campaign_cmd(tmp_path, "x", "y", toml="damaged.toml"),
                           capture_output=True, text=True, timeout=300)
        assert r.returncode == 1, r.stderr[-2000:]
        rows = {line.split()[0]: line for line in r.stdout.splitlines()
                if line.startswith(("jar ", "can ", "aluminium_block "))}
        assert " failed " in rows["jar"] and "done before" in rows["can"] and \
            "done before" in rows["aluminium_block"], r.stdout
        assert f"jar: failed: {damaged}" in r.stdout and "1 of 3 objects failed" in r.stderr
        damaged.unlink()

        # where no emulator mounts (the pty itself), the operator is asked: s skips, q stops
        (tmp_path / "more.toml").write_text(
            CAMPAIGN + '\n[[object]]\nid = "cup"\nmaterial = "paper"\n'
            'size_mm = [81.0, 81.0, 96.0]\nround = true\n'
            '\n[[object]]\nid = "mug"\nmaterial = "steel"\nsize_mm = [85.0, 85.0, 96.0]\n'
            'round = true\n')
        pts = emu.server.ports
        r = subprocess.run(campaign_cmd(tmp_path, pts["sensor"].path, pts["stage"].path,
                                        toml="more.toml"),
                           input="s\nq\n", capture_output=True, text=True, timeout=300)
        assert r.returncode == 1, r.stderr[-2000:]
        assert "place cup (paper, 81 x 81 x 96 mm) on the table, centred; Enter to scan, " \
            "s to skip, q to stop" in r.stdout, r.stdout
        assert "cup: skipped" in r.stdout and "place mug (steel" in r.stdout
        assert "campaign stopped before object 4 of 4 (mug): q typed" in r.stdout
        assert "0 of 4 objects failed, 2 not scanned" in r.stderr
        assert len(list((tmp_path / "db" / "scans").glob("*.h5"))) == 2
    print("\n" + "\n".join(f"{k}: {float(v):.0f} s" for k, v in times.items()))
