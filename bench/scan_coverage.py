"""Scan coverage benchmark: coverage, accuracy, laser duty and keep-out of step, fly and auto scans.

For the block and six household objects of the emulator (a handled mug, a bottle with a neck,
the concave bowl, ...), three scans each with the same seed, in process (`run_plan` against an
`Emulator` started here, `--speed` x the wall clock): step and fly on `plan_for_size`'s fixed
plans (one level at half the height, four angles) and auto on `plan_for_size(mode="auto")` with
its levels restricted to a band of the object's height (every 2 mm from 4.5 mm up to
4.5 + `--band-mm`): the band is scanned, not the whole height, to keep the emulator's time
within a bench run. Per object and mode one row: points per modality, wall and emulated time,
points per emulated second, coverage at 2 mm of the emulator's true reachable surface within
the band (bench/coverage_truth.py; the same band for every mode, so the rows compare; per
modality: what OA can reach from some table angle within 60 deg of incidence, US within 15,
the sensor's limits in docs/scanning.md), the
mean and 95th percentile of the points' distance to the true surface (and, per mode, its
mean and std by the incidence the beam met the true surface at, against the paper's head-on
figures: bench/incidence_accuracy.py), the laser's duty
(host/scan/coverage.py) and keep-out violations: laser shots whose true sensor position came
within 2 mm (the keep-out margin) of the true object surface. The ranging calibration is
measured once, on the block, as a user does with the gauge block, and serves every scan; the
geometric calibration (v, n, X_R) is the emulator's truth. A scan that raises is a row with
its reason.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import tempfile
import threading
import time
import traceback
from dataclasses import replace
from pathlib import Path

import numpy as np
from coverage_truth import reachable_truth  # bench/, this script's folder
from incidence_accuracy import PAPER_MM, by_incidence, pooled, text
from scipy.spatial import cKDTree

from dmdsm.host.links.sensor import SensorClient
from dmdsm.host.links.stage import StageClient
from dmdsm.host.ranging.procedure import calibrate_range
from dmdsm.host.scan.coverage import coverage, laser_duty
from dmdsm.host.scan.plan import AUTO_LOWEST_MM, AUTO_SPACING_MM, plan_for_size
from dmdsm.host.scan.points import MODS, scan_points
from dmdsm.host.scan.scanfile import read_scan
from dmdsm.host.scan.session import run_plan
from dmdsm.sim.boards.sensor.core_board import TICK_HZ
from dmdsm.sim.physics.objects import SCENES, bounding_size
from dmdsm.sim.physics.scene import table_frame
from dmdsm.sim.physics.visibility import surface_samples
from dmdsm.sim.servers.emulator import Emulator
from dmdsm.sim.servers.runner import SimConfig, Simulation

# object: is it round (its bounding cylinder from its width, not its diagonal)
OBJECTS = {"aluminium_block": False, "mug": False, "plastic_bottle_neck": True, "bowl": True,
           "pear": True, "can_with_label": True, "jar_with_lid": True, "tissue_box": False}
QUICK = ("aluminium_block", "mug")
MODES = ("step", "fly", "auto", "sweep")
SPACING_MM = 2.0          # coverage spacing (the target's)
MARGIN_MM = 2.0           # the keep-out margin (host/links/safety.py KeepOut)
# the incidence (deg) each modality ranges at (docs/scanning.md, "What the sensor ranges
# well": OA 30-60 deg, US 15): a surface US cannot reach is not held against it
MAX_INCIDENCE_DEG = {"oa": 60.0, "us": 15.0}
MAX_DIST_POINTS = 20_000  # points per modality whose distance to the truth is computed
TARGETS = {"coverage": 0.95, "duty": 0.50, "violations": 0}
RANGING_AT_MM = (235.0, 266.0, 20.0)  # in front of the block's face (host/commands/sim.py)


def object_frame(S: np.ndarray, theta_deg: np.ndarray, n: np.ndarray, X_R: np.ndarray
                 ) -> np.ndarray:
    """Stage-frame positions S (k, 3, mm) taken with the table at theta_deg (k,) in the
    object frame: B^T R_n(-theta) (S - X_R), as reconstruct.object_points, one rotation per
    row (Rodrigues' formula) instead of one per distinct angle."""
    n = np.asarray(n, float) / np.linalg.norm(n)
    r = np.asarray(S, float) - np.asarray(X_R, float)
    a = -np.radians(np.asarray(theta_deg, float))[:, None]
    nxr = np.cross(n, r)
    rot = r + np.sin(a) * nxr + (1 - np.cos(a)) * np.cross(n, nxr)
    return rot @ table_frame(n)


def keep_out(shots: np.ndarray, truths: list, n: np.ndarray, X_R: np.ndarray,
             margin_mm: float = MARGIN_MM) -> dict:
    """Laser shots (rows: S x, y, z (mm), theta (deg)) whose true sensor position lies within
    margin_mm of an object's true surface or inside it, and the least clearance (mm): exact
    (trimesh signed distance) where a dense surface sample is within margin + 1.5 mm, else
    the distance to the nearest sample (0.5 mm apart; at most about 0.5 mm above the truth)."""
    if len(shots) == 0:
        return {"violations": 0, "shots": 0, "min_clearance_mm": None}
    P = object_frame(shots[:, :3], shots[:, 3], n, X_R)
    bad = np.zeros(len(P), bool)
    clear = np.full(len(P), np.inf)
    for t in truths:
        V = np.asarray(t.mesh.vertices, float) @ np.asarray(t.R, float).T + t.center
        lo, hi = V.min(axis=0), V.max(axis=0)
        near = np.flatnonzero(np.all((P > lo - 4.0) & (P < hi + 4.0), axis=1))
        if not near.size:
            continue
        samples, _ = surface_samples(t, 0.5)
        dq, _ = cKDTree(samples).query(P[near])
        clear[near] = np.minimum(clear[near], dq)
        cand = near[dq < margin_mm + 1.5]
        if cand.size:
            key, inv = np.unique(np.round(P[cand], 3), axis=0, return_inverse=True)
            sd = t.signed_distance(key)[inv.ravel()]  # positive inside
            clear[cand] = np.minimum(clear[cand], -sd)
            bad[cand] |= sd > -margin_mm
        far = near[dq >= margin_mm + 1.5]  # far from the surface: inside it?
        if far.size:
            inside = np.asarray(t.mesh.contains(t.to_object(P[far])), bool)
            bad[far[inside]] = True
            clear[far[inside]] = -np.inf
    finite = clear[np.isfinite(clear)]
    return {"violations": int(bad.sum()), "shots": int(len(P)),
            "min_clearance_mm": float(finite.min()) if finite.size else None}


def truth_distance(P: np.ndarray, truths: list) -> dict:
    """Mean and 95th percentile (mm) of |distance| of object-frame points to the nearest true
    surface (at most MAX_DIST_POINTS of them, drawn with a fixed seed)."""
    P = np.asarray(P, float).reshape(-1, 3)
    P = P[np.all(np.isfinite(P), axis=1)]
    if not len(P) or not truths:
        return {"mean_mm": float("nan"), "p95_mm": float("nan"), "n": 0}
    if len(P) > MAX_DIST_POINTS:
        P = P[np.random.default_rng(0).choice(len(P), MAX_DIST_POINTS, replace=False)]
    d = np.min([np.abs(t.signed_distance(P)) for t in truths], axis=0)
    return {"mean_mm": float(d.mean()), "p95_mm": float(np.percentile(d, 95)), "n": len(P)}


def auto_levels(height_mm: float, band_mm: float) -> list[float]:
    """Every 2 mm from 4.5 mm up to 4.5 + band (below the top less 0.5 mm, as plan_for_size)."""
    top = min(height_mm - 0.5, AUTO_LOWEST_MM + band_mm + 1e-9)
    return [round(float(z), 1) for z in np.arange(AUTO_LOWEST_MM, top, AUTO_SPACING_MM)] or [
        round(max(height_mm / 2, AUTO_LOWEST_MM), 1)]


def true_reach_mm(truths: list) -> float:
    """The truth's farthest point from the table axis (mm): what an operator measures for
    plan new --reach-mm."""
    P = np.concatenate([np.asarray(t.mesh.vertices, float) @ np.asarray(t.R).T + t.center
                        for t in truths])
    return float(np.hypot(P[:, 0], P[:, 1]).max())


def bench_plan(obj: str, size: tuple, round_: bool, material: str, mode: str,
               true_reach: float) -> tuple:
    """(plan_for_size's plan, the reach_mm given or None): the reach (to 0.1 mm up) where
    the footprint's bounding cylinder is inside the object's farthest point (the mug's
    handle), as an operator would give it."""
    plan = plan_for_size(obj, size, round_, material, mode)
    if plan.radius_mm >= true_reach:
        return plan, None
    reach = math.ceil(true_reach * 10) / 10
    return plan_for_size(obj, size, round_, material, mode, reach_mm=reach), reach


def calibrate(seed: int, speed: float) -> object:
    """The ranging setup, measured on the block (gauge) with the same seed as the scans."""
    emu = Emulator(sim=Simulation(SimConfig(scene="aluminium_block", seed=seed)),
                   speed=speed).start()
    try:
        with StageClient(emu.stage) as st:
            st.home()
            x, y, z = RANGING_AT_MM
            st.move(x=x, y=y, z=z, wait=True)
            st.wait()
            sc = SensorClient(emu.sensor)
            try:
                setup, _ = calibrate_range(st, sc, {"X": x, "Y": y, "Z": z},
                                           emu.sim.truth()["distance_mm"], steps=6,
                                           step_mm=1.0, shots=2, fit_c=False, lateral=5)
            finally:
                sc.close()
            st.home()
    finally:
        emu.stop()
    return setup


def _progress(what: str):
    """A progress callback printing done/planned to stderr at most every 10 s."""
    last = [0.0]

    def show(done: int, planned: int, *_: object) -> None:
        if time.monotonic() - last[0] >= 10.0:
            last[0] = time.monotonic()
            print(f"    {what}: {done}/{planned}", file=sys.stderr, flush=True)

    return show


def revision() -> str:
    """The checkout's commit and the files changed in its working tree (the code measured)."""
    root = Path(__file__).resolve().parent.parent
    try:
        head = subprocess.run(["git", "-C", str(root), "rev-parse", "--short", "HEAD"],
                              capture_output=True, text=True, timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain",
                                "--untracked-files=no"], capture_output=True, text=True,
                               timeout=10).stdout.split()[1::2]
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return head + (f" with uncommitted changes to {', '.join(dirty)}" if dirty else "")


