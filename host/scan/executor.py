"""Step-and-shoot scanning: move, settle, acquire, range and store each planned point, resumable.

The executor knows the two clients, the plan, the calibration and the ranging setup; it writes
through `scanfile.ScanWriter`, so every finished point is on disk before the next move. An
interruption (Ctrl-C, a lost board) closes the file as `interrupted` and quick-stops the stage
(the StageClient context manager); running the same plan again continues after the last
finished point.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from ..ranging.calibrate import K, RangingSetup
from ..ranging.matched_filter import MatchedFilter
from .plan import Point, ScanPlan
from .scanfile import PHASES, ScanWriter

RETRIES = 3  # arms per point before a waveform is recorded as lost
CONTINUITY_MM = 3.0  # a lone pulse continues the previous point's surface within this
CONTINUITY_DB = 10.0  # ... and at most this much weaker than it


@dataclass
class ScanStats:
    """What a run did: points stored, waveforms lost, wall time per phase (s)."""

    stored: int = 0
    lost: int = 0
    phase_s: dict[str, float] = field(default_factory=lambda: dict.fromkeys(PHASES, 0.0))
    store_s: float = 0.0
    wall_s: float = 0.0
    clock: dict = field(default_factory=dict)  # fly: the clock sync (drift, residual, RTT)

    def per_point_ms(self) -> dict[str, float]:
        """Mean wall time per stored point and phase (ms)."""
        n = max(self.stored, 1)
        out = {k: 1e3 * v / n for k, v in self.phase_s.items()}
        out["store"] = 1e3 * self.store_s / n
        return out


class PointRanger:
    """Both modalities' distances (mm) for one waveform, gated to the plan's depth range.

    One receiver hears both arrivals, so a lone pulse at time t is either OA from
    c (t - t0_OA) or US from c (t - t0_US) / 2. Each reading is checked for its partner (the
    other modality from the same surface, within `pair_mm`): a confirmed pair fixes both; a
    lone pulse is read as the plan's modality ("both": OA, which survives oblique incidence
    where the specular US echo does not)."""
    # A lone pulse in a "both" plan is read as whichever modality puts it within
    # CONTINUITY_MM of the previous point of the same line (surfaces are continuous) at an
    # SNR no more than CONTINUITY_DB below that point's in the same modality (a much
    # weaker pulse is something else: e.g. OA from a grazing side face far behind); with
    # no such neighbour it is ambiguous and both distances are NaN.

    def __init__(self, setup: RangingSetup, plan: ScanPlan, n_samples: int,
                 tick_hz: float, pair_mm: float = 2.0) -> None:
        self.setup = setup
        self.tick_hz = tick_hz
        self.plan_modality = plan.modality
        self.pair_mm = pair_mm
        self.n = n_samples
        self.lo = max(plan.standoff_mm - plan.depth_margin_mm, 0.5)
        self.hi = plan.standoff_mm + 2 * plan.radius_mm + plan.depth_margin_mm
        self.filters = {m: MatchedFilter(setup.templates[m], n_samples) for m in setup.cals}

    def _gate(self, m: str, d_lo: float, d_hi: float, phase_s: float, pre: int
              ) -> tuple[int, int]:
        """Samples where an arrival from d_lo..d_hi mm lands (calibrated t0 and c)."""
        cal = self.setup.cals[m]
        fs = self.setup.fs_hz
        t = [cal.t0_s + K[m] * d / cal.c_mm_s - phase_s for d in (d_lo, d_hi)]
        return (max(int(np.floor(t[0] * fs)) + pre - 1, 0),
                min(int(np.ceil(t[1] * fs)) + pre + 2, self.n))

    def _range(self, m: str, x: np.ndarray, d_lo: float, d_hi: float, phase_s: float,
               pre: int) -> tuple[float, float]:
        cal = self.setup.cals[m]
        mf = self.filters[m]
        lo, hi = self._gate(m, d_lo, d_hi, phase_s, pre)
        hi = min(hi, self.n - len(mf.t.pulse) + int(mf.t.center))  # no circular wrap
        if hi - int(mf.t.center) - 2 * mf.period < max(lo - int(mf.t.center), 0):
            return np.nan, 0.0  # the window is off the end of the waveform
        arr = mf(x, gate=(lo, hi))
        t = arr.times_s(self.setup.fs_hz, phase_s, pre)[0]
        return float(cal.c_mm_s * (t - cal.t0_s) / K[m]), float(arr.snr_db[0])

    def __call__(self, waveform: np.ndarray, phase_ticks: int, pretrigger: int = 0,
                 previous: tuple[float, dict[str, float]] | None = None
                 ) -> dict[str, tuple[float, float]]:
        """modality -> (distance mm or NaN, SNR dB); previous: (surface distance mm,
        {modality: SNR dB}) of the previous point on the same scan line, if any."""
        x = waveform.astype(np.float32)[None, :] - 32768.0
        ph = phase_ticks / self.tick_hz
        mods = [m for m in ("oa", "us") if m in self.filters]
        wide = {m: self._range(m, x, self.lo, self.hi, ph, pretrigger) for m in mods}
        out = {m: (np.nan, wide[m][1]) for m in mods}
        if len(mods) < 2:
            m = mods[0]
            if self.plan_modality in ("both", m):
                out[m] = wide[m]
            return out
        w = self.pair_mm
        pairs = []  # (partner SNR, oa reading, us reading)
        d_us, snr_us = wide["us"]
        if np.isfinite(d_us):
            oa = self._range("oa", x, d_us - w, d_us + w, ph, pretrigger)
            if np.isfinite(oa[0]):
                pairs.append((oa[1], oa, wide["us"]))
        d_oa, snr_oa = wide["oa"]
        if np.isfinite(d_oa):
            us = self._range("us", x, d_oa - w, d_oa + w, ph, pretrigger)
            if np.isfinite(us[0]):
                pairs.append((us[1], wide["oa"], us))
        if pairs:
            _, oa, us = max(pairs, key=lambda p: p[0])
            return {"oa": oa if self.plan_modality != "us" else (np.nan, oa[1]),
                    "us": us if self.plan_modality != "oa" else (np.nan, us[1])}
        if self.plan_modality != "both":
            lone = self.plan_modality
        elif previous is not None and np.isfinite(previous[0]):
            near = [m for m in mods if abs(wide[m][0] - previous[0]) < CONTINUITY_MM
                    and wide[m][1] >= previous[1].get(m, np.inf) - CONTINUITY_DB]
            lone = near[0] if len(near) == 1 else None
        else:
            lone = None
        if lone is not None and np.isfinite(wide[lone][0]):
            out[lone] = wide[lone]
        return out


def run_scan(stage: object, sensor: object, plan: ScanPlan, points: list[Point],
             writer: ScanWriter, ranger: PointRanger,
             progress: Callable[[int, int, dict], None] | None = None) -> ScanStats:
    """Measure points[writer.n_done:] in order, appending each to the file as it finishes.

    The caller has checked every move (plan.check_plan) and configured the sensor.
    """
    stats = ScanStats()
    t_start = time.monotonic()
    todo = points[writer.n_done:]
    previous = _last_distance(writer, points)
    if todo:  # approach: into the front plane along Y, then to the first point
        here = stage.where()
        stage.move(x=here["X"], y=todo[0].y, z=here["Z"], feed_mm_min=plan.feed_mm_min)
    for p in todo:
        timing = dict.fromkeys(PHASES, 0.0)
        t0 = time.monotonic()
        stage.move(x=p.x, y=p.y, z=p.z, a=p.theta_deg, feed_mm_min=plan.feed_mm_min)
        stage.wait()
        t1 = time.monotonic()
        timing["move"] = t1 - t0
        if plan.settle_s > 0:
            stage.send(f"G4 P{plan.settle_s * 1000:.0f}")
            stage.wait()
        timing["settle"] = time.monotonic() - t1
        got = None
        attempts = 0
        while got is None and attempts < RETRIES:
            attempts += 1
            shots = sensor.acquire(1)
            if shots.received[0]:
                got = shots
            else:
                stats.lost += 1
        t2 = time.monotonic()
        if got is not None and got.first_byte_s and got.done_s:  # bytes on the wire
            timing["transfer"] = got.done_s - got.first_byte_s
        timing["acquire"] = t2 - t1 - timing["settle"] - timing["transfer"]
        if got is not None:
            wave = got.samples[0].astype(np.uint16)
            prev = previous if previous is not None and previous[0] == (p.angle_index,
                                                                         p.level) else None
            r = ranger(wave, int(got.trigger_phase[0]), int(got.config.get("pretrigger", 0)),
                       prev[1] if prev else None)
            previous = ((p.angle_index, p.level), _surface(r))
            ids = dict(n_average=int(got.n_average[0]), timestamp=int(got.timestamp[0]),
                       trigger_phase=int(got.trigger_phase[0]), received=True)
        else:
            wave = np.zeros(writer.data["waveforms"].shape[1], np.uint16)
            r = {}
            ids = dict(n_average=0, timestamp=0, trigger_phase=0, received=False)
        timing["ranging"] = time.monotonic() - t2
        nan = (np.nan, 0.0)
        t3 = time.monotonic()
        writer.append(wave, stage_position_mm=[p.x, p.y, p.z], theta_deg=p.theta_deg,
                      level=p.level, column=p.column, angle_index=p.angle_index,
                      distance_oa_mm=r.get("oa", nan)[0], distance_us_mm=r.get("us", nan)[0],
                      snr_oa_db=r.get("oa", nan)[1], snr_us_db=r.get("us", nan)[1],
                      phase_time_s=[timing[k] for k in PHASES], host_time=time.time(),
                      attempts=attempts, point_index=p.index, **ids)
        stats.store_s += time.monotonic() - t3
        stats.stored += 1
        for k in PHASES:
            stats.phase_s[k] += timing[k]
        if progress is not None:
            progress(writer.n_done, len(points), timing)
    stats.wall_s = time.monotonic() - t_start
    return stats


def _last_distance(writer: ScanWriter, points: list[Point]) -> tuple | None:
    """((angle index, level), surface distance mm) of the last stored point, so a resumed
    scan ranges its next point exactly as an uninterrupted one would."""
    i = writer.n_done - 1
    if i < 0:
        return None
    d = writer.data
    r = {m: (float(d[f"distance_{m}_mm"][i]), float(d[f"snr_{m}_db"][i]))
         for m in ("oa", "us")}
    return ((points[i].angle_index, points[i].level), _surface(r))


def _surface(r: dict[str, tuple[float, float]]) -> tuple[float, dict[str, float]]:
    """(surface distance mm, {modality: SNR dB} of the modalities that found it)."""
    found = {m: v for m, v in r.items() if np.isfinite(v[0])}
    d = next(iter(found.values()))[0] if found else np.nan
    return d, {m: v[1] for m, v in found.items()}
