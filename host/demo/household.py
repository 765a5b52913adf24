"""Stage 4 of the demo: the household set, a plan per object from its size, scanned step and fly."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..report.page import Section
from ..scan.plan import ScanPlan, modality_for
from .session import TITLES, Demo, scan_into, write_plan

FIGURES = ("soda_can", "apple_red", "foam_block", "glass_jar", "tissue_box", "steel_can",
           "plastic_bottle")  # the objects whose contours the report shows (Fig. 4)
FLY = {"mode": "fly", "average": 12}  # 12 shots per waveform at 1 kHz, step_mm apart
# (2 mm: 167 mm/s; docs/scanning.md)


def _mm(x: float) -> float:
    """x to 0.1 mm, as the demo's plans give an object's sizes."""
    return round(float(x), 1)


def object_plan(name: str, material: str, radius: float, width: float, height: float,
                modality: str, quick: bool, mode: str) -> ScanPlan:
    """One object's plan: its bounding cylinder (radius + 1 mm) and height, one level at half
    the height (at most 40 mm), the middle 70 % of its width; step and shoot every 4 mm (8 mm
    quick), fly every 2 mm; one angle quick, else four."""
    return ScanPlan(name, material=material, radius_mm=_mm(radius + 1.0), height_mm=_mm(height),
                    levels_mm=[_mm(min(0.5 * height, 40.0))],
                    angles_deg=[0.0] if quick else [0.0, 90.0, 180.0, 270.0],
                    half_width_mm=_mm(0.35 * width),
                    step_mm=(8.0 if quick else 4.0) if mode == "step" else 2.0,
                    modality=modality, turntable_radius_mm=60.0,
                    **(FLY if mode == "fly" else {}))


def stage_household(d: Demo) -> Section:
    """Every household object scanned into one database (Fig. 4 contours)."""
    from dmdsm.sim.physics.objects import HOUSEHOLD, bounding_size, household

    from ..report.plots import contour_figure
    from ..scan.points import scan_points
    from ..scan.scanfile import read_scan

    sec = Section(TITLES["stage_household"])
    names = list(HOUSEHOLD)
    rows: list[list] = []
    wrong: list[str] = []  # scans whose modalities are not those of their material
    for name in names:
        material = HOUSEHOLD[name][0]
        obj = household(name)[0]
        w, dep, height = bounding_size(obj)
        boxy = type(obj.shape).__name__ == "Box"
        radius = float(np.hypot(w, dep) / 2) if boxy else w / 2
        mod = modality_for(material)
        d.mount(name)
        runs: dict[str, dict] = {}
        for mode, db in (("step", "db"), ("fly", "db_fly")):
            plan = object_plan(name, material, radius, w, height, mod, d.quick, mode)
            path = write_plan(d, f"{name}{'' if mode == 'step' else '_fly'}", plan)
            runs[mode] = scan_into(d, path, db)
        s = runs["step"]
        scan = read_scan(Path(s["file"]), waveforms=False)
        p = scan.points
        n_oa = int(np.isfinite(p["distance_oa_mm"]).sum())
        n_us = int(np.isfinite(p["distance_us_mm"]).sum())
        fly = runs["fly"]
        fly_scan = read_scan(Path(fly["file"]), waveforms=False).points
        fly_oa = int(np.isfinite(fly_scan["distance_oa_mm"]).sum())
        fly_us = int(np.isfinite(fly_scan["distance_us_mm"]).sum())
        rows.append([name, material, mod, s["points"], n_oa, n_us, s["points_per_s"],
                     fly["points"], fly_oa, fly_us, fly["points_per_s"]])
        sec.values[name] = {"material": material, "modality": mod, "points": s["points"],
                            "oa_points": n_oa, "us_points": n_us,
                            "fly": {"points": fly["points"], "oa_points": fly_oa,
                                    "us_points": fly_us,
                                    "points_per_s": fly["points_per_s"]}}
        if name in FIGURES:
            contour_figure(scan_points(scan), d.out / f"fig4_{name}.png", title=name)
            sec.figures.append((d.out / f"fig4_{name}.png", f"{name} ({material}): "
                                f"reconstructed points, OA squares, US crosses, lines "
                                f"between neighbours, + the table axis"
                                + ("; one table angle (quick), so one side" if d.quick
                                   else "")))
        expected = {"us": n_oa == 0 and n_us > 0, "oa": n_us == 0 and n_oa > 0,
                    "both": n_oa > 0 and n_us > 0}[mod]
        fly_expected = {"us": fly_oa == 0 and fly_us > 0, "oa": fly_us == 0 and fly_oa > 0,
                        "both": fly_oa > 0 and fly_us > 0}[mod]
        if not expected:
            wrong.append(f"{name} step (OA {n_oa}, US {n_us})")
        if not fly_expected:
            wrong.append(f"{name} fly (OA {fly_oa}, US {fly_us})")
    sec.check("modalities with points, per object and scan mode:",
              "; ".join(wrong) if wrong else f"all {len(names)} objects, step and fly",
              "OA points only where the material gives them (not glass or steel), US "
              "points only where it echoes (not foam), as in the paper's Fig. 4", not wrong)
    sec.table(["object", "material", "modality", "points", "OA points", "US points",
               "points/s", "fly: points", "OA", "US", "points/s"], rows)

    def rate(n: int, r: int) -> float:  # points over the set / its scanning time
        return sum(x[n] for x in rows) / max(sum(x[n] / x[r] for x in rows if x[r]), 1e-9)

    rates = {"step": rate(3, 6), "fly": rate(7, 10)}  # points/s over the set
    d.rates = rates
    sec.text.append(
        f"Each object is scanned twice: step and shoot ({rates['step']:.1f} "
        f"points/s over the set, into {d.out / 'db'}) and fly ("
        f"{rates['fly']:.1f} points/s, 2 mm apart, into {d.out / 'db_fly'}: "
        f"each line one constant-speed move, every waveform placed by the X STEP pulses "
        f"time-stamped on the sensor board). The emulator runs moves 8x faster than the "
        f"machine but a fly line only as fast as it can compute the shots (about 1.5x real "
        f"time, `python bench/emulator.py`), so these rates understate fly; `python "
        f"bench/scan.py` compares the two at x1 (docs/scanning.md). The "
        f"classification below trains on the step-and-shoot database: a fly waveform averages "
        f"its 12 shots over 2 mm of travel, which on a curved surface smears the pulse the "
        f"classifier reads (docs/scanning.md).")
    sec.text.append(f"Database: {d.out / 'db'} (`dmdsm db list --db {d.out / 'db'}`).")
    return sec