def one_scan(obj: str, mode: str, plan, setup, seed: int, speed: float, z_band: tuple,
             reference: dict, out: Path, timeout_s: float) -> dict:
    """One scan of `obj` in `mode` against a fresh emulator; returns its figures."""
    sim = Simulation(SimConfig(scene=obj, seed=seed))
    shots: list[tuple[float, float, float, float]] = []
    recording = [False]
    pose = sim.pose

    def recorded(t: float) -> tuple[np.ndarray, float]:
        S, theta = pose(t)
        if recording[0]:
            shots.append((float(S[0]), float(S[1]), float(S[2]), float(theta)))
        return S, theta

    sim.sensor.pose = recorded
    s = sim.scene
    cal = {"v": (s.v / np.linalg.norm(s.v)).tolist(), "n": (s.n / np.linalg.norm(s.n)).tolist(),
           "X_R": np.asarray(s.X_R, float).tolist()}
    text = "[calibration]\n" + "".join(f"{k} = {v}\n" for k, v in cal.items())
    truths = sim.truth_objects()
    emu = Emulator(sim=sim, speed=speed).start()
    watchdog = threading.Timer(timeout_s, emu.stop)  # a hung scan ends as a failed row
    watchdog.daemon = True
    watchdog.start()
    try:
        sensor = SensorClient(emu.sensor)
        try:
            with StageClient(emu.stage) as st:
                st.home()  # before the clocks: a scan starts from the homed stage
                recording[0] = True
                sim_t0, wall0 = sim.t, time.monotonic()
                run = run_plan(sensor, st, plan, calibration=cal, calibration_toml=text,
                               setup=setup, db=out / f"{obj}-{mode}", home=False,
                               progress=_progress(f"{obj} {mode}"))
                wall_s, sim_s = time.monotonic() - wall0, sim.t - sim_t0
                recording[0] = False
        finally:
            sensor.close()
    finally:
        watchdog.cancel()
        emu.stop()
    if run.status != "complete":
        raise RuntimeError(f"the scan ended {run.status}")
    scan = read_scan(run.path, waveforms=False)
    stored = len(scan.points["timestamp"])
    pts = scan_points(scan)
    ts = np.sort(np.asarray(scan.points["timestamp"], float))
    row = {"object": obj, "mode": mode, "ok": True, "stored": stored,
           "points": {m: int(len(pts[m]["P"])) for m in MODS}, "wall_s": wall_s,
           "emulated_s": sim_s,
           "waveform_span_s": float((ts[-1] - ts[0]) / TICK_HZ) if stored > 1 else None,
           "points_per_emulated_s": stored / sim_s if sim_s > 0 else float("nan"),
           "duty_waveform_span": laser_duty(stored, plan.average, sim.cfg.rep_rate_hz,
                                            float((ts[-1] - ts[0]) / TICK_HZ))
           if stored > 1 else None,
           "coverage": {m: coverage(reference["surface"][m], pts[m]["P"], SPACING_MM)
                        for m in MODS},
           "distance": {m: truth_distance(pts[m]["P"], truths) for m in MODS},
           "incidence": {m: by_incidence(pts[m]["P"], pts[m]["S"], pts[m]["theta_deg"],
                                         np.asarray(cal["v"]), np.asarray(cal["n"]),
                                         np.asarray(cal["X_R"]), truths, object_frame)
                         for m in MODS},
           "duty": laser_duty(stored, plan.average, sim.cfg.rep_rate_hz, sim_s),
           "keep_out": keep_out(np.asarray(shots, float).reshape(-1, 4), truths,
                                np.asarray(cal["n"]), np.asarray(cal["X_R"])),
           "plan": {"modality": plan.modality, "offsets_mm": plan.offsets_mm,
                    "levels_mm": plan.levels_mm, "angles_deg": plan.angles_deg,
                    "step_mm": plan.step_mm, "average": plan.average,
                    "radius_mm": plan.radius_mm, "half_width_mm": plan.half_width_mm},
           "z_band_mm": list(z_band), "file": str(run.path)}
    if run.auto:
        row["auto"] = run.auto
    return row


