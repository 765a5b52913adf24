"""The demo's emulator session (both boards on ptys, `dmdsm` commands in-process), stages 1-3, 5.

Stages: (1) ranging calibration on the block (t0, c), (2) the rig calibration of §IV-D
(Table I with uncertainties next to the emulator's truth), (3) the aluminium block
validation scan of §V-A2, (4) a household set scanned into a database, (5) material
classification. Where a user re-mounts the rig or an object by hand, the demo writes the
scene's name into the emulator's `scene` file (`dmdsm sim --link-dir DIR` watches it).
Stage 4 is in household.py; run.py runs the five and writes the report.
"""

from __future__ import annotations

import contextlib
import io
import json
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..report.page import Section
from ..scan.plan import ScanPlan

PAPER_E = {"oa": (0.06, 0.06), "us": (0.15, 0.11)}
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


def write_plan(d: Demo, name: str, plan: ScanPlan) -> Path:
    """out/plans/NAME.toml: the plan as a user would write it for `dmdsm scan --plan`."""
    path = d.out / "plans" / f"{name}.toml"
    path.parent.mkdir(exist_ok=True)
    path.write_text(plan.to_toml())
    return path


def scan_into(d: Demo, plan: Path, db: str) -> dict:
    """`dmdsm scan` of a plan into out/DB with the stage 1 and 2 results; its JSON summary."""
    return json.loads(d.run("scan", *d.ports, "--no-home", "--calibration",
                            str(d.out / "calibration.toml"), "--ranging",
                            str(d.out / "ranging.json"), "--plan", str(plan), "--db",
                            str(d.out / db), "--json").splitlines()[-1])


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
    from ..report.plots import rig_figure

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
    plan = ScanPlan("aluminium_block", material="aluminium", radius_mm=30.0, height_mm=40.0,
                    levels_mm=[20.0] if d.quick else [12.0, 24.0],
                    angles_deg=[0.0, 90.0, 180.0, 270.0], half_width_mm=32.0,
                    step_mm=4.0 if d.quick else 2.0, modality="both", turntable_radius_mm=60.0)
    s = scan_into(d, write_plan(d, "aluminium_block", plan), "validation")
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
