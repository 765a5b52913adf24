"""Ranging calibration with the rig: the stage as a ruler for t0 and c (drives both boards)."""

from __future__ import annotations

import numpy as np

from ..links.interfaces import ShotSensor, StageMotion
from ..links.safety import TABLE_I
from .calibrate import (
    MODALITIES,
    T0_MAX_S,
    K,
    RangeCal,
    RangingSetup,
    fit_range,
    gate_for,
    learn_template,
)
from .matched_filter import MatchedFilter, speed_of_sound_mm_s


def positions(start: dict[str, float], steps: int, step_mm: float, lateral: int = 1,
              lateral_mm: float = 0.5, rise_mm: float = 0.5) -> np.ndarray:
    """(steps * lateral, 3) stage X, Y, Z (mm) the procedure visits, in its order: depth i
    is i * step_mm back in Y, rise_mm-spaced heights in an order unrelated to the depth,
    lateral X positions lateral_mm apart centred on start."""
    heights = np.random.default_rng(0).permutation(steps)  # fixed, unrelated to the depth
    out = []
    for i in range(steps):
        dz = rise_mm * (float(heights[i]) - (steps - 1) / 2)  # centred on the gauged spot
        for j in range(lateral):
            dx = lateral_mm * (j - (lateral - 1) / 2)
            out.append((start["X"] + dx, start["Y"] - i * step_mm, start["Z"] + dz))
    return np.array(out, float).reshape(-1, 3)


def calibrate_range(stage: StageMotion, sensor: ShotSensor, start: dict[str, float],
                    start_distance_mm: float, steps: int = 11, step_mm: float = 0.5,
                    shots: int = 10, average: int = 16, temperature_c: float = 20.0,
                    along_beam: float = 1.0 / TABLE_I["v"][1], fit_c: bool = True,
                    lateral: int = 1, lateral_mm: float = 0.5, rise_mm: float = 0.5
                    ) -> tuple[RangingSetup, dict]:
    """Step the sensor away from a flat target along Y, record, learn pulses, fit t0 and c.

    start_distance_mm is the known beam distance at `start` (a gauge block or feeler);
    each Y step of s mm lengthens the beam path by s * along_beam (1 / v_y for a face
    normal to Y; the paper's v by default). fit_c=False keeps c from the air temperature
    and fits t0 alone: better when the travel is short (c from 20 mm of travel is good to
    ~0.5 %, from a thermometer reading within 1 degC to 0.2 %). lateral > 1 also records
    that many X positions lateral_mm apart at each depth, centred on start (same distance on
    a face normal to Y), and each depth is taken rise_mm higher or lower (in an order
    unrelated to the depth, so a tilt of the target cannot pass for t0 or c): every record
    is on a fresh surface spot, so the surface's scatter is independent between the points
    of the fit and its standard errors hold. The target's tilt over these offsets is fitted
    as a nuisance."""
    c0 = speed_of_sound_mm_s(temperature_c)
    fs = sensor.identity.adc_rate_hz
    n = sensor.configure(n_samples=1024, n_average=average, pretrigger=0,
                         trigger_timeout_ms=2000)["n_samples"]
    waves, phases, dists, spots, offs = [], [], [], [], []
    where = positions(start, steps, step_mm, lateral, lateral_mm, rise_mm)
    for i in range(steps):
        for j in range(lateral):
            x, y, z = where[i * lateral + j]
            dx, dz = x - start["X"], z - start["Z"]
            stage.move(x=x, y=y, z=z)
            stage.wait()
            got = sensor.acquire(shots)
            ok = got.received
            waves.append(got.samples[ok].astype(float) - 32768.0)
            phases.append(got.trigger_phase[ok] / sensor.identity.tick_hz)
            dists.append(np.full(ok.sum(), start_distance_mm + i * step_mm * along_beam))
            spots.append(np.full(ok.sum(), i * lateral + j))
            offs.append(np.tile([dx, dz], (ok.sum(), 1)))
    x, ph, d = np.vstack(waves), np.concatenate(phases), np.concatenate(dists)
    spot, off = np.concatenate(spots), np.vstack(offs)
    templates, gates, cals, report = {}, {}, {}, {}
    for m in MODALITIES:
        g = [gate_for(di, m, fs, c0, n) for di in d]
        lo, hi = min(a for a, _ in g), max(b for _, b in g)
        try:
            tmpl = learn_template(x[spot == 0], fs, g[0])
        except ValueError:
            report[m] = "no echo (this target gives none in this modality)"
            continue
        mf = MatchedFilter(tmpl, n)
        idx = np.full(len(x), np.nan)
        for di in np.unique(d):  # gate each position around where its echo can be
            sel = d == di
            idx[sel] = mf(x[sel], gate=gate_for(di, m, fs, c0, n)).index
        t = idx / fs + ph
        # one point per surface spot: shots at one spot share its surface scatter, so
        # fitting them separately would overstate the precision
        ids = np.unique(spot)
        t_spot = np.array([_spot_time(t[spot == s]) for s in ids])
        first = np.array([np.argmax(spot == s) for s in ids])
        cal = fit_range(t_spot, d[first], m, None if fit_c else c0, off[first])
        check_start_distance(cal, start_distance_mm)
        templates[m], gates[m], cals[m] = tmpl, (lo, hi), cal
        report[m] = (f"t0 {cal.t0_s * 1e6:.4f} +/- {cal.t0_std_s * 1e6:.4f} us, "
                     f"c {cal.c_mm_s / 1e3:.2f} +/- {cal.c_std_mm_s / 1e3:.2f} m/s "
                     f"(air model {c0 / 1e3:.2f}), residual {cal.residual_mm * 1000:.1f} um, "
                     f"{cal.n} positions")
    if not cals:
        raise ValueError("no echoes in either modality: is the target in front of the beam?")
    return RangingSetup(fs, templates, gates, cals), report


def _spot_time(t: np.ndarray) -> float:
    """Arrival time (s) at one surface spot: the median over its shots (NaN if none)."""
    return float(np.nanmedian(t)) if np.isfinite(t).any() else np.nan


def check_start_distance(cal: RangeCal, start_distance_mm: float) -> None:
    """Refuse a fit whose t0 says the given start distance is wrong: an echo cannot arrive
    before the laser fires (t0 >= 0), nor later than any trigger delay (T0_MAX_S). A
    start distance off by D mm moves t0 by -K D / c and leaves c alone, so a wrong gauge
    reading is invisible in the residuals and shows only here."""
    m, sigma = cal.modality.upper(), 4 * cal.t0_std_s
    least_mm = -(cal.t0_s + sigma) * cal.c_mm_s / K[cal.modality]
    if cal.t0_s + sigma < 0:
        raise ValueError(f"--start-distance {start_distance_mm:g} mm is too long by at least "
                         f"{least_mm:.2f} mm: it gives t0 {m} = "
                         f"{cal.t0_s * 1e6:.3f} us, but an echo cannot arrive before the "
                         f"laser fires; measure the distance to the target again")
    if cal.t0_s - sigma > T0_MAX_S:
        raise ValueError(f"--start-distance {start_distance_mm:g} mm is too short: it gives "
                         f"t0 {m} = {cal.t0_s * 1e6:.1f} us, more than any trigger delay "
                         f"({T0_MAX_S * 1e6:g} us); measure the distance to the target again")