def fmt(x: float | None, spec: str) -> str:
    """A number in `spec`, or '-' for None / NaN."""
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, spec)


HEAD = (f"{'object':20s} {'mode':5s} {'pts OA':>7s} {'pts US':>7s} {'wall s':>7s} "
        f"{'emu s':>7s} {'pt/emu-s':>8s} {'cov OA':>6s} {'cov US':>6s} {'eOA mn':>6s} "
        f"{'eOA 95':>6s} {'eUS mn':>6s} {'eUS 95':>6s} {'duty':>5s} {'viol':>6s} "
        f"{'clear':>5s}")


def row_text(r: dict) -> str:
    """One printed row of the table (or the scan's failure)."""
    if not r["ok"]:
        return f"{r['object']:20s} {r['mode']:5s} FAILED: {r['reason']}"
    c, d, k = r["coverage"], r["distance"], r["keep_out"]
    return (f"{r['object']:20s} {r['mode']:5s} {r['points']['oa']:7d} {r['points']['us']:7d} "
            f"{r['wall_s']:7.1f} {r['emulated_s']:7.1f} {r['points_per_emulated_s']:8.1f} "
            f"{fmt(100 * c['oa'], '5.1f'):>5s}% {fmt(100 * c['us'], '5.1f'):>5s}% "
            f"{fmt(d['oa']['mean_mm'], '6.3f'):>6s} {fmt(d['oa']['p95_mm'], '6.3f'):>6s} "
            f"{fmt(d['us']['mean_mm'], '6.3f'):>6s} {fmt(d['us']['p95_mm'], '6.3f'):>6s} "
            f"{fmt(100 * r['duty'], '4.1f'):>4s}% {k['violations']:6d} "
            f"{fmt(k['min_clearance_mm'], '5.1f'):>5s}")


