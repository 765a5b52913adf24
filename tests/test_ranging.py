"""Ranging: arrivals at the Cramer-Rao bound, no bogus distances, first echo, phase removal."""

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from dmdsm.host.ranging.matched_filter import (
    MatchedFilter,
    crlb_samples,
    distance_mm,
    gaussian_pulse,
    interpolation_weights,
    speed_of_sound_mm_s,
)

FS = 240e6 / 72
N = 1024
US = gaussian_pulse(FS, 1.0e6, 0.6)
OA = gaussian_pulse(FS, 0.8e6, 0.9)
FILTERS = {"us": MatchedFilter(US, N), "oa": MatchedFilter(OA, N)}


def pulse_at(template, delay, amp=1.0):
    """The template's continuous pulse placed with its reference at `delay` samples."""
    fc = {id(US): (1.0e6, 0.6), id(OA): (0.8e6, 0.9)}[id(template)]
    sg = np.sqrt(2 * np.log(2)) / (np.pi * fc[1] * fc[0])
    t = (np.arange(N) - delay) / FS
    return amp * np.exp(-0.5 * (t / sg) ** 2) * np.cos(2 * np.pi * fc[0] * t)


@settings(max_examples=60)
@given(kind=st.sampled_from(["us", "oa"]), delay=st.floats(60, 850),
       amp=st.floats(50, 5000), snr_db=st.floats(22, 45), seed=st.integers(0, 2**31))
def test_arrival_is_within_a_few_crlb(kind, delay, amp, snr_db, seed):
    tmpl = US if kind == "us" else OA
    sigma = amp * np.sqrt(tmpl.energy) / 10 ** (snr_db / 20)
    rng = np.random.default_rng(seed)
    x = pulse_at(tmpl, delay, amp) + rng.normal(0, sigma, N)
    r = FILTERS[kind](x[None, :])
    bound = crlb_samples(tmpl, sigma, amp)
    assert abs(r.index[0] - delay) < 6 * bound
    assert abs(r.snr_db[0] - snr_db) < 6 * snr_std_db(snr_db)


def snr_std_db(snr_db):
    """The SNR estimate's scatter (dB): the peak's amplitude noise (8.686 / linear SNR) and
    the noise level's estimate from the finite noise window (0.55 dB, measured)."""
    return float(np.hypot(8.686 * 10 ** (-snr_db / 20), 0.55))


@pytest.mark.parametrize("kind, snr_db", [("us", 22.0), ("oa", 30.0), ("us", 45.0)])
def test_snr_estimate_is_unbiased_with_the_predicted_scatter(kind, snr_db):
    tmpl = US if kind == "us" else OA
    rng = np.random.default_rng(7)
    sigma = 100 * np.sqrt(tmpl.energy) / 10 ** (snr_db / 20)
    x = np.stack([pulse_at(tmpl, d, 100) for d in rng.uniform(60, 850, 400)])
    est = FILTERS[kind](x + rng.normal(0, sigma, x.shape)).snr_db - snr_db
    assert abs(est.mean()) < 0.2
    assert est.std() == pytest.approx(snr_std_db(snr_db), rel=0.15)


@pytest.mark.parametrize("kind", ["us", "oa"])
def test_noiseless_arrivals_are_unbiased_at_every_fraction_of_a_sample(kind):
    tmpl = US if kind == "us" else OA
    delays = 300 + np.linspace(0, 1, 65)
    x = np.stack([pulse_at(tmpl, d) for d in delays])
    r = FILTERS[kind](x)
    assert np.abs(r.index - delays).max() < 1e-3  # raw-sample parabolas: ~5e-2


