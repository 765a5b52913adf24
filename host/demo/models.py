"""Stage 6 of the demo: the 3D contour/material database — a campaign over the household set
(`dmdsm campaign`: each object mounted, auto scanned, modelled, classified), each model judged
against the emulator's truth and shown in 3D in the report."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..report.page import Section
from ..scan.plan import modality_for
from ..scan.reach import US_MAX_INCIDENCE_DEG
from .session import TITLES, Demo
from .sweeps import met_band, span_duty, sweep_scans

# one object per material of the household set (emulator time: every object of it at every
# level would take hours); the quick demo takes the first
CAMPAIGN = ("soda_can", "tissue_box", "plastic_tub", "apple_red", "foam_cup", "glass_jar",
            "steel_can")
LEVELS = 3           # the auto scans' levels, 2 mm apart about half the height (at most 40)
LEVELS_QUICK = 3
SPACING_MM = 2.0
# the true surface each modality's coverage is of: within this of head on from some table
# angle (an auto plan's max_incidence_deg for OA; US echoes only near head on)
INCIDENCE_DEG = {"oa": 45.0, "us": US_MAX_INCIDENCE_DEG}
SWEEP_TARGET = 0.95  # a sweep's coverage of the truth, per modality (issue 32: at 2 mm)


def campaign_file(d: Demo, names: tuple[str, ...], levels: int) -> Path:
    """out/campaign.toml: the objects as a user lists them (id, material, size, levels)."""
    from dmdsm.sim.physics.objects import HOUSEHOLD, bounding_size, household

    lines = ["# the demo's campaign (dmdsm campaign, docs/scanning.md)", ""]
    for name in names:
        material = HOUSEHOLD[name][0]
        obj = household(name)[0]
        w, dep, h = bounding_size(obj)
        boxy = type(obj.shape).__name__ == "Box"
        mid = min(0.5 * h, 40.0)
        z = [round(mid + SPACING_MM * (k - (levels - 1) / 2), 1) for k in range(levels)]
        mod = modality_for(material)
        lines += ["[[object]]", f'id = "{name}"', f'material = "{material}"',
                  f"size_mm = [{w:.1f}, {dep:.1f}, {h:.1f}]",
                  f"round = {'false' if boxy else 'true'}", f'modality = "{mod}"',
                  f"levels_mm = [{', '.join(f'{x:g}' for x in z)}]", ""]
    path = d.out / "campaign.toml"
    path.write_text("\n".join(lines))
    return path


def judge(model: object, truths: list, z_band: tuple[float, float]) -> dict:
    """A model against the truth within its scanned band: |error| of the supported vertices
    (mean, p95, mm), RMS error/sigma, and the share of them whose material is the truth's."""
    sup = model.supported & (model.vertices_mm[:, 2] >= z_band[0]) & \
        (model.vertices_mm[:, 2] <= z_band[1])
    V = model.vertices_mm[sup]
    if not len(V):
        return {"vertices": 0}
    sd = np.stack([t.signed_distance(V) for t in truths])
    k = np.abs(sd).argmin(axis=0)
    err = -sd[k, np.arange(len(V))]
    out = {"vertices": int(len(V)), "e_mean_mm": float(np.abs(err).mean()),
           "e_p95_mm": float(np.percentile(np.abs(err), 95)),
           "z_rms": float(np.sqrt(np.mean((err / model.sigma_mm[sup]) ** 2)))}
    mat = model.material[sup]
    has = mat != ""
    if has.any():
        truth = np.empty(int(has.sum()), dtype=object)
        for j in np.unique(k[has]):  # one nearest-face query per object, not per vertex
            sel = k[has] == j
            truth[sel] = truths[int(j)].material_at(V[has][sel])
        out["material_right"] = float((mat[has] == truth).mean())
    return out


def own_part_z(db: Path, name: str, truths: list, z_band: tuple[float, float]
               ) -> float | None:
    """RMS error/sigma of the object's model rebuilt from the same scans without the
    calibrations' part of sigma (build_object_model(calibration_part=False)): what one run
    can check; None if that build fails."""
    from ..model.build import build_object_model
    from ..model.store import ModelError

    try:
        model = build_object_model(db, name, calibration_part=False)
    except ModelError:
        return None
    return judge(model, truths, z_band).get("z_rms")


