"""Sensor limits: SNR, detection and distance error against beam distance and incidence.

A flat face (the analytic Box) of each material stands on the table, turned so that the beam
meets it at the incidence asked (about an axis across the beam, the table's vertical but for
the beam's 3.9 deg of elevation, so that 0 deg is true normal incidence); the sensor stands
at the beam distance asked from the face. Every waveform is taken on a fresh surface spot (1 mm
apart on the face: the emulator's surface scatter is fixed per spot, as on a real surface)
with the emulator's physics in process (dmdsm.sim.data.rig_data.DirectRig: ray cast, waveform
synthesis, on-board averaging, stage scatter; no serial links, no firmware). The ranging setup
is the demo's ranging calibration on the aluminium block (block_data.ranging_calibration:
learned pulses, t0 fitted, c from the air), as a scan would use it; --true-setup takes the
emulator's t0 and c and Gaussian pulses instead (dataset.true_setup).

Each waveform is ranged by the host's PointRanger as a scan plan with its standoff at that
distance gates it (depth gate standoff - 3 .. standoff + 2 R + 3 mm, R 30 mm; --gate plan:
the scans' own gate at 8 mm standoff, 5 .. 71 mm, for every distance): once with
modality "oa" and once with "us" (a lone pulse is read as that modality; a pulse confirmed by
its partner from the other modality is read as the pair), and once with "both" without a
previous point (the share where the two modalities confirm each other: what a "both" scan
reads without the continuity of its line). Per cell: the median SNR (dB) the ranger reports,
the share of waveforms with a distance, and the error (mean, std; mm) of the distances against
the emulator's truth (Simulation.truth()'s distance: the cast's nearest return, the mean of
its rays; its mean also against the beam axis, the centre ray's distance, which differs from
it where the spot spans more than 0.3 mm of depth, from 45 deg), and the share of gross errors
(more than 1 mm off the truth: another pulse read).

Limits, per modality and material: with the error std at normal incidence and the scans'
standoff (8 mm) as the reference (that cell takes 4x the waveforms), a cell passes when at
least 95 % of its waveforms give a distance, at most 5 % are gross errors and the error std
is within 2x the reference;
the limits are the range of distances about 8 mm at normal incidence, and the largest
incidence at 8 mm, over which every cell passes.

    python bench/sensor_limits.py [--quick] [--json FILE] [--average 12,16,24] [--waveforms 20]
"""

from __future__ import annotations

import argparse
import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from dmdsm.host.ranging.calibrate import distance_std_mm  # noqa: E402
from dmdsm.host.ranging.matched_filter import MatchedFilter  # noqa: E402
from dmdsm.host.scan.plan import (  # noqa: E402
    AUTO_AVERAGE,
    FLY_AVERAGE,
    ScanPlan,
    point_ranger,
)
from dmdsm.sim.boards.sensor.core_board import TICK_HZ  # noqa: E402
from dmdsm.sim.data.block_data import block_rig, ranging_calibration  # noqa: E402
from dmdsm.sim.data.dataset import true_setup  # noqa: E402
from dmdsm.sim.data.rig_data import DirectRig  # noqa: E402
from dmdsm.sim.physics.scene import Box, Scene, SceneObject, table_frame, unit  # noqa: E402

STEP_AVERAGE = ScanPlan("x").average  # step and shoot's on-board average (16)
MODE_OF = {FLY_AVERAGE: "fly", STEP_AVERAGE: "step", AUTO_AVERAGE: "auto"}  # 12, 16, 24
DISTANCES = (4.0, 6.0, 8.0, 10.0, 15.0, 20.0, 30.0, 40.0)  # beam distance (mm)
ANGLES = (0.0, 15.0, 30.0, 45.0, 60.0, 75.0)  # incidence (deg)
MATERIALS = ("aluminium", "plastic", "paper")
QUICK = {"distances": (4.0, 8.0, 20.0, 40.0), "angles": (0.0, 15.0, 45.0, 75.0),
         "waveforms": 10, "averages": (FLY_AVERAGE,)}
STANDOFF = ScanPlan("x").standoff_mm  # the scans' standoff (8 mm): the reference distance
DETECT_MIN = 0.95  # a cell passes with at least this share of waveforms ranged ...
STD_FACTOR = 2.0   # ... and an error std within this factor of the reference's
REF_FACTOR = 4    # the reference cell takes this many times the waveforms of the others
GROSS_MM = 1.0     # an error beyond this is counted as a gross error (another pulse read)
HALF = np.array([30.0, 15.0, 30.0])  # the box's half sizes (mm): a 60 x 60 mm face
FACE = np.array([0.0, -15.0, 30.0])  # where the face's centre stands (table frame, mm)
SPOT_MM = 1.0  # spots this far apart on the face (the emulator's scatter cells are 0.2 mm)
MODS = ("oa", "us")


