"""The clock line and the stamp's sigma: least squares recovers a line, its prediction error
and the live stream's sigma hold by Monte Carlo, and a stalled exchange is left out."""

import math
import threading
import time

import numpy as np
import pytest
from client_fakes import FakeSensor
from hypothesis import example, given
from hypothesis import strategies as st

from dmdsm.host.links.sensor import SensorError, fit_clock, fit_line
from dmdsm.host.robotics import live as live_mod
from dmdsm.host.robotics.live import clock_fit, monotonic_stamp, robust_keep, split_var_s2

HZ = 240e6


@given(st.floats(-1e12, 1e12), st.floats(1e6, 1e9), st.floats(0.0, 1e6),
       st.integers(3, 60), st.floats(1e-3, 1.0))
def test_fit_line_recovers_an_exact_line(offset, rate, x0, n, spacing):
    x = x0 + np.arange(n) * spacing
    sync = fit_line(x, offset + rate * x, 2e-4)
    tol = 1e-9 * (abs(offset) + rate * (x0 + n * spacing)) / rate + 1e-9
    assert np.allclose(sync.to_host_s(offset + rate * x), x, rtol=0, atol=tol)
    assert sync.ticks_per_s == pytest.approx(rate, rel=1e-6)
    assert sync.n == n and sync.x_mean_s == pytest.approx(float(x.mean()), abs=1e-9 * x0 + 1e-9)
    assert sync.sxx_s2 == pytest.approx(float(np.sum((x - x.mean()) ** 2)), rel=1e-6)
    assert sync.residual_s <= tol and sync.rtt_s == 2e-4


@given(st.integers(5, 400), st.floats(1e-6, 1e-3), st.floats(0.1, 100.0), st.floats(-2, 2))
def test_line_std_s_grows_away_from_the_exchanges_mean(n, noise, span, where):
    rng = np.random.default_rng(n)
    x = 50.0 + np.linspace(0, span, n)
    sync = fit_line(x, 3e6 + HZ * (x + rng.normal(0, noise, n)), 2e-4)
    at_mean = sync.line_std_s(3e6 + HZ * sync.x_mean_s)
    s = sync.residual_s * math.sqrt(n / (n - 4))
    assert at_mean == pytest.approx(s / math.sqrt(n), rel=1e-3)
    dx = where * span
    t = sync.x_mean_s + dx
    ticks = sync.offset_ticks + sync.ticks_per_s * t
    expect = s * math.sqrt(1 / n + dx * dx / sync.sxx_s2)
    assert sync.line_std_s(ticks) == pytest.approx(expect, rel=1e-3, abs=1e-15)
    assert sync.line_std_s(ticks) >= at_mean * (1 - 1e-4)  # round-off of the ticks


def test_four_exchanges_give_no_sigma():
    x = np.arange(4.0)
    assert math.isinf(fit_line(x, HZ * x + np.array([0, 5, -5, 0]), 0.0).line_std_s(HZ))


@pytest.mark.parametrize("n", [8, 30, 400])
@pytest.mark.parametrize("where", [0.0, 0.5, 1.5])
def test_line_std_s_holds_by_monte_carlo(n, where):
    """Gaussian scatter on the host times: the prediction's error over its sigma has an RMS
    of 1 (within 7 %, 3000 fits) at the mean, at the window's end and beyond it."""
    rng = np.random.default_rng(n + int(10 * where))
    x = 100.0 + np.linspace(0, 40.0, n)
    truth_t = 100.0 + 20.0 + where * 40.0
    z = []
    for _ in range(3000):
        sync = fit_line(x, 7e6 + HZ * (x + rng.normal(0, 5e-4, n)), 2e-4)
        ticks = 7e6 + HZ * truth_t
        z.append((float(sync.to_host_s(ticks)) - truth_t) / sync.line_std_s(ticks))
    assert 0.93 < math.sqrt(np.mean(np.square(z))) < 1.07


def test_split_variance_is_uniform_over_the_half_round_trip():
    rng = np.random.default_rng(1)
    h = 1.7e-4
    draws = rng.uniform(-h, h, 200_000)
    assert split_var_s2(h) == pytest.approx(float(np.var(draws)), rel=0.02)


