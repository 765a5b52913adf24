"""Ranging calibration: reference pulses learned from data, and t0, c fitted with the stage as
a ruler (pure functions; the procedure that moves the stage lives in range_cmd.py)."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import scipy.fft as sfft

from ..files import one_line
from .matched_filter import MatchedFilter, Template, distance_mm, gaussian_pulse, rms_bandwidth

MODALITIES = ("oa", "us")


@dataclass
class RangeCal:
    """t0 (s) and c (mm/s) of one modality, with their standard errors and the fit residual."""

    modality: str
    t0_s: float
    c_mm_s: float
    t0_std_s: float
    c_std_mm_s: float
    residual_mm: float  # rms distance residual of the fit
    n: int


def fit_range(t_s: np.ndarray, d_mm: np.ndarray, modality: str,
              c_mm_s: float | None = None, offsets_mm: np.ndarray | None = None) -> RangeCal:
    """Least squares of t = t0 + k d / c (k = 1 for OA, 2 for US) over known distances d,
    one independent point per surface spot; with c_mm_s given (from the air temperature)
    only t0 is fitted (c_std reported as 0).

    offsets_mm (n, p): where each point was taken on the target, relative to where d was
    gauged (e.g. lateral and vertical mm); a tilted target adds g . offset to the path, and
    g is fitted as a nuisance, so t0 and c refer to the gauged spot. The standard errors are
    the least-squares ones from the residual scatter (spots far enough apart that their
    surface scatter is independent)."""
    k = 1.0 if modality == "oa" else 2.0
    t, d = np.asarray(t_s, float), np.asarray(d_mm, float)
    off = np.zeros((len(t), 0)) if offsets_mm is None else \
        np.asarray(offsets_mm, float).reshape(len(t), -1)
    good = np.isfinite(t) & np.isfinite(d) & np.isfinite(off).all(axis=1)
    t, d, off = t[good], d[good], off[good]
    off = off[:, np.ptp(off, axis=0) > 0] if len(off) else off  # constant columns: no tilt
    fixed = c_mm_s is not None
    p = 1 + (not fixed) + off.shape[1]
    if len(t) < p + 2 or np.ptp(d) == 0:
        raise ValueError("need at least three arrivals at different known distances "
                         f"(and {p + 2} in all with {off.shape[1]} target offsets)")
    y = t - k * d / c_mm_s if fixed else t
    cols = [np.ones_like(d)] + ([] if fixed else [k * d]) + [k * off[:, i] for i in
                                                             range(off.shape[1])]
    A = np.column_stack(cols)
    coef, *_ = np.linalg.lstsq(A, y, rcond=None)
    resid = y - A @ coef
    s2 = float(resid @ resid) / (len(t) - p)
    cov = s2 * np.linalg.inv(A.T @ A)
    if fixed:
        c, c_std = float(c_mm_s), 0.0
    else:
        c = 1.0 / coef[1]
        c_std = float(np.sqrt(cov[1, 1]) * c * c)
    return RangeCal(modality, float(coef[0]), c, float(np.sqrt(cov[0, 0])), c_std,
                    float(np.sqrt(s2) * c / k), len(t))


def dominant_frequency(x: np.ndarray, fs_hz: float) -> float:
    """Power-weighted mean frequency (Hz) of a batch of waveform segments."""
    p = (np.abs(sfft.rfft(x - x.mean(axis=1, keepdims=True), axis=1)) ** 2).mean(axis=0)
    f = sfft.rfftfreq(x.shape[1], 1 / fs_hz)
    return float((f * p).sum() / p.sum())


def learn_template(x: np.ndarray, fs_hz: float, gate: tuple[int, int],
                   half_width: int = 24, iterations: int = 3) -> Template:
    """A reference pulse averaged from waveforms (n, N) whose echo lies in `gate`.

    Start from a Gaussian pulse at the data's dominant frequency, then repeat: find each
    arrival with the current template, shift every waveform (exactly, in the Fourier domain)
    so its arrival sits at the same place, and average the aligned pulses.
    """
    x = np.asarray(x, dtype=float)
    n = x.shape[1]
    lo, hi = gate
    fc = dominant_frequency(x[:, lo:hi], fs_hz)
    tmpl = gaussian_pulse(fs_hz, fc, 0.6)
    w = 2 * np.pi * sfft.rfftfreq(n)  # rad per sample
    X = sfft.rfft(x, axis=1)
    for _ in range(iterations):
        arr = MatchedFilter(tmpl, n)(x, gate=gate)
        ok = np.isfinite(arr.index)
        if ok.sum() < 2:
            raise ValueError("too few echoes in the gate to learn a reference pulse")
        shift = arr.index[ok] - n / 2  # move each arrival to the middle
        aligned = sfft.irfft(X[ok] * np.exp(1j * np.outer(shift, w)), n=n, axis=1)
        mean = aligned.mean(axis=0)
        seg = mean[n // 2 - half_width:n // 2 + half_width + 1]
        seg = seg / np.sqrt(np.dot(seg, seg))
        tmpl = Template(seg, fs_hz, float(half_width))
    return tmpl


@dataclass
class RangingSetup:
    """What the scanner needs to turn waveforms into distances: per-modality template,
    gate (samples) and calibration."""

    fs_hz: float
    templates: dict[str, Template]
    gates: dict[str, tuple[int, int]]
    cals: dict[str, RangeCal]

    def save(self, path: Path) -> None:
        """JSON with the templates' samples (readable, diffable)."""
        Path(path).write_text(self.to_json())

    def to_json(self) -> str:
        """The setup as JSON text (what save() writes; scan files embed it)."""
        obj = {"format": "dmdsm-ranging", "version": 1, "fs_hz": self.fs_hz,
               "modalities": {m: {"template": self.templates[m].pulse.tolist(),
                                  "center": self.templates[m].center,
                                  "gate": list(self.gates[m]),
                                  "calibration": asdict(self.cals[m])}
                              for m in self.templates}}
        return json.dumps(obj, indent=1)

    @classmethod
    def load(cls, path: Path) -> RangingSetup:
        """Read a file written by save(); raises ValueError with what is wrong."""
        try:
            return cls.from_json(Path(path).read_text())
        except OSError as e:
            raise ValueError(f"{path}: not a readable ranging calibration ({e})") from None
        except ValueError as e:
            raise ValueError(f"{path}: {e}") from None

    def check(self) -> None:
        """Raise ValueError naming the first value no ranging calibration has."""
        if not (np.isfinite(self.fs_hz) and 1e3 < self.fs_hz < 1e10):
            raise ValueError(f"fs_hz {self.fs_hz} is not a sample rate")
        if not self.cals or not set(self.cals) <= set(MODALITIES) or \
                set(self.templates) != set(self.cals) or set(self.gates) != set(self.cals):
            raise ValueError("modalities must be oa and/or us, each with a template, a gate "
                             "and a calibration")
        for m, tmpl in self.templates.items():
            p = tmpl.pulse
            if p.ndim != 1 or not 3 <= p.size <= 4096 or not np.isfinite(p).all() or \
                    not p.any() or not 0 <= tmpl.center < p.size:
                raise ValueError(f"{m} template is not a pulse (1-D, 3..4096 finite samples, "
                                 f"center inside)")
            if len(self.gates[m]) != 2 or not 0 <= self.gates[m][0] < self.gates[m][1]:
                raise ValueError(f"{m} gate {self.gates[m]} is not a sample range")
            c = self.cals[m]
            vals = (c.t0_s, c.c_mm_s, c.t0_std_s, c.c_std_mm_s, c.residual_mm)
            if c.modality != m or not np.isfinite(vals).all() or not c.c_mm_s > 0 or \
                    min(vals[2:]) < 0 or abs(c.t0_s) > 1e-3:
                raise ValueError(f"{m} calibration has values no calibration gives "
                                 f"(t0, c, stds): run `dmdsm calibrate-range` again")

    @classmethod
    def from_json(cls, text: str) -> RangingSetup:
        """Parse to_json() text; raises ValueError with what is wrong."""
        try:
            obj = json.loads(text)
            if obj.get("format") != "dmdsm-ranging":
                raise ValueError("not a dmdsm ranging calibration")
            fs = float(obj["fs_hz"])
            mods = obj["modalities"]
            setup = cls(fs, {m: Template(np.asarray(v["template"], float), fs,
                                         float(v["center"])) for m, v in mods.items()},
                        {m: tuple(int(g) for g in v["gate"]) for m, v in mods.items()},
                        {m: RangeCal(**v["calibration"]) for m, v in mods.items()})
            setup.check()
            return setup
        except (KeyError, TypeError, AttributeError, IndexError, ValueError,
                OverflowError) as e:  # OverflowError: int() of an Infinity in the JSON
            msg = one_line(str(e), 300) if "ranging calibration" in str(e) else \
                f"not a readable ranging calibration ({type(e).__name__}: {one_line(str(e), 120)})"
            raise ValueError(msg) from None


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



