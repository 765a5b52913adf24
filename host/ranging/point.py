"""One waveform's OA and US distances (mm) inside a depth gate: the two-modality ranging policy.

One receiver hears both arrivals, so a lone pulse at time t is either OA from c (t - t0_OA) or
US from c (t - t0_US) / 2; PointRanger decides which (a scan, the emulator's data generators
and `dmdsm classify predict --sensor` range alike). It knows no scan plan: the scan layer
gives it the plan's modality and depth gate (scan.plan.point_ranger).
"""

from __future__ import annotations

import numpy as np

from .calibrate import K, RangingSetup
from .matched_filter import MatchedFilter

CONTINUITY_MM = 3.0  # a lone pulse continues the previous point's surface within this
CONTINUITY_DB = 10.0  # ... and at most this much weaker than it
WINDOW_MARGIN_MM = 1.0  # a lone pulse read by the window: its other reading this far outside


class PointRanger:
    """Both modalities' distances (mm) for one waveform, gated to depth_mm = (lo, hi) mm.

    Each reading is checked for its partner (the other modality from the same surface,
    within `pair_mm`): a confirmed pair fixes both; a lone pulse is read as `modality` when
    that is "oa" or "us", and with "both" as below."""
    # A lone pulse with modality "both" is read as whichever modality puts it within
    # CONTINUITY_MM of the previous point of the same line (surfaces are continuous) at an
    # SNR no more than CONTINUITY_DB below that point's in the same modality (a much
    # weaker pulse is something else: e.g. OA from a grazing side face far behind); with
    # no such neighbour it is ambiguous and both distances are NaN. Before that, where a
    # window is given (where the object can be along the beam), lone_by_window reads the
    # pulses it can tell apart: a neighbour (or the outline's prediction) can mislead, the
    # window cannot (an OA pulse 16 mm away reads as a US echo at ~8 mm, where an auto
    # line expects the surface). Between the two, with lone_is_oa (the scan layer's: a
    # sweep of an object whose declared material answers in both), a lone pulse within the
    # window is OA: a lone US echo would mean a surface met head on whose OA pulse failed.
    # For the same reason, with answers_both (any scan of such an object) no lone pulse is
    # read as US, whatever the window or a neighbour says.

    def __init__(self, setup: RangingSetup, n_samples: int, tick_hz: float,
                 modality: str, depth_mm: tuple[float, float], pair_mm: float = 2.0,
                 answers_both: bool = False, lone_is_oa: bool = False) -> None:
        """setup: templates and t0, c; n_samples per waveform; tick_hz of trigger phases;
        modality "both", "oa" or "us"; depth_mm (lo, hi) where echoes are searched (mm);
        answers_both: the object answers in both (its declared material), so with "both" a
        lone pulse is never read as a US echo; lone_is_oa: and one the window cannot read is
        OA if within the window (see __call__)."""
        self.answers_both = answers_both
        self.lone_is_oa = lone_is_oa
        self.setup = setup
        self.tick_hz = tick_hz
        self.modality = modality
        self.pair_mm = pair_mm
        self.n = n_samples
        self.lo, self.hi = depth_mm
        self.filters = {m: MatchedFilter(setup.templates[m], n_samples) for m in setup.cals}

    def _gate(self, m: str, d_lo: float, d_hi: float, phase_s: float, pre: int
              ) -> tuple[int, int]:
        """Samples where an arrival from d_lo..d_hi mm lands (calibrated t0 and c)."""
        cal = self.setup.cals[m]
        fs = self.setup.fs_hz
        t = [cal.t0_s + K[m] * d / cal.c_mm_s - phase_s for d in (d_lo, d_hi)]
        return (max(int(np.floor(t[0] * fs)) + pre - 1, 0),
                min(int(np.ceil(t[1] * fs)) + pre + 2, self.n))

    def _range(self, m: str, corr: dict, d_lo: float, d_hi: float, phase_s: float,
               pre: int) -> tuple[float, float]:
        """(distance mm or NaN, SNR dB) of modality m's first arrival from d_lo..d_hi mm;
        corr: the waveform's correlation per modality (MatchedFilter.correlate)."""
        cal = self.setup.cals[m]
        mf = self.filters[m]
        lo, hi = self._gate(m, d_lo, d_hi, phase_s, pre)
        hi = min(hi, self.n - len(mf.t.pulse) + int(mf.t.center))  # no circular wrap
        if hi - int(mf.t.center) - 2 * mf.period < max(lo - int(mf.t.center), 0):
            return np.nan, 0.0  # the window is off the end of the waveform
        arr = mf.arrivals(*corr[m], gate=(lo, hi))
        t = arr.times_s(self.setup.fs_hz, phase_s, pre)[0]
        return float(cal.c_mm_s * (t - cal.t0_s) / K[m]), float(arr.snr_db[0])

    def other_reading_mm(self, m: str, d_mm: float) -> float:
        """The distance (mm) the arrival that modality m reads as d_mm gives when read as the
        other modality (same arrival time; calibrated t0, c and one way / round trip)."""
        o = "us" if m == "oa" else "oa"
        cm, co = self.setup.cals[m], self.setup.cals[o]
        t = cm.t0_s + K[m] * d_mm / cm.c_mm_s
        return float(co.c_mm_s * (t - co.t0_s) / K[o])

    def same_arrival(self, oa_mm: float, us_mm: float) -> bool:
        """Whether an OA and a US reading are one pulse read twice: within pair_mm of each
        other's arrival time (in OA mm; a reading at a gate's end can be a pulse's edge).
        Within ~6 mm an OA pulse at d read as a US echo (~d / 2) lies within pair_mm of it:
        a pair of one pulse, its US reading half the distance (a box's sweep passing its
        corners 4 mm away stored 132 US points 2.6 mm off them). A true pair's two arrivals
        are d apart (one way and round trip)."""
        return abs(self.other_reading_mm("us", us_mm) - oa_mm) < self.pair_mm

    def lone_by_window(self, wide: dict[str, tuple[float, float]],
                       window: tuple[float, float]) -> str | None:
        """The modality a lone pulse is read as, or None, from where the surface can be:
        window = (near, far) beam distances (mm) between which the beam crosses the object's
        bounding volume (nothing else is in front of the sensor).

        A reading is plausible within near - m .. far + m (m = WINDOW_MARGIN_MM); it is taken
        only if the same arrival read as the other modality is impossible: read as OA at d,
        its US reading (about d / 2) must be nearer than near - m (no echo from within the
        volume comes back that early); read as US, its OA reading (about 2 d) must be beyond
        far + m (no OA pulse from within the volume arrives that late). So no US echo is ever
        read as OA (a surface twice as far as it is: a keep-out too small) nor an OA pulse as
        US, whatever the material. With both readings taken (two different arrivals), the
        nearer surface wins."""
        near, far = window
        if not (np.isfinite(near) and np.isfinite(far)):
            return None
        lo, hi = near - WINDOW_MARGIN_MM, far + WINDOW_MARGIN_MM
        ok = []
        for m in ("oa", "us"):
            d = wide.get(m, (np.nan, 0.0))[0]
            if m not in self.filters or not (np.isfinite(d) and lo <= d <= hi):
                continue
            other = self.other_reading_mm(m, d)
            if (other < lo) if m == "oa" else (other > hi):
                ok.append((d, m))
        return min(ok)[1] if ok else None

    def __call__(self, waveform: np.ndarray, phase_ticks: int, pretrigger: int = 0,
                 previous: tuple[float, dict[str, float]] | None = None,
                 window: tuple[float, float] | None = None
                 ) -> dict[str, tuple[float, float]]:
        """modality -> (distance mm or NaN, SNR dB); previous: (surface distance mm,
        {modality: SNR dB}) of the previous point on the same scan line, if any; window:
        (near, far) beam distances (mm) where the beam crosses the object's bounding volume,
        if known (a lone pulse is read by lone_by_window first, then as OA within the
        window if lone_is_oa, then by continuity with previous; modality "both" only: "oa"
        and "us" read every lone pulse as theirs, searched for within the window only)."""
        x = waveform.astype(np.float32)[None, :] - 32768.0
        ph = phase_ticks / self.tick_hz
        mods = [m for m in ("oa", "us") if m in self.filters]
        corr = {m: self.filters[m].correlate(x) for m in mods}  # one FFT pair a modality
        gate = {m: (self.lo, self.hi) for m in mods}
        if self.modality in gate and window is not None and np.all(np.isfinite(window)):
            # a one-modality plan reads every lone pulse as its own: only where the window
            # allows it (nothing lies nearer than its near end or beyond its far end), so a
            # steel can's paper label's OA pulse is not read as a US echo at half its distance
            gate[self.modality] = (max(self.lo, window[0] - WINDOW_MARGIN_MM),
                                   min(self.hi, window[1] + WINDOW_MARGIN_MM))
        wide = {m: self._range(m, corr, lo, hi, ph, pretrigger) if lo < hi else
                (np.nan, self._range(m, corr, self.lo, self.hi, ph, pretrigger)[1])
                for m, (lo, hi) in gate.items()}
        out = {m: (np.nan, wide[m][1]) for m in mods}
        if len(mods) < 2:
            m = mods[0]
            if self.modality in ("both", m):
                out[m] = wide[m]
            return out
        w = self.pair_mm
        pairs = []  # (partner SNR, oa reading, us reading)
        d_us, snr_us = wide["us"]
        oa_readings = [wide["oa"]]
        if np.isfinite(d_us):
            oa = self._range("oa", corr, d_us - w, d_us + w, ph, pretrigger)
            if np.isfinite(oa[0]) and not self.same_arrival(oa[0], d_us):
                pairs.append((oa[1], oa, wide["us"]))
            elif np.isfinite(oa[0]):  # the US reading was an OA pulse: read it as one (the
                # wide OA reading can be a US echo over twice as strong, a paper face 4 mm
                # away head on), then look for its echo
                o = self.other_reading_mm("us", d_us)
                oa_readings.append(self._range("oa", corr, o - w, o + w, ph, pretrigger))
        for oa in oa_readings:
            if np.isfinite(oa[0]):
                us = self._range("us", corr, oa[0] - w, oa[0] + w, ph, pretrigger)
                if np.isfinite(us[0]) and not self.same_arrival(oa[0], us[0]):
                    pairs.append((us[1], oa, us))
        if pairs:
            _, oa, us = max(pairs, key=lambda p: p[0])
            return {"oa": oa if self.modality != "us" else (np.nan, oa[1]),
                    "us": us if self.modality != "oa" else (np.nan, us[1])}
        if self.modality != "both":
            lone = self.modality
        else:  # the window first: where it decides, it cannot be wrong; then continuity
            lone = self.lone_by_window(wide, window) if window is not None else None
            if lone is None and self.lone_is_oa and window is not None:
                # an object that answers in both: a US echo comes back only within ~15 deg
                # of head on, where its OA pulse never fails (docs/scanning.md, "What the
                # sensor ranges well"), so a lone pulse is OA (oblique incidence), where
                # the window allows it
                d = wide.get("oa", (np.nan, 0.0))[0]
                if window[0] - WINDOW_MARGIN_MM <= d <= window[1] + WINDOW_MARGIN_MM:
                    lone = "oa"
            if lone is None and previous is not None and np.isfinite(previous[0]):
                near = [m for m in mods if abs(wide[m][0] - previous[0]) < CONTINUITY_MM
                        and wide[m][1] >= previous[1].get(m, np.inf) - CONTINUITY_DB]
                lone = near[0] if len(near) == 1 else None
        if lone == "us" and self.answers_both:
            # a lone echo from an object that answers in both would have had its OA pulse:
            # it is an OA pulse from twice as far (a bowl's auto line, its beam passing
            # under the wall the outline predicted to meet the bottom at grazing incidence:
            # the US reading fell on the prediction, 13 mm off the bowl)
            lone = None
        if lone is not None and np.isfinite(wide[lone][0]):
            out[lone] = wide[lone]
        return out


def surface(r: dict[str, tuple[float, float]]) -> tuple[float, dict[str, float]]:
    """(surface distance mm, {modality: SNR dB} of the modalities that found it) of one
    PointRanger reading: the `previous` of the next point on the same line."""
    found = {m: v for m, v in r.items() if np.isfinite(v[0])}
    d = next(iter(found.values()))[0] if found else np.nan
    return d, {m: v[1] for m, v in found.items()}