def band_coverage(truths: list, v: np.ndarray, n: np.ndarray, files: dict[str, str],
                  z_band: tuple[float, float]) -> dict:
    """Per scan (name -> file), per modality: the share of the object's true surface in the
    band that the modality can see (within INCIDENCE_DEG of it from some table angle: US
    only near head on) with a point of it within 2 mm."""
    from dmdsm.sim.physics.visibility import reachable_surface

    from ..scan.coverage import coverage
    from ..scan.points import scan_points
    from ..scan.scanfile import read_scan

    ref = {m: np.concatenate([reachable_surface(t, v, n, spacing_mm=SPACING_MM,
                                                z_range_mm=z_band, max_incidence_deg=a)[0]
                              for t in truths]) for m, a in INCIDENCE_DEG.items()}
    out = {}
    for mode, f in files.items():
        pts = scan_points(read_scan(Path(f), waveforms=False))
        out[mode] = {m: float(coverage(ref[m], pts[m]["P"], SPACING_MM)) for m in ("oa", "us")}
    return out


def _fixed_scans(d: Demo, name: str) -> dict[str, str]:
    """Stage 4's step and fly scans of the object (their files), for the comparison."""
    from ..scan.catalogue import list_scans

    out = {}
    for mode, db in (("step", "db"), ("fly", "db_fly")):
        rows = [r for r in list_scans(d.out / db, name) if r["status"] == "complete"]
        if rows:
            out[mode] = rows[-1]["path"]
    return out