_BETAS: dict[int, tuple[Template, float]] = {}  # id -> (template, rms bandwidth rad/sample)


def _beta(tmpl: Template) -> float:
    """rms_bandwidth(tmpl), computed once per template (a live stream asks per waveform)."""
    hit = _BETAS.get(id(tmpl))
    if hit is None or hit[0] is not tmpl:
        if len(_BETAS) > 64:
            _BETAS.clear()
        hit = _BETAS[id(tmpl)] = (tmpl, rms_bandwidth(tmpl))
    return hit[1]


def distance_std_mm(setup: RangingSetup, modality: str, snr_db: np.ndarray | float
                    ) -> np.ndarray:
    """Standard deviation (mm) of a distance read at this SNR: the Cramer-Rao bound of the
    arrival (1 / (SNR beta) samples, which the matched filter reaches above the ambiguity
    SNR) combined with the surface's own scatter, estimated as the ranging calibration's
    residual on its target. The calibration's t0 error is common to every point (not here)."""
    cal, tmpl = setup.cals[modality], setup.templates[modality]
    snr = 10 ** (np.asarray(snr_db, float) / 20)
    t_std = 1.0 / (np.maximum(snr, 1e-30) * _beta(tmpl) * setup.fs_hz)
    return np.hypot(cal.c_mm_s * t_std / K[modality], cal.residual_mm)


def range_waveforms(x: np.ndarray, phase_s: np.ndarray, setup: RangingSetup, modality: str,
                    pretrigger: int = 0, gate: tuple[int, int] | None = None
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Distances (mm, NaN where no echo) and SNR (dB) for baseline-free waveforms."""
    tmpl, cal = setup.templates[modality], setup.cals[modality]
    arr = MatchedFilter(tmpl, x.shape[1])(x, gate=gate or setup.gates[modality])
    t = arr.times_s(setup.fs_hz, phase_s, pretrigger)
    return distance_mm(t, cal.t0_s, cal.c_mm_s, modality), arr.snr_db
