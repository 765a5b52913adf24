"""The link figures `dmdsm info` and `acquire` print: a waveform's bytes on the wire bound the
real frames, and the rate is the slower of the link and the laser (issue 37)."""

import numpy as np
from hypothesis import assume, given
from hypothesis import strategies as st

from dmdsm.host.links.link_rate import LASER_HZ, link_rate, waveform_wire_bytes
from dmdsm.protocol import Message, encode_frame


def _frame(samples: np.ndarray, fmt: int) -> bytes:
    return encode_frame(Message("waveform", shot_id=7, timestamp=1 << 40, trigger_phase=3,
                                n_average=2, pretrigger=0, sample_rate_div=1, sample_format=fmt,
                                modality=0, triggers_skipped=0, adc_overruns=0,
                                integrity_faults=0, sync_steps=0, sync_steps_a=0, samples=samples))


@given(st.integers(16, 8192), st.sampled_from([0, 1]), st.integers(0, 2**32 - 1))
def test_wire_bytes_bound_every_frame_and_are_reached(n, fmt, seed):
    dtype = "<u2" if fmt == 0 else "<u4"
    assume(n * np.dtype(dtype).itemsize <= 16384)  # the largest payload the protocol carries
    rng = np.random.default_rng(seed)
    samples = rng.integers(0, np.iinfo(dtype).max, n, endpoint=True).astype(dtype)
    assert len(_frame(samples, fmt)) <= waveform_wire_bytes(n, fmt)
    no_zero = np.full(n, 0x0101 if fmt == 0 else 0x01010101, dtype)  # COBS's worst case
    assert abs(len(_frame(no_zero, fmt)) - waveform_wire_bytes(n, fmt)) <= 1


@given(st.integers(16, 8192), st.integers(1, 4096))
def test_rate_is_the_slower_of_link_and_laser(n, average):
    r = link_rate(n, average)
    assert r.waveforms_hz == min(r.link_hz, LASER_HZ / average)
    assert 0.0 <= r.skipped_share < 1.0
    if r.limit == "link":  # an average up to free_average keeps the same rate
        assert link_rate(n, r.free_average).waveforms_hz >= r.waveforms_hz * 0.999
        assert link_rate(n, r.free_average + 1).limit == "laser"
    else:
        assert r.skipped_share == 0.0


def test_the_defaults_of_a_fresh_board():
    r = link_rate(1024, 1)
    assert r.wire_bytes == 2110 and round(r.link_hz) == 95 and r.limit == "link"
    assert r.free_average == 10 and "91% of laser shots are skipped (not a loss)" in r.text()
