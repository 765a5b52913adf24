"""`dmdsm calibrate-range` and `dmdsm range`: the stage as a ruler for t0 and c, and ranging of
recorded acquisitions."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from .range_cal import MODALITIES, RangingSetup, fit_range, learn_template
from .ranging import MatchedFilter, distance_mm, speed_of_sound_mm_s
from .safety import TABLE_I

T0_MAX_S = 10e-6  # prior: trigger-to-emission delays are below 10 us
K = {"oa": 1.0, "us": 2.0}  # one way, round trip


def gate_for(d_mm: float, modality: str, fs_hz: float, c_mm_s: float, n: int,
             t0_s: float | None = None) -> tuple[int, int]:
    """Samples where an echo from d mm can be: for any 0 <= t0 <= T0_MAX_S, or, with a
    calibrated t0_s (s), within a few samples of t0_s + k d / c."""
    t = K[modality] * d_mm / c_mm_s
    if t0_s is not None:
        return max(0, int((t0_s + t) * fs_hz) - 2), min(n, int((t0_s + t) * fs_hz) + 3)
    return max(0, int(t * fs_hz) - 2), min(n, int((t + T0_MAX_S) * fs_hz) + 16)


def calibrate_range(stage: object, sensor: object, start: dict[str, float],
                    start_distance_mm: float, steps: int = 11, step_mm: float = 0.5,
                    shots: int = 10, average: int = 16, temperature_c: float = 20.0,
                    along_beam: float = 1.0 / TABLE_I["v"][1], fit_c: bool = True,
                    lateral: int = 1, lateral_mm: float = 0.5) -> tuple[RangingSetup, dict]:
    """Step the sensor away from a flat target along Y, record, learn pulses, fit t0 and c.

    start_distance_mm is the known beam distance at `start` (a gauge block or feeler);
    each Y step of s mm lengthens the beam path by s * along_beam (1 / v_y for a face
    normal to Y; the paper's v by default). fit_c=False keeps c from the air temperature
    and fits t0 alone: better when the travel is short (c from 20 mm of travel is good to
    ~0.5 %, from a thermometer reading within 1 degC to 0.2 %). lateral > 1 also records
    that many X positions lateral_mm apart at each depth (same distance on a face normal to
    Y): the surface under the spot changes, so its roughness averages out of t0."""
    c0 = speed_of_sound_mm_s(temperature_c)
    fs = sensor.identity.adc_rate_hz
    n = sensor.configure(n_samples=1024, n_average=average, pretrigger=0,
                         trigger_timeout_ms=2000)["n_samples"]
    waves, phases, dists, lats = [], [], [], []
    for i in range(steps):
        for j in range(lateral):
            stage.move(x=start["X"] + j * lateral_mm, y=start["Y"] - i * step_mm,
                       z=start["Z"], wait=True)
            stage.wait()
            got = sensor.acquire(shots)
            ok = got.received
            waves.append(got.samples[ok].astype(float) - 32768.0)
            phases.append(got.trigger_phase[ok] / sensor.identity.tick_hz)
            dists.append(np.full(ok.sum(), start_distance_mm + i * step_mm * along_beam))
            lats.append(np.full(ok.sum(), j))
    x, ph, d = np.vstack(waves), np.concatenate(phases), np.concatenate(dists)
    lat = np.concatenate(lats)
    templates, gates, cals, report = {}, {}, {}, {}
    for m in MODALITIES:
        g = [gate_for(di, m, fs, c0, n) for di in d]
        lo, hi = min(a for a, _ in g), max(b for _, b in g)
        try:
            tmpl = learn_template(x[(d == d[0]) & (lat == 0)], fs, g[0])
        except ValueError:
            report[m] = "no echo (this target gives none in this modality)"
            continue
        mf = MatchedFilter(tmpl, n)
        idx = np.full(len(x), np.nan)
        for di in np.unique(d):  # gate each position around where its echo can be
            sel = d == di
            idx[sel] = mf(x[sel], gate=gate_for(di, m, fs, c0, n)).index
        t = idx / fs + ph
        # one point per position: shots at one position share its surface scatter, so
        # fitting them separately would overstate the precision
        pos = np.unique(d)
        t_pos = np.array([_depth_time(t, d == di, lat, lateral) for di in pos])
        cal = fit_range(t_pos, pos, m, None if fit_c else c0)
        templates[m], gates[m], cals[m] = tmpl, (lo, hi), cal
        report[m] = (f"t0 {cal.t0_s * 1e6:.4f} +/- {cal.t0_std_s * 1e6:.4f} us, "
                     f"c {cal.c_mm_s / 1e3:.2f} +/- {cal.c_std_mm_s / 1e3:.2f} m/s "
                     f"(air model {c0 / 1e3:.2f}), residual {cal.residual_mm * 1000:.1f} um, "
                     f"{cal.n} positions")
    if not cals:
        raise ValueError("no echoes in either modality: is the target in front of the beam?")
    return RangingSetup(fs, templates, gates, cals), report


def _depth_time(t: np.ndarray, sel: np.ndarray, lat: np.ndarray, lateral: int) -> float:
    """Arrival time (s) at one depth: the mean over lateral positions of each one's median
    over its shots (NaN if no shot there has an arrival)."""
    meds = [np.nanmedian(t[sel & (lat == j)]) for j in range(lateral)
            if np.isfinite(t[sel & (lat == j)]).any()]
    return float(np.mean(meds)) if meds else np.nan


def range_waveforms(x: np.ndarray, phase_s: np.ndarray, setup: RangingSetup, modality: str,
                    pretrigger: int = 0, gate: tuple[int, int] | None = None
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Distances (mm, NaN where no echo) and SNR (dB) for baseline-free waveforms."""
    tmpl, cal = setup.templates[modality], setup.cals[modality]
    arr = MatchedFilter(tmpl, x.shape[1])(x, gate=gate or setup.gates[modality])
    t = arr.times_s(setup.fs_hz, phase_s, pretrigger)
    return distance_mm(t, cal.t0_s, cal.c_mm_s, modality), arr.snr_db


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """Register calibrate-range and range."""
    p = sub.add_parser("calibrate-range", help="fit t0 and c with the stage as a ruler")
    p.add_argument("--sensor")
    p.add_argument("--stage")
    p.add_argument("--config", type=Path, default=None)
    p.add_argument("-x", type=float, required=True, help="start X (mm)")
    p.add_argument("-y", type=float, required=True, help="start Y (mm), closest to the target")
    p.add_argument("-z", type=float, required=True, help="start Z (mm)")
    p.add_argument("--start-distance", type=float, required=True,
                   help="beam distance to the flat target at the start (mm)")
    p.add_argument("--steps", type=int, default=11)
    p.add_argument("--step", type=float, default=0.5, help="Y step away from the target (mm)")
    p.add_argument("--shots", type=int, default=10)
    p.add_argument("--average", type=int, default=16)
    p.add_argument("--temperature", type=float, default=20.0, help="air temperature (degC)")
    p.add_argument("--lateral", type=int, default=1,
                   help="X positions per depth (0.5 mm apart) to average surface roughness")
    p.add_argument("--fixed-c", action="store_true",
                   help="take c from --temperature and fit t0 only (short travel)")
    p.add_argument("-o", "--output", type=Path, default=Path("ranging.json"))
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_calibrate_range)
    p = sub.add_parser("range", help="distances from a recorded acquisition (dmdsm acquire)")
    p.add_argument("file", type=Path)
    p.add_argument("--calibration", type=Path, default=Path("ranging.json"))
    p.add_argument("--modality", choices=MODALITIES, default="oa")
    p.add_argument("--temperature", type=float, default=None,
                   help="use c from this air temperature (degC) instead of the fitted c")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_range)


