"""`dmdsm demo`: the paper's experiments end to end on the emulator, through the same `dmdsm`
commands and serial paths a user with hardware runs, into out/report.html.

Stages: (1) ranging calibration on the block (t0, c), (2) the rig calibration of §IV-D
(Table I with uncertainties next to the emulator's truth), (3) the aluminium block
validation scan of §V-A2, (4) a household set scanned into a database, (5) material
classification. Where a user re-mounts the rig or an object by hand, the demo writes the
scene's name into the emulator's `scene` file (`dmdsm sim --link-dir DIR` watches it).
"""

from __future__ import annotations

import contextlib
import io
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from .page import Section, html_page, markdown

PAPER_E = {"oa": (0.06, 0.06), "us": (0.15, 0.11)}
US_ONLY, OA_ONLY = {"glass", "steel"}, {"foam"}
TITLES = {
    "stage_ranging": "1. Ranging calibration (t0, c per modality; the stage as a ruler)",
    "stage_rig": "2. Scanner calibration with the rig (paper §IV-D, Table I)",
    "stage_block": "3. Aluminium block validation (paper §V-A2, Fig. 3)",
    "stage_household": "4. Household set scanned into the database (paper §V-B, Fig. 4)",
    "stage_classify": "5. Material classification (paper §V-B2, Fig. 5)",
}


class Demo:
    """The emulator on ptys plus a way to run `dmdsm` commands and collect their output."""

    def __init__(self, out: Path, quick: bool, speed: float,
                 command: Callable[[list[str]], int], stage_firmware: str = "") -> None:
        from dmdsm.sim.servers.emulator import Emulator
        from dmdsm.sim.servers.runner import SimConfig

        self.out, self.quick, self.command = out, quick, command
        self.step_points_per_s: float | None = None  # the block's step-and-shoot rate
        self.rates: dict[str, float] = {}  # the household set's points/s per scan mode
        self.emulator = Emulator(SimConfig(scene="aluminium_block", seed=7,
                                           stage_firmware=stage_firmware),
                                 speed=speed, link_dir=str(out / "ports")).start()
        self.sim = self.emulator.sim
        self.ports = ["--sensor", str(out / "ports" / "sensor"),
                      "--stage", str(out / "ports" / "stage")]

    def run(self, *args: str) -> str:
        """`dmdsm ARGS` in this process; returns its stdout; raises on a non-zero exit."""
        buf = io.StringIO()
        with contextlib.redirect_stdout(buf):
            rc = self.command(list(args))
        if rc != 0:
            raise RuntimeError(f"dmdsm {' '.join(args[:2])} exited with {rc}")
        return buf.getvalue()

    def mount(self, scene: str) -> None:
        """The user jogs the sensor back and puts another object on the turntable."""
        self.run("stage", "move", "-y", "150", *self.ports[2:])
        (self.out / "ports" / "scene").write_text(scene + "\n")
        time.sleep(0.5)  # the emulator checks the file every 0.2 s

    def close(self) -> None:
        """Stop the emulator."""
        self.emulator.stop()


def _truth(sim: object) -> dict[str, np.ndarray]:
    s = sim.scene
    return {"v": s.v / np.linalg.norm(s.v), "n": s.n / np.linalg.norm(s.n), "X_R": s.X_R}


