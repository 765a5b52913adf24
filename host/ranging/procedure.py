"""Ranging calibration with the rig: the stage as a ruler for t0 and c (drives both boards)."""

from __future__ import annotations

import numpy as np

from ..links.safety import TABLE_I
from .calibrate import MODALITIES, RangingSetup, fit_range, gate_for, learn_template
from .matched_filter import MatchedFilter, speed_of_sound_mm_s


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