def face_pose(scene: Scene, incidence_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """World rotation of the box (columns: its x, y, z) whose -y face meets the beam at the
    incidence, and the box's centre in the table frame (its face centre at FACE)."""
    v = unit(scene.v)
    across = unit(np.cross(scene.n, v))  # horizontal, across the beam
    i = np.radians(incidence_deg)
    normal = -v * np.cos(i) + across * np.sin(i)  # the face's outward normal
    up = unit(scene.n - np.dot(scene.n, normal) * normal)
    y = -normal
    W = np.column_stack([np.cross(y, up), y, up])
    B = table_frame(scene.n)
    R = B.T @ W  # local -> table frame (the table at 0 deg)
    return W, FACE - R @ np.array([0.0, -HALF[1], 0.0])


def rangers_at(setup: object, d_mm: float, cache: dict, gate: str) -> dict:
    """The PointRangers ("oa", "us", "both") of a scan plan whose standoff is d_mm (gate
    "standoff") or the scans' 8 mm (gate "plan")."""
    standoff = d_mm if gate == "standoff" else STANDOFF
    if standoff not in cache:
        cache[standoff] = {m: point_ranger(ScanPlan("bench", standoff_mm=standoff, modality=m),
                                           setup, 1024, TICK_HZ) for m in ("oa", "us", "both")}
    return cache[standoff]


def cell_waveform(material: str, d_mm: float, incidence_deg: float, average: int = 24,
                  seed: int = 0) -> tuple[np.ndarray, int, float, object]:
    """One waveform (samples, trigger phase), the true distance (mm) and the auto plan's
    "both" ranger, for a face of `material` d_mm away at the incidence (tests use it)."""
    rig = block_rig(seed)
    setup = ranging_calibration(rig)
    scene = Scene(objects=[])
    W, center = face_pose(scene, incidence_deg)
    R = table_frame(scene.n).T @ W
    scene.objects = [SceneObject(f"{material}_face", material, Box(center=center, R=R,
                                                                  half=HALF))]
    rig.scene = scene
    rig.configure(n_samples=1024, n_average=average)
    S = scene.X_R + table_frame(scene.n) @ FACE - d_mm * unit(scene.v)
    rig.move(*S)
    truth = scene.cast(*rig.pose()).d
    got = rig.acquire(1)
    ranger = point_ranger(ScanPlan("t", standoff_mm=STANDOFF, modality="both"), setup, 1024,
                          TICK_HZ)
    return got.samples[0], int(got.trigger_phase[0]), float(truth), ranger


def cell(rig: DirectRig, setup: object, material: str, d_mm: float, incidence_deg: float,
         n_waves: int, average: int, band: int, cache: dict, gate: str) -> dict:
    """n_waves waveforms at beam distance d_mm and the incidence, each on its own spot of the
    face; the per-modality readings and their statistics."""
    scene = Scene(objects=[])
    W, center = face_pose(scene, incidence_deg)
    R = table_frame(scene.n).T @ W
    # the object's name keys the emulator's surface scatter: every cell its own patch
    name = f"{material}_face_{incidence_deg:g}_{d_mm:g}"
    scene.objects = [SceneObject(name, material, Box(center=center, R=R, half=HALF))]
    axis = Scene(objects=scene.objects, spot_radius=1e-6)  # the centre ray alone
    rig.scene = scene
    rig.configure(n_samples=1024, n_average=average)
    v = unit(scene.v)
    aim = scene.X_R + table_frame(scene.n) @ FACE
    plan = ScanPlan("bench", standoff_mm=d_mm if gate == "standoff" else STANDOFF)
    rangers = rangers_at(setup, d_mm, cache, gate)
    cols = 5
    rows = -(-n_waves // cols)
    rec: dict[str, list] = {k: [] for k in ("truth", "axis", "cos_i", "paired")}
    for m in MODS:
        rec[m] = []
    for k in range(n_waves):
        # spots 1 mm apart on the face, a band of its height per distance
        a = (k % cols - (cols - 1) / 2) * SPOT_MM
        b = (k // cols - (rows - 1) / 2) * SPOT_MM + band
        S = aim - d_mm * v + a * W[:, 0] + b * W[:, 2]
        rig.move(*S)
        pose = rig.pose()
        hit = scene.cast(*pose)
        rec["truth"].append(hit.d)
        rec["axis"].append(axis.cast(*pose).d)
        rec["cos_i"].append(hit.cos_incidence)
        got = rig.acquire(1)
        wave, phase = got.samples[0], int(got.trigger_phase[0])
        for m in MODS:
            rec[m].append(rangers[m](wave, phase, 0, None)[m])
        both = rangers["both"](wave, phase, 0, None)
        rec["paired"].append(all(np.isfinite(both[m][0]) for m in MODS))
    truth, on_axis = np.array(rec["truth"]), np.array(rec["axis"])
    out = {"material": material, "d_mm": d_mm, "incidence_deg": incidence_deg,
           "average": average, "waveforms": n_waves,
           "incidence_measured_deg": float(np.degrees(np.arccos(np.mean(rec["cos_i"])))),
           "truth_minus_axis_mm": float(np.mean(truth - on_axis)),
           "paired_share": float(np.mean(rec["paired"])), "depth_gate_mm": plan.depth_gate_mm()}
    for m in MODS:
        d = np.array([r[0] for r in rec[m]])
        snr = np.array([r[1] for r in rec[m]])
        ok = np.isfinite(d)
        err = d[ok] - truth[ok]
        out[m] = {
            "snr_db_median": float(np.median(snr)),
            "snr_db_range": [float(snr.min()), float(snr.max())],
            "detected": float(ok.mean()),
            "error_mean_mm": float(err.mean()) if ok.any() else None,
            "error_std_mm": float(err.std(ddof=1)) if ok.sum() > 1 else None,
            "gross_share": float(np.sum(np.abs(err) > GROSS_MM) / len(d)),
            "axis_error_mean_mm": float((d[ok] - on_axis[ok]).mean()) if ok.any() else None,
            "reported_std_mm_median": float(np.median(distance_std_mm(setup, m, snr[ok])))
            if ok.any() else None,
        }
    return out


def passes(c: dict, m: str, ref: float | None) -> bool:
    """A cell passes: detection >= 95 %, gross errors (another pulse read) <= 5 % and the
    error std within 2x the reference."""
    s = c[m]
    return ref is not None and s["detected"] >= DETECT_MIN and s["error_std_mm"] is not None \
        and s["gross_share"] <= 1 - DETECT_MIN and s["error_std_mm"] <= STD_FACTOR * ref


def limits(cells: list[dict], m: str, distances: list[float], angles: list[float]) -> dict:
    """One modality's limits on one material at one average (cells of that material)."""
    at = {(c["d_mm"], c["incidence_deg"]): c for c in cells}
    ref_cell = at.get((STANDOFF, 0.0))
    ref = ref_cell[m]["error_std_mm"] if ref_cell and \
        ref_cell[m]["detected"] >= DETECT_MIN else None
    ok = {key: passes(c, m, ref) for key, c in at.items()}
    ds = sorted(distances)
    k0 = ds.index(STANDOFF)

    def span(a: float) -> tuple[float | None, float | None]:
        """The distances about the standoff over which every cell passes, at incidence a."""
        if not ok[(STANDOFF, a)]:
            return None, None
        lo = hi = k0
        while lo > 0 and ok[(ds[lo - 1], a)]:
            lo -= 1
        while hi < len(ds) - 1 and ok[(ds[hi + 1], a)]:
            hi += 1
        return ds[lo], ds[hi]

    max_i = None
    for a in sorted(angles):
        if not ok[(STANDOFF, a)]:
            break
        max_i = a
    return {"reference_std_mm": ref, "distance_range_mm": span(0.0), "max_incidence_deg": max_i,
            "distance_range_by_incidence": {a: span(a) for a in sorted(angles)},
            "passing": {f"{d:g}/{a:g}": ok[(d, a)] for d, a in sorted(ok)}}


def table(title: str, cells: list[dict], distances: list[float], angles: list[float],
          value: object, fmt: str) -> None:
    """One quantity, rows = distance, OA | US columns = incidence."""
    at = {(c["d_mm"], c["incidence_deg"]): c for c in cells}
    w = 7
    print(f"\n  {title}")
    print(f"  {'d mm':>5} | " + " ".join(f"{'OA ' + format(a, 'g'):>{w}}" for a in angles)
          + " | " + " ".join(f"{'US ' + format(a, 'g'):>{w}}" for a in angles))
    for d in distances:
        parts = []
        for m in MODS:
            vals = [value(at[(d, a)], m) for a in angles]
            parts.append(" ".join(f"{'-' if x is None else format(x, fmt):>{w}}" for x in vals))
        print(f"  {d:>5g} | " + " | ".join(parts))


def show_range(r: tuple) -> str:
    """A distance span for the summary."""
    return "none" if r[0] is None else f"{r[0]:g}-{r[1]:g} mm"


def main() -> int:
    """Measure every cell, print the tables and the limits."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true",
                    help="4 distances, 4 incidences, 10 waveforms, average 12 only")
    ap.add_argument("--json", type=str, default=None, help="write every cell and limit here")
    ap.add_argument("--average", default=f"{FLY_AVERAGE},{STEP_AVERAGE},{AUTO_AVERAGE}",
                    help="on-board averages (fly 12, step 16, auto 24)")
    ap.add_argument("--waveforms", type=int, default=20, help="waveforms per cell")
    ap.add_argument("--materials", default=",".join(MATERIALS))
    ap.add_argument("--distances", default=",".join(f"{d:g}" for d in DISTANCES))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--gate", choices=("standoff", "plan"), default="standoff",
                    help="depth gate: a plan's whose standoff is the distance measured "
                    "(standoff), or the scans' own at 8 mm standoff, 5..71 mm (plan)")
    ap.add_argument("--true-setup", action="store_true",
                    help="the emulator's t0, c and Gaussian pulses instead of a calibration")
    args = ap.parse_args()
    distances = sorted({float(x) for x in args.distances.split(",")} | {STANDOFF})
    angles = list(ANGLES)
    averages = [int(x) for x in args.average.split(",")]
    n_waves = args.waveforms
    if args.quick:
        distances, angles = list(QUICK["distances"]), list(QUICK["angles"])
        n_waves, averages = QUICK["waveforms"], list(QUICK["averages"])
    materials = args.materials.split(",")
    t_start = time.perf_counter()
    rig = block_rig(args.seed)
    setup = true_setup(rig.model) if args.true_setup else ranging_calibration(rig)
    model = rig.model
    c = model.c_mm_us
    t0_err = {m: (setup.cals[m].t0_s * 1e6 - t0) * c / (1 if m == "oa" else 2)
              for m, t0 in (("oa", model.t0_oa_us), ("us", model.t0_us_us))}
    floors = {m: MatchedFilter(setup.templates[m], 1024).ambiguity_snr_db for m in MODS}
    print(f"ranging setup: {'the emulator' if args.true_setup else 'calibrated on the block'}"
          f" (seed {args.seed}); its t0 error as a distance: OA {t0_err['oa']:+.3f} mm, US "
          f"{t0_err['us']:+.3f} mm (common to every cell's mean error); readings need SNR >= "
          f"OA {floors['oa']:.1f} dB, US {floors['us']:.1f} dB (the ambiguity floor)")
    print(f"{n_waves} waveforms per cell, each on its own spot; distances {distances} mm, "
          f"incidences {angles} deg; depth gate "
          + ("standoff - 3 .. standoff + 63 mm with the distance measured as the standoff"
             if args.gate == "standoff" else "5 .. 71 mm (a plan at 8 mm standoff, R 30 mm)"))
    cells: list[dict] = []
    cache: dict = {}
    for average in averages:
        for material in materials:
            for di, d in enumerate(distances):
                for a in angles:
                    band = int((di - (len(distances) - 1) / 2) * 5)  # mm up or down the face
                    # the reference cell (the standoff, normal incidence) with 4x the waveforms
                    n = REF_FACTOR * n_waves if (d, a) == (STANDOFF, 0.0) else n_waves
                    cells.append(cell(rig, setup, material, d, a, n, average, band, cache,
                                      args.gate))
    elapsed = time.perf_counter() - t_start
    result: dict = {"config": {"waveforms": n_waves, "distances_mm": distances,
                               "incidences_deg": angles, "averages": averages,
                               "materials": materials, "seed": args.seed,
                               "true_setup": args.true_setup, "gate": args.gate,
                               "elapsed_s": elapsed},
                    "setup_t0_error_mm": t0_err, "ambiguity_snr_db": floors,
                    "cells": cells, "limits": {}}
    for average in averages:
        print(f"\n=== on-board average {average} "
              f"({MODE_OF.get(average, 'not a plan default')}) ===")
        for material in materials:
            cs = [c for c in cells if c["average"] == average and c["material"] == material]
            print(f"\n{material}")
            table("median SNR (dB) the ranger reports", cs, distances, angles,
                  lambda c, m: c[m]["snr_db_median"], ".1f")
            table("detection: share of waveforms with a distance (%)", cs, distances, angles,
                  lambda c, m: 100 * c[m]["detected"], ".0f")
            table("error mean (mm) against the emulator's truth", cs, distances, angles,
                  lambda c, m: c[m]["error_mean_mm"], "+.3f")
            table("error mean (mm) against the beam axis (the centre ray's distance)", cs,
                  distances, angles, lambda c, m: c[m]["axis_error_mean_mm"], "+.3f")
            table("error std (mm)", cs, distances, angles,
                  lambda c, m: c[m]["error_std_mm"], ".3f")
            table(f"gross errors: readings more than {GROSS_MM:g} mm off (% of waveforms)", cs,
                  distances, angles, lambda c, m: 100 * c[m]["gross_share"], ".0f")
            at = {(c["d_mm"], c["incidence_deg"]): c for c in cs}
            print("\n  both modalities confirm each other (% of waveforms; 'both' scans "
                  "need this or the line's continuity)")
            print(f"  {'d mm':>5} | " + " ".join(f"{format(a, 'g'):>7}" for a in angles))
            for d in distances:
                print(f"  {d:>5g} | " + " ".join(
                    f"{100 * at[(d, a)]['paired_share']:>7.0f}" for a in angles))
    offset = {a: np.mean([c["truth_minus_axis_mm"] for c in cells if c["incidence_deg"] == a])
              for a in angles}
    print("\nthe emulator's truth (its nearest return: rays within 0.3 mm of depth) lies along "
          "the beam from the centre ray by (mm): " + ", ".join(f"{a:g} deg {offset[a]:+.3f}"
                                                             for a in angles))
    print(f"\n=== limits: detection >= {DETECT_MIN:.0%}, gross errors <= {1 - DETECT_MIN:.0%} "
          f"and error std <= {STD_FACTOR:g}x its value at normal incidence and {STANDOFF:g} mm "
          f"===")
    for average in averages:
        lim: dict = {}
        for material in materials:
            cs = [c for c in cells if c["average"] == average and c["material"] == material]
            lim[material] = {m: limits(cs, m, distances, angles) for m in MODS}
        result["limits"][str(average)] = lim
        print(f"\naverage {average} ({MODE_OF.get(average, 'not a plan default')}):")
        print(f"  {'material':>10} {'mod':>3} {'ref std':>8} {'distances at 0 deg':>19} "
              f"{'max incidence at ' + format(STANDOFF, 'g') + ' mm':>25}   distances by "
              f"incidence")
        for material in materials:
            for m in MODS:
                r = lim[material][m]
                ref = "-" if r["reference_std_mm"] is None else f"{r['reference_std_mm']:.3f}"
                mi = "none" if r["max_incidence_deg"] is None else f"{r['max_incidence_deg']:g} deg"
                by = ", ".join(f"{a:g}: {show_range(s)}"
                               for a, s in r["distance_range_by_incidence"].items())
                print(f"  {material:>10} {m.upper():>3} {ref:>8} "
                      f"{show_range(r['distance_range_mm']):>19} {mi:>25}   {by}")
        for m in MODS:
            rs = [lim[mat][m] for mat in materials]
            his = [r["distance_range_mm"][1] for r in rs]
            los = [r["distance_range_mm"][0] for r in rs]
            inc = [r["max_incidence_deg"] for r in rs]
            worst_hi = None if None in his else min(his)
            worst_lo = None if None in los else max(los)
            worst_i = None if None in inc else min(inc)
            print(f"  {'all':>10} {m.upper():>3} {'':>8} "
                  f"{show_range((worst_lo, worst_hi)):>19} "
                  f"{'none' if worst_i is None else format(worst_i, 'g') + ' deg':>25}   "
                  f"(the worst of the materials; {distances[-1]:g} mm and {angles[-1]:g} deg "
                  f"are the largest measured)")
    print(f"\n{len(cells)} cells in {elapsed:.0f} s")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(result, f, indent=1, default=lambda o: list(o) if isinstance(o, tuple)
                      else str(o))
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
