"""Live records: every waveform the board streams, stamped in host time, ranged and classified.

`live(sensor, ranging, model)` arms the board continuously and yields one LiveRecord per
waveform, in order: the host time of its first laser edge through the clock sync (offset and
drift fitted over clock_sync exchanges, re-fitted while the stream runs, with the stamp's
uncertainty), each modality's distance with its sigma and SNR, the material with a model, the
samples, and what the board and the link lost. The per-waveform work (WaveformRanger,
Classifier, ClockFit.stamp) is pure; live() only moves waveforms and exchanges. Close the
generator (contextlib.closing, or leave the loop by an exception) to disarm the board.
"""

from __future__ import annotations

import functools
import math
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.stats import t as student_t

from ..classify.live import RADIUS_MM
from ..links.sensor import CLOCK_SPACING_S, ClockSync, SensorClient, SensorError, fit_line
from ..links.shots import LOSS_COUNTERS
from ..links.transport import LinkError
from ..ranging.calibrate import RangingSetup, distance_std_mm
from ..ranging.point import surface
from ..scan.plan import ScanPlan, point_ranger

MODS = ("oa", "us")
COUNTERS = ("triggers_skipped", "adc_overruns", "integrity_faults")
RESYNC_S = 0.1         # a clock_sync exchange this often while the stream runs (s)
KEEP_EXCHANGES = 400   # the last exchanges kept for the fit (the fly scan keeps as many)
TAKE_WAIT_S = 0.05     # how long one wait for the next waveforms lasts (s)
MIN_FIT_EXCHANGES = 8  # a clock fit uses at least this many exchanges
CLIP_SIGMA = 3.0       # an exchange this many sigmas of the others off the clock line is left out,
OUTLIER_ALPHA = 0.05   # or more where a good one would pass that with this probability
IDLE_RTT_PCT = 25      # the idle round trip: this percentile of those before the arm


@dataclass
class LiveRecord:
    """One streamed waveform as the robot sees it; distances in mm, times in s."""

    seq: int                       # the board's shot id since the arm (0, 1, ...)
    device_ticks: int              # device clock at the first averaged laser edge
    host_s: float                  # that edge on the host's monotonic clock (s)
    host_std_s: float              # 1-sigma of host_s (s): clock offset, drift, split
    unix_s: float                  # the same instant as Unix time (s), for ROS stamps
    received_s: float              # host monotonic (s) when the waveform was taken in
    n_average: int                 # laser shots averaged on board
    trigger_phase: int             # ticks from the edge to the first sample
    samples: np.ndarray            # the waveform (ADC counts)
    distance_mm: dict[str, float | None] = field(default_factory=dict)   # None: no echo
    distance_std_mm: dict[str, float | None] = field(default_factory=dict)
    snr_db: dict[str, float | None] = field(default_factory=dict)
    material: str | None = None    # with a model: the most probable class
    probabilities: dict[str, float] | None = None
    lost_before: int = 0           # shot ids missing just before this one (lost on the link)
    counters: dict[str, int] = field(default_factory=dict)  # device counters since the arm
    clock: dict[str, float] = field(default_factory=dict)   # the fit this stamp came from

    @property
    def device_lost(self) -> int:
        """Bursts the board lost since the arm (ADC overruns, integrity faults)."""
        return sum(self.counters.get(k, 0) for k in LOSS_COUNTERS)


# ---------------------------------------------------------------------------- clock