def stage_ranging(d: Demo) -> Section:
    """Step the sensor away from the block's face: t0 per modality (c from 20 degC air)."""
    sec = Section(TITLES["stage_ranging"])
    d.run("stage", "home", *d.ports[2:])
    d.run("stage", "move", "-x", "235", "-y", "266", "-z", "20", *d.ports[2:])
    start = d.sim.truth()["distance_mm"]  # a gauge block would give this on the machine
    rep = json.loads(d.run("calibrate-range", *d.ports, "-x", "235", "-y", "266", "-z", "20",
                           "--start-distance", f"{start:.4f}", "--steps",
                           "8" if d.quick else "21", "--step", "1", "--shots", "2",
                           "--lateral", "3" if d.quick else "5", "--fixed-c",
                           "-o", str(d.out / "ranging.json"), "--json"))
    t = d.sim.truth()
    setup = json.loads((d.out / "ranging.json").read_text())["modalities"]
    rows = []
    for m, t0_true in (("oa", t["t0_oa_us"]), ("us", t["t0_us_us"])):
        c = setup[m]["calibration"]
        t0, sd = c["t0_s"] * 1e6, c["t0_std_s"] * 1e6
        z = (t0 - t0_true) / sd if sd > 0 else float("nan")
        rows.append([m.upper(), f"{t0:.4f} ± {sd:.4f}", f"{t0_true:.4f}", f"{z:+.1f}",
                     f"{c['c_mm_s'] / 1e3:.2f} (air model, fixed)",
                     f"{c['residual_mm'] * 1e3:.0f}"])
        sec.values[m] = {"t0_us": t0, "t0_std_us": sd, "t0_true_us": t0_true, "z": z,
                         "c_m_s": c["c_mm_s"] / 1e3, "residual_um": c["residual_mm"] * 1e3}
        sec.ok &= bool(abs(z) < 4)
    sec.table(["modality", "t0 ± std (µs)", "emulator truth (µs)", "error / std", "c (m/s)",
               "surface scatter per spot (µm)"], rows)
    sec.text.append(f"{rep['oa'].split(', ')[-1]} on the block's face, each on a fresh "
                    f"surface spot. The std is the least-squares one; the surface scatter is "
                    f"the fit's residual, which each scanned distance's std includes.")
    return sec


def stage_rig(d: Demo) -> tuple[Section, dict]:
    """Tip frames, edge frames, solved into Table I."""
    from dmdsm.sim.physics.scene import table_frame

    from ..calibration.rig_file import read_raw
    from .plots import rig_figure

    sec = Section(TITLES["stage_rig"])
    tr = _truth(d.sim)
    frame = table_frame(tr["n"])
    data, cal = d.out / "rig.csv", d.out / "calibration.toml"
    data.unlink(missing_ok=True)
    q = ["--tip-depths", "0", "4", "8", "--tip-step", "0.2", "--edge-levels", "10", "25",
         "40", "--edge-step", "0.15"] if d.quick else []
    d.mount("rig_horizontal")
    tip = tr["X_R"] + frame @ np.array([0.0, -10.0, 20.0]) - 6 * tr["v"]
    d.run("calibrate", "--step", "tip", *d.ports, "--ranging", str(d.out / "ranging.json"),
          "--data", str(data), "--at", *(f"{c:.3f}" for c in tip), "--json", *q)
    d.mount("rig_vertical")
    fil = tr["X_R"] + frame @ np.array([25.0, 0.0, 0.0]) - 6.25 * tr["v"]
    r = json.loads(d.run("calibrate", "--step", "edge", *d.ports, "--ranging",
                         str(d.out / "ranging.json"), "--data", str(data), "--at",
                         f"{fil[0]:.3f}", f"{fil[1]:.3f}", "0", "-o", str(cal), "--json", *q))
    rows = []
    for k in ("v", "n", "X_R"):
        est, sd, true = np.array(r[k]), np.array(r["std"][k]), tr[k]
        rows.append([k + (" (mm)" if k == "X_R" else ""),
                     "; ".join(f"{a:.4f} ± {b:.4f}" for a, b in zip(est, sd)),
                     "; ".join(f"{a:.4f}" for a in true),
                     "; ".join(f"{(a - b) / s:+.1f}" if s > 0 else "-"
                               for a, b, s in zip(est, true, sd))])
    sec.table(["parameter", "estimate ± std", "emulator truth (Table I)", "error / std"], rows)
    ang = {k: float(np.degrees(np.arccos(np.clip(np.dot(r[k], tr[k]), -1, 1))))
           for k in ("v", "n")}
    dxr = float(np.linalg.norm(np.array(r["X_R"][:2]) - tr["X_R"][:2]))
    sec.text.append(f"Errors: v {ang['v']:.3f} deg, n {ang['n']:.3f} deg, X_R {dxr:.3f} mm "
                    f"(in the table plane); rms residual {r['rms_residual_mm'] * 1e3:.1f} um; "
                    f"raw points in {data.name}, result in {cal.name}.")
    sec.ok = ang["v"] < 2.0 and ang["n"] < 0.5 and dxr < 0.3
    sec.values = {"v_error_deg": ang["v"], "n_error_deg": ang["n"], "X_R_error_mm": dxr,
                  "result": r, "truth": {k: np.asarray(x).tolist() for k, x in tr.items()}}
    rig_figure(read_raw(data), d.out / "fig2_rig.png")
    sec.figures.append((d.out / "fig2_rig.png", "Response amplitude over the tip frames' "
                        "rasters and the edge frames' sweeps (like the paper's Fig. 2)"))
    return sec, r