def summary(rows: list[dict], modes: list[str]) -> list[str]:
    """Per mode: average coverage (per modality, over the objects scanned for it: their
    material's modality, with a surface in the band it can reach) and duty, total
    violations, against the targets."""
    out = [f"targets: coverage >= {TARGETS['coverage']:.0%} at {SPACING_MM:g} mm, laser duty "
           f">= {TARGETS['duty']:.0%}, {TARGETS['violations']} keep-out violations"]
    for mode in modes:
        ok = [r for r in rows if r["mode"] == mode and r["ok"]]
        failed = sum(1 for r in rows if r["mode"] == mode and not r["ok"])
        if not ok:
            out.append(f"{mode:5s}: no finished scan ({failed} failed)")
            continue
        parts = []
        for m in MODS:  # over the objects scanned for m (their material's modality)
            mine = [r for r in ok if r["plan"]["modality"] in ("both", m)
                    and np.isfinite(r["coverage"][m])]  # and with a surface m can reach
            if not mine:
                continue
            cov = np.nanmean([r["coverage"][m] for r in mine])
            miss = TARGETS["coverage"] - cov
            parts.append(f"coverage {m.upper()} {cov:.1%} over {len(mine)}" + (
                f" (misses by {100 * miss:.1f} points)" if miss > 0 else " (met)"))
        duty = np.nanmean([r["duty"] for r in ok])
        miss = TARGETS["duty"] - duty
        parts.append(f"duty {duty:.1%}" + (f" (misses by {100 * miss:.1f} points)" if miss > 0
                                          else " (met)"))
        v = sum(r["keep_out"]["violations"] for r in ok)
        parts.append(f"violations {v}" + (" (met)" if v <= TARGETS["violations"] else
                                          f" (misses by {v})"))
        out.append(f"{mode:5s} ({len(ok)} scans" + (f", {failed} failed" if failed else "") +
                   "): " + "; ".join(parts))
        for m in MODS:  # |e| by incidence, every scan's points pooled
            bins = pooled([r.get("incidence", {}).get(m) or [] for r in ok])
            if any(b["n"] for b in bins):
                out.append(f"      {m.upper()} |e| by incidence (deg: mean +- std mm (points); "
                           f"paper head on {PAPER_MM[m][0]:g} +- {PAPER_MM[m][1]:g}): "
                           + text(bins))
    return out


