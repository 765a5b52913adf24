"""Ranging benchmark: RMSE / Cramer-Rao bound and bias vs SNR for US- and OA-like pulses at
3.333 MS/s (the NUCLEO's paced ADC), throughput on one core, and two naive baselines side by
side (threshold crossing and envelope peak). Targets (DESIGN.md §8): RMSE <= 1.2 CRB at >= 20
dB, |bias| < 1 um, >= 50 000 waveforms/s of 1024 samples; and no wrong distance reported as
good (issue 18): from 5 to 40 dB, fewer than 0.1 % of the reported arrivals more than 5 of
their own std from the truth, the readings below the ambiguity SNR (cycle slips) flagged
instead, their rate printed.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # "one core": no BLAS threads
import sys
import time

import numpy as np
import scipy.fft as sfft
from scipy.signal import hilbert

from dmdsm.host.ranging.matched_filter import (
    MatchedFilter,
    crlb_samples,
    gaussian_pulse,
    speed_of_sound_mm_s,
)

FS = 240e6 / 72
N = 1024
PULSES = {"US": (1.0e6, 0.6), "OA": (0.8e6, 0.9)}
MM_PER_SAMPLE = {"US": speed_of_sound_mm_s(20) / FS / 2, "OA": speed_of_sound_mm_s(20) / FS}


def make(fc: float, bw: float, delays: np.ndarray, sigma: float, rng: np.random.Generator
         ) -> np.ndarray:
    """Waveforms with the continuous pulse at fractional delays plus white noise."""
    sg = np.sqrt(2 * np.log(2)) / (np.pi * bw * fc)
    t = (np.arange(N)[None, :] - delays[:, None]) / FS
    x = np.exp(-0.5 * (t / sg) ** 2) * np.cos(2 * np.pi * fc * t)
    return (x + rng.normal(0, sigma, x.shape)).astype(np.float32)


def threshold_crossing(x: np.ndarray, sigma: float) -> np.ndarray:
    """Baseline 1: first sample whose |x| exceeds 5 sigma, linearly interpolated."""
    above = np.abs(x) > 5 * sigma
    i = above.argmax(axis=1).astype(float)
    return np.where(above.any(axis=1), i, np.nan)


def envelope_peak(x: np.ndarray) -> np.ndarray:
    """Baseline 2: peak of the Hilbert envelope with parabolic interpolation."""
    env = np.abs(hilbert(x, axis=1))
    i = env.argmax(axis=1)
    rows = np.arange(len(x))
    i = np.clip(i, 1, x.shape[1] - 2)
    ym, y0, yp = env[rows, i - 1], env[rows, i], env[rows, i + 1]
    return i + 0.5 * (ym - yp) / (ym - 2 * y0 + yp)


def main() -> int:
    """Print the figures; exit 1 if a target is missed."""
    rng = np.random.default_rng(0)
    ok = True
    for name, (fc, bw) in PULSES.items():
        tmpl = gaussian_pulse(FS, fc, bw)
        mf = MatchedFilter(tmpl, N)
        mm = MM_PER_SAMPLE[name]
        print(f"{name}-like pulse: {fc / 1e6:.1f} MHz, {bw:.0%} bandwidth, "
              f"1 sample = {mm * 1000:.1f} um")
        print(f"  ambiguity floor {mf.ambiguity_snr_db:.1f} dB (next cycle at rho1 "
              f"{mf.rho1:.2f})")
        print(f"  {'SNR':>5} {'CRB um':>8} | {'matched: RMSE/CRB':>17} {'bias um':>8} "
              f"{'miss':>6} {'>5 own std':>10} | {'threshold RMSE/CRB':>18} | "
              f"{'envelope RMSE/CRB':>17}")
        for snr_db in (5, 10, 15, 17, 18, 19, 20, 25, 30, 40):
            n = 4000
            delays = rng.uniform(150, 850, n)
            sigma = np.sqrt(tmpl.energy) / 10 ** (snr_db / 20)
            x = make(fc, bw, delays, sigma, rng)
            crb = crlb_samples(tmpl, sigma)
            r = mf(x, min_snr_db=0.0)  # every reading the ambiguity floor lets through
            err = r.index - delays
            good = np.isfinite(err)
            far = np.abs(err[good]) > 5 * r.index_std[good]
            ok &= far.sum() <= 0.001 * max(good.sum(), 1)
            rmse = np.sqrt(np.mean(err[good] ** 2)) / crb if good.any() else np.nan
            bias_um = np.mean(err[good]) * mm * 1000 if good.any() else np.nan
            # baselines measured against the same truth; their offsets are removed (best case)
            thr = threshold_crossing(x, sigma) - delays
            env = envelope_peak(x) - delays - tmpl.center + tmpl.center
            thr_rmse = np.nanstd(thr) / crb
            env_rmse = np.nanstd(env) / crb
            print(f"  {snr_db:>3}dB {crb * mm * 1000:>8.3f} | {rmse:>17.3f} {bias_um:>8.3f} "
                  f"{np.mean(~good):>6.1%} {np.mean(far) if good.any() else 0:>10.3%} | "
                  f"{thr_rmse:>18.1f} | {env_rmse:>17.1f}")
            if snr_db >= 20:
                ok &= rmse <= 1.2 and abs(bias_um) < 1.0
    tmpl = gaussian_pulse(FS, 1.0e6, 0.6)
    mf = MatchedFilter(tmpl, N)
    x = make(1.0e6, 0.6, rng.uniform(150, 850, 20000), 0.05, rng)
    mf(x[:512])
    best = np.inf
    with sfft.set_workers(1):  # one FFT thread (the default, made explicit)
        for _ in range(3):
            t0 = time.perf_counter()
            mf(x)
            best = min(best, time.perf_counter() - t0)
    rate = len(x) / best
    t0 = time.perf_counter()
    envelope_peak(x)
    env_rate = len(x) / (time.perf_counter() - t0)
    print(f"throughput, 1024 samples, one core: matched filter {rate:,.0f} waveforms/s "
          f"(target 50,000); envelope-peak baseline {env_rate:,.0f}/s")
    ok &= rate >= 50_000
    print("PASS" if ok else "FAIL: a target was missed")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