def stage_block(d: Demo) -> Section:
    """The block validation scan, reconstructed with the calibration just made."""
    from ..scan.points import scan_points, validate_block
    from ..scan.scanfile import read_scan

    sec = Section(TITLES["stage_block"])
    d.mount("aluminium_block")
    plan = d.out / "plans" / "aluminium_block.toml"
    plan.parent.mkdir(exist_ok=True)
    plan.write_text(_plan("aluminium_block", "aluminium", 30.0, 40.0,
                          "[20.0]" if d.quick else "[12.0, 24.0]",
                          "[0.0, 90.0, 180.0, 270.0]", 32.0, 4.0 if d.quick else 2.0, "both"))
    s = json.loads(d.run("scan", *d.ports, "--no-home", "--calibration",
                         str(d.out / "calibration.toml"), "--ranging",
                         str(d.out / "ranging.json"), "--plan", str(plan), "--db",
                         str(d.out / "validation"), "--json").splitlines()[-1])
    truth = d.out / "block.toml"
    truth.write_text('shape = "box"\nsize_mm = [50.0, 30.0, 40.0]\n')
    rec = json.loads(d.run("reconstruct", s["file"], "--truth", str(truth), "--plot",
                           str(d.out / "fig3_block.png"), "--ply",
                           str(d.out / "block.ply"), "--json"))
    scan = read_scan(Path(s["file"]), waveforms=False)
    scan.calibration.update(_truth(d.sim))
    ideal = validate_block(scan_points(scan), (50.0, 30.0))
    rows = []
    for m, (pm, ps) in PAPER_E.items():
        f, g = rec["validation"][m], ideal[m]
        rows.append([m.upper(), f"{f['e_mean_mm']:.3f} ± {f['e_std_mm']:.3f}",
                     f"{g['e_mean_mm']:.3f} ± {g['e_std_mm']:.3f} "
                     f"(mean ± {g['e_mean_se_mm']:.3f})", f"{pm:.2f} ± {ps:.2f}",
                     f"{g['e_over_std_rms']:.2f}", f["n"]])
        sec.ok &= g["e_mean_mm"] <= pm + 3 * g["e_std_mm"] / np.sqrt(g["n"])
        sec.values[m] = {"calibrated": f, "true_parameters": g, "paper": [pm, ps]}
    sec.table(["modality", "e (mm), calibration from stage 2",
               "e (mm), emulator's true v, n, X_R", "paper", "RMS e / point std", "points"],
              rows)
    sec.text.append("e is given as mean ± spread (std of e over the points), as the paper "
                    "does; the mean's own standard error is in brackets. Each distance "
                    "carries its own std (the bound at its SNR with the surface scatter from "
                    "the ranging calibration); RMS e / std near 1 says those stds hold.")
    d.step_points_per_s = float(s["points_per_s"])
    sec.text.append(f"{s['points']} points at {s['points_per_s']} points/s (step and shoot); "
                    f"per point (ms): "
                    + ", ".join(f"{k} {v}" for k, v in s["ms_per_point"].items()))
    sec.figures.append((d.out / "fig3_block.png", "Reconstructed block contour: OA squares, "
                        "US crosses, fitted outlines (like the paper's Fig. 3)"))
    return sec