def stage_models(d: Demo) -> Section:
    """Train the classifier on stage 4's databases, run the campaign, judge and show each
    model."""
    from dmdsm.sim.physics.objects import household

    from ..model.store import load_object_model
    from ..report.viewer import model_section

    sec = Section(TITLES["stage_models"])
    clf = d.out / "materials.npz"
    # both of stage 4's databases: the campaign's auto scans are fly lines, whose pulses the
    # depth change over each waveform's travel smears (docs/classification.md)
    d.run("classify", "train", "--db", str(d.out / "db"), "--db", str(d.out / "db_fly"),
          "-o", str(clf), "--json")
    names = CAMPAIGN[:1] if d.quick else CAMPAIGN
    toml = campaign_file(d, names, LEVELS_QUICK if d.quick else LEVELS)
    db = d.out / "db_models"
    out = d.run("campaign", str(toml), "--db", str(db), *d.ports, "--calibration",
                str(d.out / "calibration.toml"), "--ranging", str(d.out / "ranging.json"),
                "--classifier", str(clf), "--yes", "--json", ok=(0, 1))
    rows = json.loads(out.splitlines()[-1])["objects"]
    bands = {r["object_id"]: load_plan_levels(toml, r["object_id"]) for r in rows}
    sweeps = sweep_scans(d, tuple(bands), bands)
    s = d.sim.scene
    v, n = s.v / np.linalg.norm(s.v), s.n / np.linalg.norm(s.n)
    table, missing, cover, worse, idle, swept, short = [], [], [], [], [], [], []
    for r in rows:
        name = r["object_id"]
        try:
            model = load_object_model(db, name)
        except ValueError as e:
            missing.append(f"{name} ({e})")
            continue
        z = model.points_mm[:, 2]
        band = (float(z.min()) - 1.0, float(z.max()) + 1.0)
        truths = [_truth(o) for o in household(name)]
        j = judge(model, truths, band)
        j["z_rms_own"] = own_part_z(db, name, truths, band)
        files = {**_fixed_scans(d, name), "auto": str(db / "scans" / f"{r['scan_id']}.h5")}
        cov = band_coverage(truths, v, n, files, band)
        duty = {mode: span_duty(f) for mode, f in files.items()}
        for mode in ("step", "fly", "auto"):
            if mode in cov:
                cover.append([name, mode, _pct(cov[mode]["oa"]), _pct(cov[mode]["us"]),
                              _pct(duty[mode])])
        # the sweep over the auto scan's follow levels and the auto scan, side by side, in
        # the band the sweep's beam crossed at every radius (the beam dips: below the
        # sensor's Z), the one its own figure is of; else where its points are
        lv = bands[name]
        levels_band = (min(lv) - SPACING_MM / 2, max(lv) + SPACING_MM / 2)
        both = {"auto": files["auto"]}
        if name in sweeps:
            both["sweep"] = sweeps[name]["file"]
            duty["sweep"] = span_duty(both["sweep"])
            own = ((sweeps[name]["summary"].get("coverage") or {}).get("band_mm")
                   or met_band(both["sweep"]))
            levels_band = tuple(own) if own else levels_band
        cov_levels = band_coverage(truths, v, n, both, levels_band)
        told = {"auto": r.get("coverage") or {},  # what each scan reported, from its points
                "sweep": (sweeps.get(name) or {}).get("summary", {}).get("coverage") or {}}
        for mode in both:
            swept.append([name, mode, f"{levels_band[0]:.1f}-{levels_band[1]:.1f}",
                          _pct(cov_levels[mode]["oa"]), _pct(cov_levels[mode]["us"]),
                          f"{_pct(told[mode].get('oa'))} / {_pct(told[mode].get('us'))}",
                          _pct(duty[mode])])
        if not (duty.get("sweep") or 0) >= 0.5:
            idle.append(f"{name} ({_pct(duty.get('sweep'))} %)")
        modality = modality_for(r.get("material", ""))
        mods = ("oa", "us") if modality == "both" else (modality,)
        short += [f"{name} {m.upper()} {_pct(cov_levels['sweep'][m])} %" for m in mods
                  if "sweep" in cov_levels and not cov_levels["sweep"][m] >= SWEEP_TARGET]
        best = max(cov["auto"].values())
        fixed = max((c for k, m in cov.items() if k in ("step", "fly") for c in m.values()),
                    default=0)
        if not best > fixed:
            worse.append(f"{name} (auto {100 * best:.0f} % vs fixed {100 * fixed:.0f} %)")
        verdict = r.get("verdict") or {}
        table.append([name, r.get("material", ""), r.get("points", 0),
                      _pct(r.get("coverage", {}).get("oa")), _pct(r.get("coverage", {}).get("us")),
                      j.get("vertices", 0), _mm(j.get("e_mean_mm")), _mm(j.get("e_p95_mm")),
                      _f(j.get("z_rms")), _f(j.get("z_rms_own")),
                      _pct(j.get("material_right")),
                      f"{verdict.get('material', '-')}"
                      + (f" ({'right' if verdict.get('right') else 'WRONG'})" if verdict else ""),
                      f"{r.get('total_s', 0):.0f}"])
        sec.values[name] = {"campaign": r, "truth": j, "band_mm": band,
                            "coverage_truth": cov, "laser_duty_span": duty,
                            "levels_band_mm": levels_band, "coverage_levels": cov_levels}
        sec.views.append(model_section(
            f"{name} ({r.get('material', '')}): model v{model.version}", model.vertices_mm,
            model.faces, model.sigma_mm, model.support, model.supported, list(model.classes),
            model.material_prob, points_mm=model.points_mm[~model.points_outlier],
            notes={"scanned band (mm)": f"{band[0]:.1f} to {band[1]:.1f}",
                   "supported vertices in the band": str(j.get("vertices", 0)),
                   "mean error (mm)": _mm(j.get("e_mean_mm"))}))
    sec.check("a model of every object of the campaign:",
              "; ".join(missing) if missing else f"all {len(names)}",
              "the campaign scans, models and classifies each object", not missing)
    sec.check("auto scans cover more of the true surface in their band than the fixed plans:",
              "; ".join(worse) if worse else "yes, every object",
              "coverage at 2 mm of the surface each modality can see (OA within 45 deg, US "
              f"within {US_MAX_INCIDENCE_DEG:g}), from the "
              "emulator's truth (stage 4's step and fly scans: one level, four angles)",
              not worse)
    sec.table(["object", "material", "points", "OA % of outline", "US % of outline",
               "supported vertices", "e mean (mm)", "e p95 (mm)", "RMS e/sigma",
               "RMS e/sigma, calibration apart", "vertex material right",
               "classifier's verdict", "time (s)"], table)
    sec.check("sweeps cover what each modality can see:", "; ".join(short) if short else
              f"yes, every object (at least {100 * SWEEP_TARGET:.0f} % in each modality its "
              f"material answers in)", "issue 32's coverage target, of the truth in the "
              "sweep's own band (second table below)", not short)
    sec.check("sweeps keep the laser busy:", "; ".join(idle) if idle else
              "yes, every object (at least 50 % of the shots fired from its first waveform to "
              "its last in a stored waveform)", "issue 32's laser duty target (50 %)", not idle)
    sec.table(["object", "scan", "OA coverage % (band)", "US coverage % (band)",
               "laser duty % (first to last waveform)"], cover)
    sec.table(["object", "scan", "z band (mm): the sweep's own (its beam across the cylinder)",
               "OA coverage %",
               "US coverage %", "OA / US % the scan reported (of its own outline)",
               "laser duty % (first to last waveform)"], swept)
    sec.text.append(
        f"Each object is also swept over the campaign's levels (`dmdsm scan --mode sweep`, "
        f"into {d.out / 'db_sweep'}: the table turning under the sensor, a ring "
        f"every 2 mm); the second coverage table compares it with the auto scan in that band "
        f"(the first is over the whole band the auto scan's model spans, its first look's "
        f"included), from the emulator's truth beside what each scan reported without it "
        f"(an auto scan of its first look's outline, a sweep of the outline its own points "
        f"measure in the band it swept: docs/scanning.md). The laser duty is the share of "
        f"the shots fired from a scan's first waveform to its last that went into a "
        f"stored waveform; `python bench/scan_coverage.py` gives it from the scan's "
        f"start, approach included. "
        f"`dmdsm campaign {toml}` ({len(names)} object{'s' if len(names) > 1 else ''}, "
        f"one per material, each over {LEVELS_QUICK if d.quick else LEVELS} levels 2 mm "
        f"apart about half its height: the emulator's time), into {db}; the classifier is "
        f"trained on stage 4's step and fly databases (`dmdsm classify train --db "
        f"{d.out / 'db'} --db {d.out / 'db_fly'}`). The errors are of the "
        f"model's supported vertices within the scanned band against the emulator's true "
        f"surface; the surface beyond the band is closed but unsupported (grey in the "
        f"views). RMS e/sigma holds within 0.8-1.25 when the sigma are right; every vertex of "
        f"every model of a run shares one calibration error, one draw of what its stated "
        f"std allows (checked over many runs: `python bench/calibration.py --seeds 40`, `python "
        f"bench/uncertainty.py`). The column beside it is the same scans' models built "
        f"with the calibrations' part of sigma left out: the first counts all of what the "
        f"calibration may be off, the second none of it, and this run's error holds one draw "
        f"of it, so the sigma are right when the two bracket 1 (a run whose calibration is "
        f"close shows the first below 0.8, one whose calibration is further off the second "
        f"above 1.25). `dmdsm db list --models --db {db}`, "
        f"`dmdsm model show OBJECT --db {db} "
        f"--html FILE`, `dmdsm model export OBJECT --db {db} -o FILE.glb`.")
    return sec


def load_plan_levels(toml: Path, name: str) -> list[float]:
    """The levels (mm) the campaign file gives an object."""
    import tomllib

    doc = tomllib.loads(Path(toml).read_text())
    return [float(x) for o in doc.get("object", []) if o.get("id") == name
            for x in o.get("levels_mm", [])]


def _truth(obj: object) -> object:
    from dmdsm.sim.physics.mesh import object_truth

    return object_truth(obj)


def _pct(x: float | None) -> str:
    return "-" if x is None else f"{100 * x:.1f}"


def _mm(x: float | None) -> str:
    return "-" if x is None else f"{x:.3f}"


def _f(x: float | None) -> str:
    return "-" if x is None else f"{x:.2f}"
