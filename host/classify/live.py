"""Windows for `dmdsm classify predict --sensor`: a few shots where the sensor is, ranged like
a scan, cut like the database; lone pulses (glass and steel give no OA, foam no US) are
returned apart because nothing in one waveform says which modality they are."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..ranging.calibrate import RangingSetup
from ..scan.plan import ScanPlan, point_ranger
from .materials import MODS, ClassifyError, Dataset, arrival_sample, windows

RADIUS_MM = 30.0     # echoes are searched 5..71 mm from the sensor (plan standoff 8 mm)
N_SAMPLES = 1024     # samples per live waveform (as `dmdsm scan` takes them)


def live_windows(samples: np.ndarray, phase_ticks: np.ndarray, setup: RangingSetup,
                 tick_hz: float, window: int) -> tuple[Dataset, np.ndarray]:
    """Range each waveform (n, n_samples) u16 and cut windows: a Dataset of the waveforms
    with an OA+US pair, and the (k, window) windows of lone pulses of unknown modality."""
    n_samples = samples.shape[1]
    ranger = {m: point_ranger(ScanPlan("live", radius_mm=RADIUS_MM, modality=m), setup,
                              n_samples, tick_hz) for m in ("both", *setup.cals)}
    X: dict[str, list] = {m: [] for m in MODS}
    lone: list[np.ndarray] = []
    for wave, ph in zip(samples.astype(np.uint16), phase_ticks):
        phase_s = float(ph) / tick_hz
        r = ranger["both"](wave, int(ph))
        if all(np.isfinite(r.get(m, (np.nan,))[0]) for m in MODS):
            cut = {m: windows(wave[None], arrival_sample(setup.cals[m], m, [r[m][0]], phase_s,
                                                         setup.fs_hz), window) for m in MODS}
            if all(ok[0] for _, ok in cut.values()):
                for m in MODS:
                    X[m].append(cut[m][0][0])
                continue
        for m in setup.cals:  # one pulse: read it as this modality, cut where it is
            d = ranger[m](wave, int(ph))[m][0]
            if np.isfinite(d):
                w, ok = windows(wave[None], arrival_sample(setup.cals[m], m, [d], phase_s,
                                                           setup.fs_hz), window)
                if ok[0]:
                    lone.append(w[0])
                    break
    n = len(X["oa"])
    paired = Dataset({m: np.array(X[m], np.float32).reshape(n, window) for m in MODS},
                     {m: np.ones(n, bool) for m in MODS}, np.full(n, "?"), np.full(n, "live"),
                     setup.fs_hz, window)
    return paired, np.array(lone, np.float32).reshape(len(lone), window)


def acquire_windows(args: argparse.Namespace, prov: dict,
                    check: Callable[[dict, Path, float, int], None]
                    ) -> tuple[Dataset, np.ndarray]:
    """Configure the sensor like the model's training data (sample rate, averaging),
    acquire args.shots waveforms and cut them (see live_windows)."""
    from ..links.sensor import SPEC, SensorClient

    try:
        setup = RangingSetup.load(args.ranging)
    except ValueError as e:
        raise ClassifyError(f"{e}; run `dmdsm calibrate-range` first") from None
    check(prov, args.model, setup.fs_hz, args.window)
    if args.shots < 1:
        raise ClassifyError(f"--shots must be at least 1 (got {args.shots})")
    sc = SensorClient(args.sensor)
    try:
        adc, tick = float(sc.identity.adc_rate_hz), float(sc.identity.tick_hz)
        div = max(int(round(adc / prov["fs_hz"])), 1)
        check(prov, args.model, adc / div, args.window)
        sc.configure(n_samples=N_SAMPLES, sample_rate_div=div, pretrigger=0,
                     sample_format=SPEC.enums["sample_format"]["u16_mean"],
                     n_average=int(prov.get("n_average") or 16), trigger_timeout_ms=2000)
        shots = sc.acquire(args.shots)
    finally:
        sc.close()
    got = np.nonzero(shots.received)[0]
    if not len(got):
        raise ClassifyError(f"none of the {args.shots} shots arrived: is the laser firing?")
    paired, lone = live_windows(shots.samples[got], shots.trigger_phase[got], setup, tick,
                                args.window)
    if not len(paired) and not len(lone):
        raise ClassifyError(f"no echo 5..{8 + 2 * RADIUS_MM + 3:.0f} mm in front of the "
                            f"sensor in {len(got)} waveforms: is an object there?")
    return paired, lone