def _plan(obj: str, material: str, radius: float, height: float, levels: str, angles: str,
          half: float, step: float, modality: str, fly: bool = False) -> str:
    # fly: 12 shots per waveform at 1 kHz, step_mm apart (2 mm: 167 mm/s; docs/scanning.md)
    extra = 'mode = "fly"\naverage = 12\n' if fly else ""
    return (f'[sample]\nobject_id = "{obj}"\nmaterial = "{material}"\n[object]\n'
            f"radius_mm = {radius:.1f}\nheight_mm = {height:.1f}\n"
            f"turntable_radius_mm = 60.0\n[scan]\nlevels_mm = {levels}\n"
            f"angles_deg = {angles}\nhalf_width_mm = {half:.1f}\nstep_mm = {step}\n"
            f'modality = "{modality}"\n{extra}')


def stage_household(d: Demo) -> Section:
    """Every household object scanned into one database (Fig. 4 contours)."""
    from dmdsm.sim.physics.objects import HOUSEHOLD, bounding_size, household

    from ..scan.points import scan_points
    from ..scan.scanfile import read_scan
    from .plots import contour_figure

    sec = Section(TITLES["stage_household"])
    names = list(HOUSEHOLD)
    rows = []
    for name in names:
        material = HOUSEHOLD[name][0]
        obj = household(name)[0]
        w, dep, height = bounding_size(obj)
        boxy = type(obj.shape).__name__ == "Box"
        radius = float(np.hypot(w, dep) / 2) if boxy else w / 2
        mod = "us" if material in US_ONLY else "oa" if material in OA_ONLY else "both"
        d.mount(name)
        runs = {}
        for mode, db in (("step", "db"), ("fly", "db_fly")):
            plan = d.out / "plans" / f"{name}{'' if mode == 'step' else '_fly'}.toml"
            plan.write_text(_plan(name, material, radius + 1.0, height,
                                  f"[{min(0.5 * height, 40.0):.1f}]",
                                  "[0.0]" if d.quick else "[0.0, 90.0, 180.0, 270.0]",
                                  0.35 * w, (8.0 if d.quick else 4.0) if mode == "step"
                                  else 2.0, mod, fly=mode == "fly"))
            runs[mode] = json.loads(d.run("scan", *d.ports, "--no-home", "--calibration",
                                          str(d.out / "calibration.toml"), "--ranging",
                                          str(d.out / "ranging.json"), "--plan", str(plan),
                                          "--db", str(d.out / db), "--json").splitlines()[-1])
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
        if name in ("soda_can", "apple_red", "foam_block", "glass_jar", "tissue_box",
                    "steel_can", "plastic_bottle"):
            contour_figure(scan_points(scan), d.out / f"fig4_{name}.png", title=name)
            sec.figures.append((d.out / f"fig4_{name}.png", f"{name} ({material}): "
                                f"reconstructed contour, OA squares, US crosses"))
        expected = {"us": n_oa == 0 and n_us > 0, "oa": n_us == 0 and n_oa > 0,
                    "both": n_oa > 0 and n_us > 0}[mod]
        fly_expected = {"us": fly_oa == 0 and fly_us > 0, "oa": fly_us == 0 and fly_oa > 0,
                        "both": fly_oa > 0 and fly_us > 0}[mod]
        sec.ok &= expected and fly_expected
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


def stage_classify(d: Demo) -> Section:
    """BOSS and MiniRocket on the database, through `dmdsm classify evaluate`."""
    sec = Section(TITLES["stage_classify"])
    runs = [("minirocket", ["--trials", "5" if d.quick else "50"]),
            # BOSS costs ~45 s per fit here: a few splits keep the demo within 10 minutes
            # (bench/classify.py runs more, and leave one object out)
            ("boss", ["--boss-trials", "1" if d.quick else "3", "--no-loo"])]
    for name, extra in runs:
        out = d.run("classify", "evaluate", "--db", str(d.out / "db"), "--out",
                    str(d.out / "classify"), "--classifiers", name, *extra, "--json")
        res = json.loads(out.splitlines()[-1])
        r = res["classifiers"][name]
        sec.values[name] = r
        sec.table([f"{name}: class", f"accuracy ({r['trials']} random 3:1 splits)",
                   "accuracy (leave one object out)"],
                  [[c, f"{a:.1%}", f"{r['loo'][c]:.1%}" if "loo" in r else "-"]
                   for c, a in r["random"].items()])
        art = [a for c, a in r["random"].items() if c != "apple"]
        sec.text.append(f"{name}: artificial materials {min(art):.1%}..{max(art):.1%}, apple "
                        f"{r['random'].get('apple', float('nan')):.1%} (paper: >= 98.5 %, "
                        f"79.0 %)")
    for png in sorted((d.out / "classify").glob("*.png")):
        sec.figures.append((png, f"Confusion matrix {png.stem} (like the paper's Fig. 5)"))
    sec.text.append("Simulated data: the emulator's materials are models (docs/sim.md), so "
                    "these figures show the pipeline works, not that the paper is reproduced.")
    return sec