def cmd_calibrate_range(args: argparse.Namespace) -> int:
    """Run the procedure against the two boards and save the ranging setup."""
    from .cli import CliError
    from .config import load_config, resolve_port
    from .sensor import SensorClient
    from .stage import StageClient

    cfg = load_config(args.config)
    sc = SensorClient(resolve_port("sensor", args.sensor, cfg))
    try:
        with StageClient(resolve_port("stage", args.stage, cfg)) as st:
            setup, report = calibrate_range(
                st, sc, {"X": args.x, "Y": args.y, "Z": args.z}, args.start_distance,
                args.steps, args.step, args.shots, args.average, args.temperature,
                fit_c=not args.fixed_c, lateral=args.lateral)
    except ValueError as e:
        raise CliError(str(e)) from None
    finally:
        sc.close()
    setup.save(args.output)
    if args.json:
        print(json.dumps({"file": str(args.output), **report}))
    else:
        for m, text in report.items():
            print(f"{m.upper()}: {text}")
        print(f"saved {args.output}")
    return 0


def cmd_range(args: argparse.Namespace) -> int:
    """Range every received shot of an HDF5 acquisition."""
    import h5py

    from .cli import CliError

    try:
        setup = RangingSetup.load(args.calibration)
    except ValueError as e:
        raise CliError(f"{e}; run `dmdsm calibrate-range` first") from None
    if args.modality not in setup.cals:
        raise CliError(f"{args.calibration} has no {args.modality.upper()} calibration")
    if args.temperature is not None:
        setup.cals[args.modality].c_mm_s = speed_of_sound_mm_s(args.temperature)
    try:
        with h5py.File(args.file, "r") as f:
            d = f["/entry/data"]
            ok = d["received"][:]
            x = d["waveforms"][:][ok].astype(float) - 32768.0
            tick_hz = float(f["/entry/instrument/sensor"].attrs["tick_hz"])
            phase = d["trigger_phase"][:][ok] / tick_hz
            pre = int(f["/entry/instrument/sensor"].attrs.get("config_pretrigger", 0))
            ids = d["shot_id"][:][ok]
    except (OSError, KeyError) as e:
        raise CliError(f"{args.file}: not a dmdsm acquisition file ({e})") from None
    dist, snr = range_waveforms(x, phase, setup, args.modality, pre)
    if args.json:
        print(json.dumps({"shot_id": ids.tolist(), "distance_mm": [
            None if np.isnan(v) else v for v in dist.tolist()], "snr_db": snr.tolist()}))
    else:
        for i, v, s in zip(ids, dist, snr):
            print(f"{i:6d} {'no echo' if np.isnan(v) else f'{v:10.4f} mm'}  SNR {s:5.1f} dB")
        good = dist[np.isfinite(dist)]
        if good.size:
            print(f"{good.size} of {len(dist)} shots: mean {good.mean():.4f} mm, "
                  f"std {good.std():.4f} mm")
    return 0
