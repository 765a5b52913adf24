"""Plans a user writes by hand are checked at once (issue 19, items 3, 7, 8): absurd sizes,
values the sensor board cannot take, non-finite numbers and a missing level are one-line
errors in bounded time, never a long silent expansion."""

import subprocess
import sys
import time

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dmdsm.host.scan.plan import MAX_POINTS, PlanError, load_plan

BASE = {"levels_mm": "[20.0]", "half_width_mm": "32.0", "step_mm": "2.0"}


def plan_text(**scan: str) -> str:
    keys = {**BASE, **scan}
    body = "\n".join(f"{k} = {v}" for k, v in keys.items() if v is not None)
    return ('[sample]\nobject_id = "block"\n[object]\nradius_mm = 30.0\nheight_mm = 40.0\n'
            f"[scan]\n{body}\n")


@pytest.mark.parametrize("change, words", [
    ({"half_width_mm": "1e9"}, "more than the machine's longest travel"),
    ({"half_width_mm": "400", "step_mm": "0.001"}, "points (at most"),
    ({"step_mm": "0.0001", "half_width_mm": "100.0"}, "points (at most"),
    ({"samples": "99999999"}, "samples = 99999999 is outside"),
    ({"average": "70000"}, "average = 70000 is outside"),
    ({"half_width_mm": "nan"}, "must be positive"),
    ({"levels_mm": "[inf]"}, "levels_mm[0] must be a finite number"),
    ({"levels_mm": None}, "levels_mm is required"),
    ({"levels_mm": '"abc"'}, "levels_mm must be a list of numbers in mm"),
    ({"levels_mm": "20.0"}, "levels_mm must be a list of numbers in mm, e.g. levels_mm = [12"),
    ({"angles_deg": '[0, "90"]'}, "angles_deg must be a list of numbers in deg"),
    ({"angles_deg": "[true]"}, "angles_deg must be a list of numbers in deg"),
])
def test_a_bad_plan_is_one_line_at_once(tmp_path, change, words):
    path = tmp_path / "plan.toml"
    path.write_text(plan_text(**change))
    t0 = time.perf_counter()
    with pytest.raises(PlanError, match=words.replace("(", r"\(").replace("[", r"\[")):
        load_plan(path)
    assert time.perf_counter() - t0 < 1.0


def test_the_scan_command_refuses_a_huge_plan_quickly_and_in_little_memory(tmp_path):
    path = tmp_path / "plan.toml"
    path.write_text(plan_text(half_width_mm="400", step_mm="0.0001"))  # 8e6 points
    code = ("import resource, sys; resource.setrlimit(resource.RLIMIT_AS, (1 << 31, 1 << 31));"
            "from dmdsm.host.commands.cli import main; sys.exit(main(sys.argv[1:]))")
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-c", code, "scan", "--plan", str(path), "--db",
                        str(tmp_path / "db")], capture_output=True, text=True, timeout=60)
    assert time.perf_counter() - t0 < 30
    assert r.returncode == 2 and "points (at most" in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "db").exists()  # a refused scan leaves no database behind


@settings(max_examples=80, deadline=2000)
@given(half=st.floats(allow_nan=True, allow_infinity=True),
       step=st.floats(allow_nan=True, allow_infinity=True),
       n_levels=st.integers(0, 5), samples=st.integers(-10, 10**9))
def test_any_plan_loads_within_bounds_or_is_refused(tmp_path_factory, half, step, n_levels,
                                                   samples):
    path = tmp_path_factory.mktemp("p") / "plan.toml"
    levels = "[" + ", ".join(["20.0"] * n_levels) + "]"
    path.write_text(plan_text(half_width_mm=repr(half),
                              step_mm=repr(step), levels_mm=levels, samples=str(samples)))
    try:
        plan = load_plan(path)
    except PlanError as e:
        assert "\n" not in str(e)
        return
    assert 0 < plan.n_points() <= MAX_POINTS