@dataclass
class ClockFit:
    """A clock sync with the terms of its stamps' uncertainty beside the line's own error:
    the round trip's unknown split and, while the line rests on the exchanges made before
    the arm, the change of regime."""

    sync: ClockSync
    split_s: float                 # half the idle round trip (s): the request's unknown share
    before_arm: bool = False       # the line rests on the idle exchanges made before the arm
    regime_s2: float = 0.0         # then: the variance of the board's change of regime (s^2)

    def stamp(self, ticks: float) -> tuple[float, float]:
        """(host monotonic s, 1-sigma s) of device ticks: the line's prediction error
        (offset, and the drift times the distance from the exchanges' mean host time), the
        unknown split of the idle round trip (uniform over +-RTT/2), and while the line
        rests on the exchanges made before the arm the change of regime (the board reads
        its clock differently on an idle link than on one busy with waveforms): one
        exchange's scatter, or the stream's first exchanges' mean square off the line if
        more."""
        t = float(self.sync.to_host_s(ticks))
        var = self.sync.line_std_s(ticks) ** 2 + split_var_s2(self.split_s) + self.regime_s2
        return t, math.sqrt(var)

    def summary(self, tick_hz: float) -> dict[str, float]:
        """Drift (ppm) and its std, residual (us), round trip (ms), exchanges used."""
        s = self.sync
        return {"drift_ppm": (s.ticks_per_s / tick_hz - 1) * 1e6,
                "drift_std_ppm": s.rate_std / tick_hz * 1e6, "residual_us": s.residual_s * 1e6,
                "rtt_ms": s.rtt_s * 1e3, "exchanges": s.n}


def split_var_s2(half_rtt_s: float) -> float:
    """Variance (s^2) of where in an idle round trip the board read its clock, taken as its
    middle: uniform over +-half_rtt_s."""
    return half_rtt_s ** 2 / 3.0


def _off_line(xr: np.ndarray, yr: np.ndarray, keep: np.ndarray, clip: float
              ) -> tuple[np.ndarray, np.ndarray, float]:
    """The least-squares line of host s on ticks through `keep`: every exchange's host s
    off it, the kept ones' externally studentized residuals (each against the line and the
    scatter of the others: the deleted-residual identities, no refit) and how many of those
    an exchange may lie off it: clip, or the Student t quantile a good one passes with
    probability OUTLIER_ALPHA among them all if larger (Bonferroni)."""
    xk, yk = xr[keep], yr[keep]
    m = len(xk)
    ym = float(yk.mean())
    syy = max(float(np.sum(np.square(yk - ym))), 1e-300)
    beta = float(np.sum((yk - ym) * (xk - xk.mean()))) / syy
    r = xk.mean() + beta * (yr - ym) - xr
    h = 1.0 / m + np.square(yk - ym) / syy  # leverage
    e = r[keep]
    sse = float(np.sum(np.square(e)))
    s2 = np.maximum((sse - e * e / np.maximum(1 - h, 1e-12)) / max(m - 3, 1), 1e-24)
    t = np.zeros(len(xr))
    t[keep] = np.abs(e) / np.sqrt(s2 * np.maximum(1 - h, 1e-12))
    return r, t, max(clip, _t_limit(m))


@functools.lru_cache(maxsize=1024)
def _t_limit(m: int) -> float:
    """The Student t quantile (m - 3 degrees of freedom) a good one of m exchanges passes
    with probability OUTLIER_ALPHA / m on either side."""
    return float(student_t.ppf(1 - OUTLIER_ALPHA / (2 * m), max(m - 3, 1)))