def main() -> int:
    """Run the scans, print the table and the summary; exit 1 if a scan failed."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--objects", nargs="+", default=list(OBJECTS),
                    help="emulator scenes (dmdsm sim --list-scenes)")
    ap.add_argument("--modes", nargs="+", default=list(MODES), choices=MODES)
    ap.add_argument("--speed", type=float, default=4.0, help="emulator speed (x wall clock)")
    ap.add_argument("--band-mm", type=float, default=30.0,
                    help="height band the auto plan scans, from 4.5 mm up (mm)")
    ap.add_argument("--quick", action="store_true", help=f"only {' and '.join(QUICK)}")
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--timeout", type=float, default=1800.0,
                    help="wall seconds a scan may take before it is stopped (a failed row)")
    ap.add_argument("--out", type=Path, default=None, help="folder for the scan files")
    ap.add_argument("--json", type=Path, default=None, help="write all figures to this file")
    args = ap.parse_args()
    objects = list(QUICK) if args.quick else args.objects
    for o in objects:
        if o not in SCENES or o == "empty":
            ap.error(f"unknown scene {o!r} (dmdsm sim --list-scenes)")
    out = args.out or Path(tempfile.mkdtemp(prefix="scan_coverage-"))
    out.mkdir(parents=True, exist_ok=True)
    rev = revision()
    print(f"seed {args.seed}, emulator speed {args.speed:g}, code {rev}, scans in {out}")
    print(f"auto scans a band of each object's height only: levels every "
          f"{AUTO_SPACING_MM:g} mm from {AUTO_LOWEST_MM:g} mm up to "
          f"{AUTO_LOWEST_MM + args.band_mm:g} mm (--band-mm {args.band_mm:g}), not the whole "
          f"height, to keep the emulator's time within a bench run; coverage is of the true "
          f"reachable surface within that band (+-{SPACING_MM / 2:g} mm) for every mode")
    print("ranging calibration on the block ...", flush=True)
    setup = calibrate(args.seed, args.speed)
    rows: list[dict] = []
    results = {"code": rev, "seed": args.seed, "speed": args.speed, "band_mm": args.band_mm,
               "spacing_mm": SPACING_MM, "margin_mm": MARGIN_MM, "targets": TARGETS,
               "rows": rows}
    printed_head = False
    for obj in objects:
        sim = Simulation(SimConfig(scene=obj, seed=args.seed))
        size = bounding_size(SCENES[obj]()[0])
        round_ = OBJECTS.get(obj, True)
        truths = sim.truth_objects()
        levels = auto_levels(size[2], args.band_mm)
        z_band = (levels[0] - SPACING_MM / 2, levels[-1] + SPACING_MM / 2)
        s = sim.scene
        surface = {m: reachable_truth(truths, s.v, s.n, SPACING_MM, z_band, a)
                   for m, a in MAX_INCIDENCE_DEG.items()}
        sim.close()
        samples = {m: len(x) for m, x in surface.items()}
        reference = {"surface": surface, "samples": samples,
                     "true_radius_mm": true_reach_mm(truths)}
        print(f"\n{obj}: {size[0]:.1f} x {size[1]:.1f} x {size[2]:.1f} mm "
              f"({'round' if round_ else 'not round'}), farthest from the table axis "
              f"{reference['true_radius_mm']:.1f} mm; band z {z_band[0]:g}..{z_band[1]:g} mm, "
              + ", ".join(f"{samples[m]} truth samples {m.upper()} reaches (within "
                          f"{MAX_INCIDENCE_DEG[m]:g} deg)" for m in MODS), flush=True)
        for mode in args.modes:
            print(f"  {mode} ...", file=sys.stderr, flush=True)
            wall0 = time.monotonic()
            try:
                plan, reach = bench_plan(obj, size, round_, SCENES[obj]()[0].material, mode,
                                         reference["true_radius_mm"])
                if reach is not None:
                    print(f"  note: the footprint's bounding cylinder is inside the object's "
                          f"farthest point: reach_mm = {reach:g}")
                if mode in ("auto", "sweep"):
                    plan = replace(plan, levels_mm=levels)
                    plan.validate()
                r = one_scan(obj, mode, plan, setup, args.seed, args.speed, z_band, reference,
                             out, args.timeout)
            except Exception as e:  # a failed scan is a row, not the end of the bench
                tb = traceback.format_exc()
                print(tb, file=sys.stderr, flush=True)
                reason = (str(e).strip().splitlines() or [""])[0]
                r = {"object": obj, "mode": mode, "ok": False,
                     "reason": f"{type(e).__name__}: {reason}"[:300],
                     "wall_s": time.monotonic() - wall0, "traceback": tb}
            r["reference_samples"] = reference["samples"]
            r["true_radius_mm"] = reference["true_radius_mm"]
            rows.append(r)
            if not printed_head:
                print(HEAD)
                printed_head = True
            print(row_text(r), flush=True)
            if args.json:
                args.json.write_text(json.dumps(results, indent=1, default=float))
    print("\ncolumns: points per modality; wall and emulated seconds of the scan; stored "
          "points per emulated second; coverage of the truth in the band each modality "
          f"reaches (OA within {MAX_INCIDENCE_DEG['oa']:g} deg of head on, US within "
          f"{MAX_INCIDENCE_DEG['us']:g}; '-': none) at {SPACING_MM:g} mm; e: |distance| "
          "of the points to the true surface (mean, 95th "
          f"percentile, mm); laser duty; viol: laser shots with the sensor within "
          f"{MARGIN_MM:g} mm of the true surface; clear: its least clearance (mm)")
    lines = summary(rows, args.modes)
    results["summary"] = lines
    print("\n" + "\n".join(lines))
    if args.json:
        args.json.write_text(json.dumps(results, indent=1, default=float))
    return 1 if any(not r["ok"] for r in rows) else 0


if __name__ == "__main__":
    sys.exit(main())