def keep_previous_databases(out: Path) -> None:
    """Each demo scans into fresh databases: a previous run's `db` and `validation` (and its
    calibrations) move to out/previous/<name>-<time of their last change>, so the classifier
    never mixes runs (or sample rates) and nothing a user may want is deleted."""
    for name in ("db", "db_fly", "validation", "ranging.json", "calibration.toml"):
        old = out / name
        if old.exists() and not old.is_symlink():
            stamp = time.strftime("%Y%m%d-%H%M%S", time.localtime(old.stat().st_mtime))
            target = out / "previous" / f"{old.stem}-{stamp}{old.suffix}"
            n = 1
            while target.exists():
                n += 1
                target = out / "previous" / f"{old.stem}-{stamp}-{n}{old.suffix}"
            target.parent.mkdir(exist_ok=True)
            old.rename(target)


def run_demo(out_dir: str, command: Callable[[list[str]], int], quick: bool = False,
             speed: float = 8.0, as_json: bool = False, stage_firmware: str = "") -> int:
    """Run every stage through `command` (the `dmdsm` entry point: argv -> exit code), write
    out/report.html, out/report.md and out/summary.json; 0 if all passed. as_json: progress
    to stderr, the summary as one JSON line on stdout. stage_firmware: a Marlin ELF run
    under simavr as the stage board, at most 2x real time (simavr's pace on one core)."""
    say = sys.stderr if as_json else sys.stdout
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    keep_previous_databases(out)
    t_all = time.perf_counter()
    if stage_firmware:
        speed = min(speed, 2.0)
    d = Demo(out, quick, speed, command, stage_firmware)
    sections: list[Section] = []
    stages = [stage_ranging, stage_rig, stage_block, stage_household, stage_classify]
    try:
        for stage in stages:
            t0 = time.perf_counter()
            try:
                got = stage(d)
            except (RuntimeError, ValueError, OSError) as e:
                got = Section(TITLES[stage.__name__], ok=False, text=[str(e)])
            sec = got[0] if isinstance(got, tuple) else got
            sec.seconds = time.perf_counter() - t0
            sections.append(sec)
            print(f"{sec.title}: {'ok' if sec.ok else 'FAILED'} ({sec.seconds:.0f} s)",
                  flush=True, file=say)
            if not sec.ok and stage in (stage_ranging, stage_rig):
                break  # later stages need these
    finally:
        d.close()
    title = f"dmdsm demo{' (quick)' if quick else ''}: the paper's experiments on the emulator"
    total = time.perf_counter() - t_all
    sections[-1].text.append(f"Total {total:.0f} s on this machine.")
    (out / "report.md").write_text(markdown(title, sections))
    (out / "report.html").write_text(html_page(title, sections))
    summary = {"ok": bool(all(s.ok for s in sections)), "seconds": total,
               "report": str(out / "report.html"), "household_points_per_s": d.rates,
               "stages": {s.title.split(".")[0]: {"title": s.title, "ok": bool(s.ok),
                                                  "seconds": s.seconds, "values": s.values}
                          for s in sections}}
    (out / "summary.json").write_text(json.dumps(summary, indent=1, default=float))
    print(f"report: {out / 'report.html'} ({total:.0f} s)", file=say)
    if as_json:
        print(json.dumps(summary, default=float))
    return 0 if all(s.ok for s in sections) and len(sections) == len(stages) else 1