def robust_keep(x: np.ndarray, y: np.ndarray, base: np.ndarray, clip: float = CLIP_SIGMA
                ) -> np.ndarray:
    """Which of the (host s, ticks) exchanges in `base` the line goes through: a host or
    board that stalled between the request's send and its receipt is left out. Rosner's
    generalized ESD on the least-squares line: the exchange standing out most from the line
    and the scatter of the others is taken out, again, up to one in eight (and no more than
    lie `clip` MADs off a median-slope line, plus two: the steps cost), and all up to
    the last one that stood out more than `clip` or the Student t quantile a good one passes
    with probability OUTLIER_ALPHA among them all stay out; then every exchange within that
    of the final line is kept; at least the MIN_FIT_EXCHANGES closest (all of `base` if it
    has fewer). Not a median absolute deviation: a dozen exchanges' MAD can come out at a
    fifth of their scatter and clip good ones."""
    x0, y0 = float(x[base][0]), float(y[base][0])
    xr, yr = x - x0, y - y0  # well conditioned: host seconds and ticks since the first
    xb, yb = xr[base], yr[base]
    half = len(xb) // 2  # slopes between the halves (each exchange in one pair): O(n)
    step = xb[half:2 * half] - xb[:half]
    ok = step != 0
    rate = float(np.median((yb[half:2 * half] - yb[:half])[ok] / step[ok])) if ok.any() \
        else 1.0
    r = (yr - float(np.median(yb - rate * xb))) / rate - xr  # host s off the line
    keep = base.copy()
    removed, out = [], 0
    nb = int(base.sum())
    rb = r[base]  # the candidates: far off the median-slope line by a MAD (which may be
    mad = 1.4826 * float(np.median(np.abs(rb - np.median(rb))))  # small: only a bound)
    cand = int(np.sum(np.abs(rb - np.median(rb)) > clip * mad)) + 2
    for k in range(min(cand, max(nb // 8, 1), nb - MIN_FIT_EXCHANGES)):  # <= 1 in 8 stalled
        _, t, limit = _off_line(xr, yr, keep, clip)  # Rosner's generalized ESD: take out
        worst = int(np.argmax(t))  # the one standing out most, again and again, and keep
        if k == 0 and t[worst] <= limit:  # out all up to the last that stood out beyond
            break                         # the limit (a few stalls mask each other); none
        keep[worst] = False               # at the first: none stalled
        removed.append(worst)
        if t[worst] > limit:
            out = k + 1
    keep = base.copy()
    keep[removed[:out]] = False
    if keep.sum() >= 3:
        r, _, limit = _off_line(xr, yr, keep, clip)
        m = int(keep.sum())
        scale = max(float(np.sqrt(np.sum(np.square(r[keep])) / (m - 2))), 1e-9)
    else:
        scale, limit = max(float(np.std(r[base])), 1e-9), clip
    final = base & (np.abs(r) <= limit * scale)
    if final.sum() < min(MIN_FIT_EXCHANGES, int(base.sum())):  # the closest
        close = np.sort(np.abs(r[base]))[:MIN_FIT_EXCHANGES]
        final = base & (np.abs(r) <= close[-1])
    return final


def clock_fit(before: list[tuple[float, float, float]] | np.ndarray,
              during: list[tuple[float, float, float]] | np.ndarray, idle_rtt_s: float
              ) -> ClockFit:
    """Fit (host mid s, ticks, round trip s) exchanges by the request's send time: the
    board stamps a clock_sync when the request arrives, but its reply waits behind the
    waveform frame on the wire (up to 10.6 ms at the link limit), so the send time plus
    half the idle round trip (`before`: made before the arm) is the arrival whatever the
    reply's wait. `during`: made while the stream runs; once MIN_FIT_EXCHANGES of them are
    there the line goes through those alone (the board's regime), else through all."""
    ex = np.concatenate([np.asarray(before, dtype=float).reshape(-1, 3),
                         np.asarray(during, dtype=float).reshape(-1, 3)])
    mid, ticks, rtt = ex.T
    x = mid - rtt / 2 + idle_rtt_s / 2
    base = np.arange(len(ex)) >= len(before)
    before_arm = int(base.sum()) < MIN_FIT_EXCHANGES
    if before_arm:
        base[:] = True
    keep = robust_keep(x, ticks, base)
    sync = fit_line(x[keep], ticks[keep], float(np.median(rtt[keep])))
    regime = sync.residual_s ** 2
    if before_arm and len(during):  # how far the stream's first exchanges sit off the line
        off = np.asarray(sync.to_host_s(ticks[len(before):])) - x[len(before):]
        regime = max(regime, float(np.mean(off ** 2)))
    return ClockFit(sync, idle_rtt_s / 2, before_arm, regime if before_arm else 0.0)


class ClockTracker:
    """The clock sync of a stream: 16 exchanges before the arm, then while it runs
    MIN_FIT_EXCHANGES at CLOCK_SPACING_S and one every resync_s after them, on a thread (a
    fit over a growing baseline, the last KEEP_EXCHANGES). The thread refits after each
    exchange, so a record only reads the latest fit: refitted on use, the record after
    each exchange waited for the fit (~1 ms idle, 2-3 ms under a live stream's load)."""

    def __init__(self, sensor: SensorClient, resync_s: float = RESYNC_S) -> None:
        self.sensor, self.resync_s = sensor, resync_s
        self.before = sensor.clock_exchanges(16, CLOCK_SPACING_S)
        self.exchanges = np.empty((0, 3))  # (host mid s, ticks, rtt s) while it runs
        # the idle round trip without the host's own scheduling delays (a wake-up after
        # the reply is in, not a leg of the trip): the quicker quartile's bound
        self.idle_rtt_s = float(np.percentile([e[2] for e in self.before], IDLE_RTT_PCT))
        self.fit = clock_fit(self.before, [], self.idle_rtt_s)
        self.missed = 0  # exchanges that got no reply while the link was up
        self.stop_event = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True, name="dmdsm-live-clock")

    def start(self) -> None:
        """Start exchanging while the stream runs."""
        self.thread.start()

    def _run(self) -> None:
        made = 0  # the first MIN_FIT_EXCHANGES quickly: the line leaves the idle ones soon
        while not self.stop_event.wait(CLOCK_SPACING_S if made < MIN_FIT_EXCHANGES
                                       else self.resync_s):
            made += 1
            try:
                ex = self.sensor.clock_exchanges(1)
            except SensorError:
                if getattr(self.sensor, "link_error", None):
                    return  # the link is lost: the stream's reader reports it
                self.missed += 1  # no reply on a live link (a reply lost): next resync
                continue
            except LinkError:
                return
            self.exchanges = np.concatenate([self.exchanges, np.asarray(ex, dtype=float)
                                             .reshape(-1, 3)])[-KEEP_EXCHANGES:]
            self.fit = clock_fit(self.before, self.exchanges, self.idle_rtt_s)  # one store

    def current(self) -> ClockFit:
        """The fit over the exchanges so far."""
        return self.fit

    def stop(self) -> None:
        """Stop exchanging (before the disarm: one thread talks to the board then)."""
        self.stop_event.set()
        if self.thread.is_alive():
            self.thread.join(2.0)


# ---------------------------------------------------------------------------- per waveform


class WaveformRanger:
    """Both modalities' distance (mm), sigma (mm) and SNR (dB) of one waveform at a time,
    gated 5..71 mm as `classify predict --sensor`; a lone pulse continues the last
    waveform's surface (the sensor does not jump between waveforms)."""

    def __init__(self, setup: RangingSetup, n_samples: int, tick_hz: float) -> None:
        self.setup = setup
        self.ranger = point_ranger(ScanPlan("live", radius_mm=RADIUS_MM, modality="both"),
                                   setup, n_samples, tick_hz)
        self.previous: tuple[float, dict[str, float]] | None = None

    def __call__(self, samples: np.ndarray, phase_ticks: int, pretrigger: int = 0
                 ) -> tuple[dict, dict, dict]:
        """({mod: mm or None}, {mod: sigma mm or None}, {mod: SNR dB or None})."""
        r = self.ranger(samples, int(phase_ticks), pretrigger, self.previous)
        self.previous = surface(r)
        d, sd, snr = {}, {}, {}
        for m in MODS:
            dist, s = r.get(m, (np.nan, np.nan))
            ok = bool(np.isfinite(dist))
            d[m] = float(dist) if ok else None
            sd[m] = float(distance_std_mm(self.setup, m, s)) if ok else None
            snr[m] = float(s) if ok and np.isfinite(s) else None
        return d, sd, snr


class Classifier:
    """A material model on one waveform: its windows cut where the ranger found the
    pulses (classify.live.live_windows), the fused probabilities over them."""

    def __init__(self, model: str | Path | tuple, setup: RangingSetup, tick_hz: float) -> None:
        from ..classify.model_file import check_provenance, read_model

        self.model, self.prov = read_model(Path(model)) if isinstance(model, str | Path) \
            else model
        check_provenance(self.prov, Path(str(model)) if not isinstance(model, tuple) else
                         Path("model"), setup.fs_hz, None)
        self.setup, self.tick_hz, self.window = setup, tick_hz, int(self.prov["window"])

    def __call__(self, samples: np.ndarray, phase_ticks: int
                 ) -> tuple[str | None, dict[str, float] | None]:
        """(material, {class: probability}), or (None, None) with no pulse to classify."""
        from ..classify.live import live_windows
        from ..classify.materials import predict_lone

        paired, lone = live_windows(samples[None], np.array([phase_ticks]), self.setup,
                                    self.tick_hz, self.window)
        if len(paired):
            p = self.model.predict_proba(paired)[0]
        elif len(lone):
            p = predict_lone(self.model, lone)[0]
        else:
            return None, None
        classes = [str(c) for c in self.model.classes]
        return classes[int(np.argmax(p))], {c: float(v) for c, v in zip(classes, p)}


# ---------------------------------------------------------------------------- the stream


def monotonic_stamp(host_s: float, std_s: float, ticks: int, last: tuple[int, float] | None,
                    ticks_per_s: float) -> tuple[float, float, tuple[int, float]]:
    """A stamp that never goes back (ROS tools and rosbags expect each topic in time order):
    if a refit puts this edge before the previous record's stamp plus half the device time
    between them, it takes that floor instead and its 1-sigma grows by the shift (s). Half,
    not all: the board's clock drifts (hundreds of ppm), and a floor at the full nominal
    interval would hold every later stamp on it, the error growing with the drift; at half,
    a shifted stamp rejoins the fit at the next record. Returns (host s, std s, (ticks,
    host s) to pass on)."""
    if last is not None and ticks > last[0]:
        floor = last[1] + 0.5 * (ticks - last[0]) / ticks_per_s
        if host_s < floor:
            std_s = math.hypot(std_s, floor - host_s)
            host_s = floor
    return host_s, std_s, (ticks, host_s)


def live(sensor: SensorClient | str, ranging: RangingSetup | str | Path | None = None,
         model: str | Path | tuple | None = None, *, resync_s: float = RESYNC_S
         ) -> Iterator[LiveRecord]:
    """Arm the board continuously and yield a LiveRecord per waveform, in order, until the
    generator is closed (the board is then disarmed; a port name is opened and closed
    here). ranging: a RangingSetup or its file (None: no distances); model: a model file
    or (FusedModel, provenance) (needs ranging)."""
    own = isinstance(sensor, str)
    sc = SensorClient(sensor) if isinstance(sensor, str) else sensor
    try:
        setup = RangingSetup.load(Path(ranging)) if isinstance(ranging, str | Path) else ranging
        if model is not None and setup is None:
            raise ValueError("a material model needs a ranging setup (--ranging)")
        tick_hz = float(sc.identity.tick_hz)
        cfg = dict(sc.request("get_config").fields)
        ranger = WaveformRanger(setup, cfg["n_samples"], tick_hz) if setup else None
        classify = Classifier(model, setup, tick_hz) if model is not None else None
        clock = ClockTracker(sc, resync_s)
        before = sc.status()
        unix_minus_mono = time.time() - time.monotonic()
        sc.stream_start()
        clock.start()
        try:
            expect = 0
            last: tuple[int, float] | None = None
            while True:
                waves = sc.stream_take(TAKE_WAIT_S)
                if not waves:
                    if sc.link_error:
                        raise SensorError(f"lost the sensor board on {sc.port_name} "
                                          f"({sc.link_error}): check its USB cable")
                    continue
                taken = time.monotonic()
                for w in waves:
                    fit = clock.current()
                    host, std = fit.stamp(w.timestamp)
                    host, std, last = monotonic_stamp(host, std, int(w.timestamp), last,
                                                      fit.sync.ticks_per_s)
                    rec = LiveRecord(int(w.shot_id), int(w.timestamp), host, std,
                                     host + unix_minus_mono, taken, int(w.n_average),
                                     int(w.trigger_phase), w.samples,
                                     lost_before=max(int(w.shot_id) - expect, 0),
                                     counters={k: int(getattr(w, k)) - int(before[k])
                                               for k in COUNTERS},
                                     clock=fit.summary(tick_hz))
                    expect = int(w.shot_id) + 1
                    if ranger is not None:
                        rec.distance_mm, rec.distance_std_mm, rec.snr_db = ranger(
                            w.samples, w.trigger_phase, int(w.pretrigger))
                    if classify is not None:
                        rec.material, rec.probabilities = classify(w.samples, w.trigger_phase)
                    yield rec
        finally:
            clock.stop()
            try:
                sc.stream_stop()
            except LinkError:
                pass
    finally:
        if own:
            sc.close()