@given(st.integers(10, 200), st.integers(0, 10_000), st.floats(10.0, 100.0), st.booleans())
@example(15, 4230, 10.0, False)  # a MAD of the kept ones shrank each pass: 6 good ones out
@example(13, 517, 10.0, False)  # four steps of the ESD in 13: 3 good ones out with the stall
def test_robust_keep_leaves_out_a_stalled_exchange(n, seed, size, late):
    rng = np.random.default_rng(seed)
    x = 10.0 + np.arange(n) * 0.1 + rng.normal(0, 5e-4, n)
    ticks = HZ * (10.0 + np.arange(n) * 0.1)
    i = int(rng.integers(n))
    x[i] += (1 if late else -1) * size * 5e-4  # stalled size sigmas
    keep = robust_keep(x, ticks, np.ones(n, bool))
    assert not keep[i] and keep.sum() >= max(8, 0.7 * n)  # few good ones left out


@given(st.integers(30, 200), st.integers(0, 10_000))
def test_robust_keep_leaves_out_several_stalls_and_keeps_the_rest(n, seed):
    rng = np.random.default_rng(seed)
    x = 10.0 + np.arange(n) * 0.1 + rng.normal(0, 5e-4, n)
    ticks = HZ * (10.0 + np.arange(n) * 0.1)
    bad = rng.choice(n, n // 10, replace=False)  # one in ten stalled, 20 to 200 sigmas
    x[bad] += rng.choice([-1, 1], len(bad)) * rng.uniform(20, 200, len(bad)) * 5e-4
    keep = robust_keep(x, ticks, np.ones(n, bool))
    good = np.setdiff1d(np.arange(n), bad)
    assert not keep[bad].any() and keep[good].mean() >= 0.9


def busy_stream(rng: np.random.Generator, split: float, n_during: int = 100,
                frame_s: float = 10.4e-3) -> tuple[list, list, float, float]:
    """Exchanges of one stream at the link limit: (before, during, idle rtt, end of window).
    Each leg of an idle round trip jitters; the request's share of it is `split`; while the
    stream runs every reply waits behind a waveform frame (uniform over its wire time)."""
    legs = 3.2e-4

    def ex(t0: np.ndarray, wait: np.ndarray) -> list[tuple[float, float, float]]:
        up = split * legs + rng.normal(0, 5e-4, t0.size)  # the board's reading jitters
        rtt = legs + wait + rng.uniform(-2e-5, 2e-5, t0.size)
        return list(zip(t0 + rtt / 2, 4e6 + HZ * (t0 + up), rtt))

    before = ex(50.0 + np.arange(16) * 0.025, np.zeros(16))
    during = ex(51.0 + np.arange(n_during) * 0.1, rng.uniform(0, frame_s, n_during))
    return before, during, legs, 51.0 + n_during * 0.1


def test_clock_fit_sigma_holds_by_monte_carlo_over_a_busy_link():
    """The live stream's stamp sigma (line, and the idle round trip's split, uniform)
    against streams whose request's share of the idle round trip is drawn uniformly and
    whose every reply waited behind a frame: RMS z 1 within 10 % over 400 streams; the
    stamps within a few tenths of a millisecond."""
    rng = np.random.default_rng(11)
    z, err = [], []
    for _ in range(400):
        split = float(rng.uniform(0.0, 1.0))
        before, during, idle, end = busy_stream(rng, split)
        fit = clock_fit(before, during, idle)
        t, sd = fit.stamp(4e6 + HZ * end)
        err.append(t - end)
        z.append((t - end) / sd)
    assert 0.9 < math.sqrt(np.mean(np.square(z))) < 1.1
    assert math.sqrt(np.mean(np.square(err))) < 3e-4


def test_fit_clock_keeps_the_exchanges_that_did_not_wait():
    """The fly scan's fit: only exchanges within 1.5x the median round trip, by midpoint."""
    rng = np.random.default_rng(2)
    host = 10.0 + np.arange(40) * 0.025
    rtt = np.where(np.arange(40) % 4 == 0, 8e-3, 3e-4 + rng.uniform(0, 5e-5, 40))
    ticks = HZ * (host + np.where(rtt > 1e-3, 3e-3, 0.0))  # the waited ones are off
    sync = fit_clock(list(zip(host, ticks, rtt)))
    assert sync.n == 30 and sync.rtt_s == pytest.approx(float(np.median(rtt)))
    assert np.allclose(sync.to_host_s(ticks[rtt < 1e-3]), host[rtt < 1e-3], atol=1e-9)


@given(st.lists(st.tuples(st.integers(1, 10**7), st.floats(-0.05, 0.05),
                          st.floats(1e-6, 1e-3)), min_size=1, max_size=60))
def test_stamps_never_go_back_and_a_shifted_one_owns_its_shift(steps):
    """Fits that jump about (+-50 ms) still give increasing stamps; an untouched stamp keeps
    its sigma, a moved one's sigma covers the move."""
    last, ticks, prev = None, 0, -math.inf
    for dticks, jump_s, std_s in steps:
        ticks += dticks
        fit_s = ticks / HZ + jump_s
        host, std, last = monotonic_stamp(fit_s, std_s, ticks, last, HZ)
        assert host > prev and last == (ticks, host)
        assert std == pytest.approx(math.hypot(std_s, host - fit_s), rel=1e-9)
        assert host == fit_s or host > fit_s
        prev = host


def test_a_drifting_clock_does_not_hold_the_stamps_on_the_floor():
    """A board clock 300 ppm slow against the nominal rate, one refit 0.3 ms back: the next
    stamp is shifted, the one after is the fit's own again (no error growing with drift)."""
    period_ticks = HZ // 100
    last, shifted = None, []
    for k in range(200):
        ticks = k * period_ticks
        fit_s = ticks / HZ * (1 - 300e-6) - (0.3e-3 if k >= 100 else 0.0)
        host, std, last = monotonic_stamp(fit_s, 1e-5, ticks, last, HZ)
        if host != fit_s:
            shifted.append(k)
    assert shifted == []  # 0.3 ms back is within half a 10 ms period: no shift needed
    # a stamp left 8 ms ahead of the fit (fit: 1.000 s at record 100, 10 ms a record)
    last = (100 * period_ticks, 1.008)
    host, std, last = monotonic_stamp(1.010, 1e-5, 101 * period_ticks, last, HZ)
    assert host == pytest.approx(1.013) and std == pytest.approx(math.hypot(1e-5, 3e-3))
    host, std, last = monotonic_stamp(1.020, 1e-5, 102 * period_ticks, last, HZ)
    assert (host, std) == (1.020, 1e-5)  # back on the fit, with its own sigma


def test_the_clock_tracker_refits_on_its_thread_not_on_the_records_path(monkeypatch):
    """A record reads the tracker's latest fit without fitting (a fit takes ~1 ms idle and
    2-3 ms under a live stream: on the record's path it delayed one record in ten), and that
    fit includes the exchanges made while the stream runs."""
    sensor = FakeSensor(motion=None)  # exchanges on its known clock, answered at once
    tracker = live_mod.ClockTracker(sensor, resync_s=0.01)
    fits_here = []
    real = live_mod.clock_fit

    def counted(*a, **k):
        if threading.current_thread() is threading.main_thread():
            fits_here.append(1)
        return real(*a, **k)

    monkeypatch.setattr(live_mod, "clock_fit", counted)
    tracker.start()
    try:
        deadline = time.monotonic() + 30
        while len(tracker.exchanges) < live_mod.MIN_FIT_EXCHANGES + 2:
            assert time.monotonic() < deadline, "the tracker made no exchanges"
            time.sleep(0.005)
        fit = tracker.current()
    finally:
        tracker.stop()
    assert not fits_here
    assert not fit.before_arm and fit.sync.n >= live_mod.MIN_FIT_EXCHANGES
    t = time.monotonic() + 1.0
    host, _ = fit.stamp(sensor.ticks(t))
    assert abs(host - t) < 1e-6


def test_the_clock_tracker_goes_on_after_an_exchange_without_reply_and_stops_on_a_lost_link():
    """A clock_sync whose reply was lost on a link still streaming is made again at the next
    resync (the thread ended there, and the stamps drifted on the last fit for the rest of
    the stream); a lost link ends the thread, for the stream's reader to report."""

    class Flaky(FakeSensor):
        calls, link_error = 0, None

        def clock_exchanges(self, n=16, spacing_s=0.0):
            self.calls += 1
            if self.calls in (2, 3):  # the thread's first two: no reply
                raise SensorError("no reply to clock_sync from /dev/fake after 3 tries")
            if self.calls == 10:  # the link goes
                self.link_error = "read failed"
                raise SensorError("lost the sensor board on /dev/fake (read failed)")
            return super().clock_exchanges(n, spacing_s)

    sensor = Flaky(motion=None)
    tracker = live_mod.ClockTracker(sensor, resync_s=0.01)
    tracker.start()
    try:
        tracker.thread.join(30)
        assert not tracker.thread.is_alive(), "the tracker went on over a lost link"
    finally:
        tracker.stop()
    assert tracker.missed == 2 and len(tracker.exchanges) == 6  # calls 4..9
