"""A scan database made straight from the physics (no serial link): household objects
measured as `dmdsm scan` would, for classification tests and benchmarks.

`python -m dmdsm.sim.data.dataset --out DB --points 24 --seed 0 [--fly-mm 4]` writes
DB/scans/*.h5 and the catalogue. Points come in raster lines of LINE positions across the
object's face at a random height and a table angle near 0/90/180/270 deg, as a scan plan
takes them; waveforms are averaged as the board's core does (each shot from its own
sampling phase; with --fly-mm, from its own place along the line's travel, as a fly scan
takes them); distances come from the host's ranging (PointRanger, with the previous point
of the line for lone pulses) with the emulator's true t0 and c, so the files match real
scans.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from dmdsm.host.files import file_hash
from dmdsm.host.ranging.calibrate import RangeCal, RangingSetup
from dmdsm.host.ranging.matched_filter import gaussian_pulse
from dmdsm.host.scan.catalogue import connect, record
from dmdsm.host.scan.plan import ScanPlan, point_ranger
from dmdsm.host.scan.scanfile import PHASES, ScanWriter

from ..boards.sensor.core_board import ADC_RATE_HZ, TICK_HZ, averaged_shots
from ..physics.objects import HOUSEHOLD, bounding_size, household
from ..physics.scene import Scene, table_frame
from ..physics.signals import MATERIALS, SensorModel, received

US_ONLY, OA_ONLY = {"glass", "steel"}, {"foam"}
LINE = 8  # points per raster line


def true_setup(model: SensorModel) -> RangingSetup:
    """A ranging setup with the emulator's t0 and c and Gaussian templates."""
    fs = ADC_RATE_HZ
    c = model.c_mm_us * 1e6
    cals = {"oa": RangeCal("oa", model.t0_oa_us * 1e-6, c, 0, 0, 0, 0),
            "us": RangeCal("us", model.t0_us_us * 1e-6, c, 0, 0, 0, 0)}
    # the received pulses: aluminium's OA and the US echo, through the receive chain
    oa = received(model, MATERIALS["aluminium"].oa_fc_mhz, MATERIALS["aluminium"].oa_bw, "oa")
    us = received(model, model.us_fc_mhz, model.us_bw, "us")
    tmpl = {"oa": gaussian_pulse(fs, oa[0] * 1e6, oa[1]),
            "us": gaussian_pulse(fs, us[0] * 1e6, us[1])}
    return RangingSetup(fs, tmpl, {"oa": (0, 1024), "us": (0, 1024)}, cals)


def scan_object(db: Path, name: str, points: int, seed: int, average: int = 16,
                n_samples: int = 1024, fly_mm: float = 0.0) -> Path:
    """Measure `points` positions around one household object into DB; returns the file.
    fly_mm > 0: as a fly scan does, each waveform's shots are spread evenly over a travel
    along X, drawn per raster line from 0..fly_mm (the depth changes over it on a curved
    face, which smears the pulse; docs/classification.md)."""
    material = HOUSEHOLD[name][0]
    obj = household(name)[0]
    w, dep, h = bounding_size(obj)
    radius = float(np.hypot(w, dep) / 2) if type(obj.shape).__name__ == "Box" else w / 2
    scene = Scene(objects=[obj])
    model = SensorModel()
    rng = np.random.default_rng(seed)  # the shots' noise and phases
    place = np.random.default_rng([seed, 1])  # the lines: the same places with or without fly
    v = scene.v / np.linalg.norm(scene.v)
    B = table_frame(scene.n)
    mod = "us" if material in US_ONLY else "oa" if material in OA_ONLY else "both"
    plan = ScanPlan(name, material, radius_mm=radius + 1, height_mm=h, modality=mod,
                    average=average, samples=n_samples)
    setup = true_setup(model)
    ranger = point_ranger(plan, setup, n_samples, TICK_HZ)
    path = db / "scans" / f"{name}-s{seed}.h5"
    path.unlink(missing_ok=True)
    writer = ScanWriter.create(
        path, scan_id=path.stem, plan_text=plan.to_toml(), plan_hash=f"sim{seed}",
        n_samples=n_samples, sensor={"board": "hil_sim dataset", "tick_hz": TICK_HZ,
                                     "adc_rate_hz": ADC_RATE_HZ, "config_pretrigger": 0},
        calibration={"v": v.tolist(), "n": scene.n.tolist(), "X_R": scene.X_R.tolist()},
        calibration_toml="", ranging_json=setup.to_json(),
        sample={"name": name, "material": material, "notes": "hil_sim dataset"},
        program_version="sim")
    previous = None
    for i in range(points):
        if i % LINE == 0:  # a new raster line: one table angle and height, X across the face
            theta = float(90 * place.integers(4) + place.uniform(-15, 15))  # plan angles
            z = float(place.uniform(0.2, 0.8) * min(h, 80.0))
            x0 = float(place.uniform(-0.4, -0.2) * w)
            travel = float(place.uniform()) * fly_mm  # drawn either way: same places
            previous = None
        x = x0 + (i % LINE) * 0.7 * w / (LINE - 1)
        front = scene.X_R + B @ np.array([x, 0.0, z]) - (radius + 8.0) * v
        if travel > 0:  # one hit per shot along the travel, centred on this position
            shots = (np.arange(average) + 0.5) / average - 0.5
            hit = scene.cast_many(front + np.outer(travel * shots, B[:, 0]), theta)
        else:
            hit = scene.cast(front, theta)
        wave, phase = averaged_shots(hit, model, n_samples, average, rng, seed)
        r = ranger(wave, phase, 0, previous)
        found = {m: val for m, val in r.items() if np.isfinite(val[0])}
        previous = (next(iter(found.values()))[0] if found else np.nan,  # as run_scan does
                    {m: val[1] for m, val in found.items()})
        writer.append(wave, stage_position_mm=front.tolist(), theta_deg=theta, level=0,
                      column=i % LINE, angle_index=i // LINE, received=True, attempts=1,
                      n_average=average,
                      timestamp=i, trigger_phase=phase, distance_oa_mm=r["oa"][0],
                      distance_us_mm=r["us"][0], snr_oa_db=r["oa"][1], snr_us_db=r["us"][1],
                      phase_time_s=np.zeros(len(PHASES)), host_time=0.0, point_index=i)
    writer.close("complete")
    record(db, path.stem, n_planned=points, content_hash=file_hash(path))
    return path


def make_database(db: Path, points: int, seed: int = 0,
                  objects: list[str] | None = None, fly_mm: float = 0.0) -> list[Path]:
    """Scan every household object (or the given ones) into DB (fly_mm: see scan_object)."""
    connect(db, create=True).close()
    return [scan_object(db, name, points, seed + k, fly_mm=fly_mm) for k, name in
            enumerate(objects or list(HOUSEHOLD))]


def main(argv: list[str] | None = None) -> int:
    """Command line: write a database."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True, help="database directory")
    ap.add_argument("--points", type=int, default=24, help="points per object")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--fly-mm", type=float, default=0.0,
                    help="fly lines: each waveform's shots spread over up to this travel (mm)")
    args = ap.parse_args(argv)
    if not 0.0 <= args.fly_mm <= 20.0:
        ap.error(f"--fly-mm must be 0..20 mm (got {args.fly_mm:g})")
    paths = make_database(args.out, args.points, args.seed, fly_mm=args.fly_mm)
    print(f"wrote {len(paths)} scans to {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
