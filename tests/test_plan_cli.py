"""`dmdsm plan new` / `plan show`, `sim --list-scenes` / `--positions` and `reconstruct
--box-mm`: the files and numbers the README's hand pipeline takes from commands (issue 30)."""

import subprocess
import sys
import tomllib

import numpy as np
from hypothesis import example, given, settings
from hypothesis import strategies as st

from dmdsm.host.scan.plan import load_plan, plan_for_size

CMD = [sys.executable, "-m", "dmdsm.host"]


def run(*args, cwd=None):
    return subprocess.run(CMD + list(args), capture_output=True, text=True, timeout=120,
                          cwd=cwd)


def test_plan_new_writes_a_plan_scan_reads(tmp_path):
    r = run("plan", "new", "soda_can", "--size-mm", "66", "66", "122", "--round",
            "--material", "aluminium", "--mode", "fly", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    plan = load_plan(tmp_path / "soda_can.toml")
    assert (plan.object_id, plan.material, plan.mode) == ("soda_can", "aluminium", "fly")
    assert plan.radius_mm == 34.0 and plan.levels_mm == [40.0] and plan.step_mm == 2.0
    assert "96 points" in r.stdout
    again = run("plan", "new", "soda_can", "--size-mm", "66", "66", "122", cwd=tmp_path)
    assert again.returncode == 2 and "--force" in again.stderr  # never over a plan
    assert load_plan(tmp_path / "soda_can.toml").mode == "fly"
    box = run("plan", "new", "block", "--size-mm", "50", "30", "40", "-o", "b.toml",
              cwd=tmp_path)
    assert box.returncode == 0 and load_plan(tmp_path / "b.toml").radius_mm == 30.2  # diagonal
    shown = run("plan", "show", "b.toml", cwd=tmp_path)
    assert shown.returncode == 0 and "36 points" in shown.stdout


def test_plan_new_says_what_a_sweep_or_an_auto_plan_scans_in_plain_numbers(tmp_path):
    r = run("plan", "new", "mug", "--size-mm", "80", "80", "95", "--mode", "sweep",
            cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert "the table turning at each height from 4.5 to 92.5 mm, 2 mm apart" in r.stdout
    plan = load_plan(tmp_path / "mug.toml")
    assert plan.mode == "sweep" and f"{plan.n_points()} points" in r.stdout
    a = run("plan", "new", "mug", "--size-mm", "80", "80", "95", "--mode", "auto", "-o",
            "a.toml", cwd=tmp_path)
    assert a.returncode == 0 and "levels [4.5, 6.5, 8.5," in a.stdout and "np." not in a.stdout
    # a box (not --round): the beam through the middles of equal strips of its width, as
    # many as reach.box_passes needs for each modality to see its faces (docs/scanning.md);
    # a box whose near faces are out of US reach from 8 mm outside its cylinder (a 120 x 60
    # tissue box: 46 mm head on) is swept from 3 mm; a round body with a handle
    # (--reach-mm): three passes, through the axis (where its body is met head on) and a
    # quarter to either side
    b = run("plan", "new", "box", "--size-mm", "50", "30", "40", "--mode", "sweep", cwd=tmp_path)
    assert b.returncode == 0 and "8 mm outside a 30.2 mm cylinder; 5 passes, the beam " \
        "-20, -10, +0, +10, +20 mm off the table axis" in b.stdout, b.stdout
    assert load_plan(tmp_path / "box.toml").offsets_mm == [-20.0, -10.0, 0.0, 10.0, 20.0]
    t = run("plan", "new", "tissues", "--size-mm", "120", "60", "90", "--material", "paper",
            "--mode", "sweep", cwd=tmp_path)
    assert t.returncode == 0 and "3 mm outside a 68.1 mm cylinder; 8 passes" in t.stdout, \
        t.stdout
    assert load_plan(tmp_path / "tissues.toml").standoff_mm == 3.0
    # a box so tall its passes would pass the point limit: one, and the plan says so
    tall = run("plan", "new", "tall", "--size-mm", "120", "60", "200", "--material", "paper",
               "--mode", "sweep", cwd=tmp_path)
    assert tall.returncode == 0 and "passes" not in tall.stdout.splitlines()[0], tall.stdout
    assert "note: one pass, through the axis, not 8: the plan has" in tall.stdout
    assert "one pass" in load_plan(tmp_path / "tall.toml").notes
    foam = run("plan", "new", "foam", "--size-mm", "120", "60", "90", "--material", "foam",
               "--mode", "sweep", cwd=tmp_path)  # OA alone: in reach, seen to 30 deg
    assert foam.returncode == 0 and "8 mm outside a 68.1 mm cylinder; 4 passes" in \
        foam.stdout, foam.stdout
    m = run("plan", "new", "cup", "--size-mm", "113.5", "80", "95", "--reach-mm", "73.5",
            "--mode", "sweep", cwd=tmp_path)
    assert m.returncode == 0 and "3 passes, the beam +0, +28.4, -28.4 mm off the table axis" \
        in m.stdout, m.stdout


def test_plan_new_scans_a_one_modality_material_in_its_modality(tmp_path):
    """Steel and glass give no OA pulse, foam no US echo: a plan of them in "both" would hear
    lone pulses it cannot read and see nothing (tests/e2e/test_auto_one_modality.py), so
    `plan new` takes the material's modality unless --modality says otherwise."""
    for material, modality in (("steel", "us"), ("Glass", "us"), ("foam", "oa"),
                               ("aluminium", "both"), ("", "both")):
        r = run("plan", "new", "x", "--size-mm", "70", "70", "90", "--round", "--material",
                material, "-o", f"{material or 'none'}.toml", cwd=tmp_path)
        assert r.returncode == 0, r.stderr
        assert load_plan(tmp_path / f"{material or 'none'}.toml").modality == modality, material
    r = run("plan", "new", "x", "--size-mm", "70", "70", "90", "--material", "steel",
            "--modality", "both", "-o", "asked.toml", cwd=tmp_path)
    assert r.returncode == 0 and load_plan(tmp_path / "asked.toml").modality == "both"


def test_plan_new_takes_the_reach_of_an_object_not_centred_by_its_footprint(tmp_path):
    """--reach-mm: the farthest point from the table axis (a mug's handle, its body on the
    axis) sets the bounding cylinder; less than half the width cannot be and is refused."""
    r = run("plan", "new", "mug", "--size-mm", "117", "80", "95", "--reach-mm", "73.5",
            "--mode", "auto", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert load_plan(tmp_path / "mug.toml").radius_mm == 74.5
    bad = run("plan", "new", "mug", "--size-mm", "117", "80", "95", "--reach-mm", "50",
              "-o", "bad.toml", cwd=tmp_path)
    assert bad.returncode == 2 and len(bad.stderr.strip().splitlines()) == 1
    assert "less than half the object's width or depth (58.5 mm)" in bad.stderr
    assert not (tmp_path / "bad.toml").exists()
    nan = run("plan", "new", "mug", "--size-mm", "117", "80", "95", "--reach-mm", "nan",
              "-o", "bad.toml", cwd=tmp_path)
    assert nan.returncode == 2 and "the reach must be a finite number of mm" in nan.stderr


def test_plan_new_refuses_a_size_it_cannot_scan(tmp_path):
    for size in (["0", "10", "10"], ["nan", "10", "10"], ["10", "10", "-1"],
                 ["900", "900", "10"]):
        r = run("plan", "new", "x", "--size-mm", *size, cwd=tmp_path)
        assert r.returncode == 2 and "Traceback" not in r.stderr, size
        assert len(r.stderr.strip().splitlines()) == 1
        assert not (tmp_path / "x.toml").exists()


@settings(max_examples=60, deadline=None)
@given(w=st.floats(1, 250), d=st.floats(1, 250), h=st.floats(5, 400), round_=st.booleans(),
       mode=st.sampled_from(["step", "fly", "auto", "sweep"]))
@example(w=1.0, d=80.0, h=100.0, round_=False, mode="sweep")  # 3 passes: over the point limit
@example(w=1.0, d=107.0, h=218.0, round_=False, mode="sweep")  # a sweep's pitch from the width
def test_a_plan_for_any_size_that_fits_the_scanner_loads_back_the_same(w, d, h, round_, mode):
    plan = plan_for_size("obj", (w, d, h), round_, "paper", mode)
    doc = tomllib.loads(plan.to_toml())
    assert doc["object"]["radius_mm"] >= max(w, d) / 2 and doc["scan"]["levels_mm"][0] <= h
    if mode in ("auto", "sweep"):  # every 2 mm over the height, clear of the turntable
        lv = doc["scan"]["levels_mm"]
        assert lv[0] >= 4.5 and np.allclose(np.diff(lv), 2.0) and lv[-1] > h - 3.0
    assert plan.hash() == plan_for_size("obj", (w, d, h), round_, "paper", mode).hash()


def test_sim_lists_each_scenes_objects_with_material_and_size():
    out = run("sim", "--list-scenes").stdout
    line = next(x for x in out.splitlines() if x.startswith("aluminium_block "))
    assert "aluminium box 50.0 x 30.0 x 40.0 mm" in line
    assert any(x.startswith("soda_can ") and "66.0 x 66.0 x 122.0 mm" in x
               for x in out.splitlines())


def test_reconstruct_names_a_plan_given_as_the_truth(tmp_path):
    run("plan", "new", "block", "--size-mm", "50", "30", "40", cwd=tmp_path)
    from dmdsm.host.commands.db import load_truth
    from dmdsm.host.commands.errors import CliError
    try:
        load_truth(tmp_path / "block.toml")
        raise AssertionError("a plan passed as a truth file")
    except CliError as e:
        assert "is a scan plan, not a truth file" in str(e) and "--box-mm" in str(e)


def test_one_vocabulary_across_commands():
    """Issue 30: --calibration was the scanner TOML in scan but ranging.json in range; --step
    was mm in calibrate-range but tip|edge in calibrate; a start position was -x/-y/-z in one
    command and --at in another. Each name now means one thing in every command's help."""
    helps = {c: " ".join(run(*c.split(), "--help").stdout.split())
             for c in ("calibrate-range", "calibrate", "range", "scan")}
    for c in ("calibrate-range", "calibrate"):
        assert "--at X Y Z" in helps[c]
    assert "--step-mm" in helps["calibrate-range"] and "--step {tip,edge}" in helps["calibrate"]
    assert "--step " not in helps["calibrate-range"].replace("--step-mm", "")
    for c in ("range", "scan", "calibrate"):
        assert "--ranging" in helps[c], c
    assert "--calibration" not in helps["range"] and "--calibration" in helps["scan"]
    assert " -x " not in helps["calibrate-range"]


def test_calibrate_range_without_a_position_says_what_to_give(tmp_path):
    r = run("calibrate-range", "--sensor", "loop://", "--stage", "loop://",
            "--start-distance", "7", cwd=tmp_path)
    assert r.returncode == 2 and "give --at X Y Z" in r.stderr