@pytest.mark.parametrize("tmpl", [US, OA])
def test_correlation_is_predicted_between_samples(tmpl):
    """The matched filter's output at fractional lags, from its samples around the lag, against
    the exact band-limited value (inverse DFT at that lag) for noise through the filter."""
    pad = np.zeros(N)
    pad[:len(tmpl.pulse)] = tmpl.pulse
    spec = np.conj(np.fft.rfft(pad))
    lags, offsets = np.arange(-11, 12), np.linspace(-0.5, 0.5, 9)
    w = interpolation_weights(np.abs(spec) ** 2, N, lags, offsets)
    C = np.fft.rfft(np.random.default_rng(2).normal(size=(100, N)), axis=1) * spec
    c = np.fft.irfft(C, n=N, axis=1)
    k = np.arange(C.shape[1])
    half = np.where((k == 0) | (k == N // 2), 1.0, 2.0) / N
    exact = (C[:, None, :] * np.exp(2j * np.pi * np.outer(500 + offsets, k) / N) * half
             ).real.sum(axis=2)
    err = c[:, 500 + lags] @ w - exact
    # 21 taps at 3.333 MS/s: US 1.7 %, OA 1.0 % (0.5 / 0.3 % at the earlier 3.58 MS/s, whose
    # Nyquist lay further above the US pulse's band); linear interpolation: ~0.3
    assert np.sqrt(np.mean(err ** 2) / np.mean(exact ** 2)) < 0.02
    assert np.abs(err[:, 4]).max() < 1e-4 * np.abs(exact).max()  # at a sample: the sample


def test_no_echo_gives_nan_and_a_reason():
    rng = np.random.default_rng(1)
    r = FILTERS["oa"](rng.normal(0, 10, (5, N)))
    assert np.isnan(r.index).all()
    assert all(s.startswith("no echo: SNR") for s in r.reason)


@given(gap=st.floats(25, 300), second=st.floats(0.2, 1.0), seed=st.integers(0, 2**31))
@settings(max_examples=40)
def test_two_echoes_give_the_first(gap, second, seed):
    rng = np.random.default_rng(seed)
    x = pulse_at(US, 300.3, 1000) + pulse_at(US, 300.3 + gap, 1000 * second)
    x += rng.normal(0, 5, N)
    r = FILTERS["us"](x[None, :])
    assert abs(r.index[0] - 300.3) < 0.05


def test_trigger_phase_and_pretrigger_removal_is_exact():
    x = np.stack([pulse_at(US, 400.0, 1000), pulse_at(US, 400.0, 1000)])
    r = FILTERS["us"](x)
    phase_s = np.array([0.0, 37 / 240e6])
    t = r.times_s(FS, phase_s, pretrigger=64)
    assert t[1] - t[0] == pytest.approx(37 / 240e6, abs=1e-15)
    assert t[0] == pytest.approx((r.index[0] - 64) / FS)


def test_gate_limits_where_an_echo_may_be():
    x = pulse_at(US, 100.0, 3000) + pulse_at(US, 600.0, 1000)
    r = FILTERS["us"](x[None, :], gate=(300, 1000))
    assert abs(r.index[0] - 600.0) < 0.01


def test_range_models():
    c = speed_of_sound_mm_s(20.0)
    assert c == pytest.approx(343_214, rel=1e-4)
    t = np.array([2e-6 + 10 / c])
    assert distance_mm(t, 2e-6, c, "oa")[0] == pytest.approx(10.0)
    assert distance_mm(t, 2e-6, c, "us")[0] == pytest.approx(5.0)


@pytest.mark.parametrize("kind", ["us", "oa"])
def test_no_reported_distance_is_far_outside_its_own_std(kind):
    """From 5 to 40 dB: readings below the ambiguity SNR are flagged, and those reported lie
    within 5 of their own std of the truth (a cycle slip is 20-50 std away)."""
    tmpl, mf = (US if kind == "us" else OA), FILTERS[kind]
    rng = np.random.default_rng(11)
    reported = far = 0
    for snr_db in (5, 10, 14, 16, 17, 18, 19, 20, 25, 40):
        delays = rng.uniform(150, 850, 300)
        x = np.stack([pulse_at(tmpl, d) for d in delays])
        sigma = np.sqrt(tmpl.energy) / 10 ** (snr_db / 20)
        r = mf(x + rng.normal(0, sigma, x.shape), min_snr_db=0.0)
        ok = np.isfinite(r.index)
        assert np.isfinite(r.index_std[ok]).all() and np.isnan(r.index_std[~ok]).all()
        assert all(s.startswith(("ambiguous", "spike")) for s in r.reason[~ok])
        reported += ok.sum()
        far += (np.abs(r.index[ok] - delays[ok]) > 5 * r.index_std[ok]).sum()
        if snr_db <= 10:
            assert ok.sum() == 0  # far below the floor nothing is reported
    assert reported > 1200
    assert far <= 0.002 * reported


@pytest.mark.parametrize("kind", ["us", "oa"])
def test_each_reading_std_is_its_rmse_above_the_floor(kind):
    tmpl, mf = (US if kind == "us" else OA), FILTERS[kind]
    rng = np.random.default_rng(3)
    delays = rng.uniform(150, 850, 2000)
    x = np.stack([pulse_at(tmpl, d) for d in delays])
    sigma = np.sqrt(tmpl.energy) / 10 ** (28 / 20)
    r = mf(x + rng.normal(0, sigma, x.shape))
    z = (r.index - delays) / r.index_std
    assert np.sqrt(np.mean(z ** 2)) == pytest.approx(1.0, abs=0.12)


def test_the_ambiguity_floor_follows_the_next_carrier_cycle():
    # a narrow-band pulse has a next cycle nearly as high as its peak: a higher floor
    narrow = MatchedFilter(gaussian_pulse(FS, 1.0e6, 0.3), N)
    assert narrow.rho1 > FILTERS["us"].rho1 > FILTERS["oa"].rho1 > 0.1
    assert narrow.ambiguity_snr_db > FILTERS["us"].ambiguity_snr_db > \
        FILTERS["oa"].ambiguity_snr_db > 14


def test_an_interference_spike_is_not_an_echo():
    """A one-sample spike correlates into a perfect template shape; it is flagged, while
    echoes of any centre frequency in the band (0.5-1.6 MHz) against a 1.1 MHz template are
    kept."""
    tmpl = gaussian_pulse(FS, 1.1e6, 0.8)
    mf = MatchedFilter(tmpl, N)
    rng = np.random.default_rng(5)
    x = rng.normal(0, 5, (40, N))
    x[np.arange(40), rng.integers(100, 900, 40)] += rng.choice([-375, 375], 40)
    r = mf(x)
    assert np.isnan(r.index).all() and all(s.startswith("spike:") for s in r.reason)
    for fc, bw in ((0.5e6, 0.9), (1.1e6, 0.8), (1.6e6, 0.9)):
        sg = np.sqrt(2 * np.log(2)) / (np.pi * bw * fc)
        delays = rng.uniform(100, 900, 40)
        t = (np.arange(N)[None, :] - delays[:, None]) / FS
        echo = 300 * np.exp(-0.5 * (t / sg) ** 2) * np.cos(2 * np.pi * fc * t)
        r = mf(echo + rng.normal(0, 5, echo.shape))
        assert not any(s.startswith("spike") for s in r.reason), fc


@settings(max_examples=40, deadline=None)
@given(kind=st.sampled_from(["us", "oa"]), seed=st.integers(0, 2**31),
       gate=st.tuples(st.integers(0, 500), st.integers(40, 1024)),
       n_echoes=st.integers(0, 3), spikes=st.integers(0, 2))
@example(kind="us", seed=2, gate=(0, 40), n_echoes=0, spikes=0)  # noise only: SNR ~0 dB
def test_one_waveform_at_a_time_reads_as_in_a_batch(kind, seed, gate, n_echoes, spikes):
    """A scan or the live stream ranges one waveform at a time (MatchedFilter._arrival, on
    scalars); a batch ranges many at once. Both read every waveform alike: whether there is
    an arrival and why not, and the arrival, SNR and std to float32 rounding (a batch's
    matrix products sum in another order: ~1e-7 samples)."""
    mf, tmpl = FILTERS[kind], US if kind == "us" else OA
    rng = np.random.default_rng(seed)
    x = rng.normal(0, rng.uniform(2, 40), (12, N))
    for row in x:
        for _ in range(n_echoes):  # anywhere, the edges included, weak to strong
            row += pulse_at(tmpl, rng.uniform(-20, N + 20), rng.uniform(20, 3000))
        row[rng.integers(0, N, spikes)] += rng.choice([-900.0, 900.0], spikes)
    lo, hi = gate[0], max(gate[0] + 40, gate[1])
    batch = mf(x, gate=(lo, hi))
    for i in range(len(x)):
        one = mf(x[i:i + 1], gate=(lo, hi))
        np.testing.assert_allclose(one.index, batch.index[i:i + 1], rtol=0, atol=1e-5)
        assert one.reason[0].split(":")[0] == batch.reason[i].split(":")[0]
        for f in ("amplitude", "index_std"):
            np.testing.assert_allclose(getattr(one, f), getattr(batch, f)[i:i + 1],
                                       rtol=1e-5, err_msg=f)
        # a log: 1e-5 of the amplitude is 8.7e-5 dB, whatever the level (an SNR near 0 dB
        # has no relative tolerance: CI found -0.070582 against -0.070581 dB)
        np.testing.assert_allclose(one.snr_db, batch.snr_db[i:i + 1], rtol=0, atol=1e-4,
                                   err_msg="snr_db")
