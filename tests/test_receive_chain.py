"""The SIL's receive chain: exact for Gaussian pulses, and what makes a 1.6 MHz OA pulse rangeable
at the board's 3.333 MS/s (before it, the arrival moved ~80 ns with the sampling phase)."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from dmdsm.host.ranging.matched_filter import MatchedFilter, gaussian_pulse
from dmdsm.sim.boards.sensor.core_board import ADC_RATE_HZ
from dmdsm.sim.physics.signals import MATERIALS, SensorModel, _pulse, received, through


def _filtered_numerically(fc, bw, pass_fc, pass_sigma):
    """The pulse through the Gaussian band by FFT on a fine grid (MHz, us)."""
    t = (np.arange(1 << 14) - (1 << 13)) * 0.002  # us, 500 MS/s
    f = np.fft.fftfreq(t.size, 0.002)  # MHz
    band = np.exp(-0.5 * ((np.abs(f) - pass_fc) / pass_sigma) ** 2)
    return t, np.fft.ifft(np.fft.fft(np.fft.ifftshift(_pulse(t, fc, bw))) * band).real


# the bands the chain uses: low-passes, and a transducer band at 1 MHz as narrow as ours
BANDS = st.one_of(st.tuples(st.just(0.0), st.floats(0.3, 2.0)),
                  st.tuples(st.just(1.0), st.floats(0.3, 0.4)))


@settings(max_examples=30, deadline=None)
@given(fc=st.floats(0.3, 1.6), bw=st.floats(0.4, 1.0), band=BANDS)
def test_through_is_the_pulse_filtered_by_the_band(fc, bw, band):
    """Exact for a low-pass; for a band pass up to the pulse's two spectral lobes meeting at
    0 Hz, within half a percent of the peak for the materials' pulses."""
    pass_fc, pass_sigma = band
    t, y = _filtered_numerically(fc, bw, pass_fc, pass_sigma)
    y = np.fft.fftshift(y)
    c, b = through(fc, bw, pass_fc, pass_sigma)
    shape = _pulse(t, c, b)
    gain = float(y @ shape / (shape @ shape))
    assert np.max(np.abs(y - gain * shape)) < 5e-3 * np.max(np.abs(y))
    assert min(fc, pass_fc) - 1e-9 <= c <= max(fc, pass_fc) + 1e-9 or pass_fc == 0.0


def test_received_pulses_lie_below_nyquist_and_keep_the_materials_apart():
    model = SensorModel()
    nyquist = ADC_RATE_HZ / 2e6
    centres = {}
    for name, mat in MATERIALS.items():
        if mat.oa:
            c, b = received(model, mat.oa_fc_mhz, mat.oa_bw, "oa")
            centres[name] = c
            assert c + b * c / 2 < nyquist  # the -6 dB band edge
    assert centres["graphite"] > centres["aluminium"] > centres["plastic"] > centres["paper"] \
        > centres["foam"]


def test_graphite_oa_arrival_does_not_move_with_the_sampling_phase():
    """Noise-free received graphite pulses at random sub-sample arrivals, ranged by the host's
    matched filter with a 1.1 MHz template: the error stays within a few ns (81 ns rms when
    the raw 1.6 MHz pulse reached the ADC)."""
    model, fs = SensorModel(), ADC_RATE_HZ
    fc, bw = received(model, MATERIALS["graphite"].oa_fc_mhz, MATERIALS["graphite"].oa_bw, "oa")
    mf = MatchedFilter(gaussian_pulse(fs, 1.1e6, 0.8), 1024)
    rng = np.random.default_rng(1)
    true = rng.uniform(100, 101, 200)
    k = np.arange(1024)
    x = np.array([3000 * _pulse((k - a) / fs * 1e6, fc, bw) for a in true])
    err_ns = (mf(x, min_snr_db=-100, noise=slice(900, 1024)).index - true) / fs * 1e9
    assert np.std(err_ns) < 6.0 and np.max(np.abs(err_ns - err_ns.mean())) < 10.0
