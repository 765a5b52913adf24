"""Python codec: round trips, resynchronisation after damage, bounded memory, clear errors."""

import numpy as np
import pytest
from cobs import cobs
from hypothesis import given
from hypothesis import strategies as st

from dmdsm.protocol import (
    FrameDecoder,
    FrameError,
    Message,
    MessageError,
    cobs_extension_loaded,
    encode_frame,
    encode_raw,
)
from strategies import SPEC, any_message


def test_cobs_c_extension_is_in_use():
    assert cobs_extension_loaded()
    assert cobs.encode.__module__ != "cobs.cobs._cobs_py"


@given(any_message)
def test_decode_of_encode_is_identity(msg):
    frame = encode_frame(msg)
    assert frame[0] == 0 and frame[-1] == 0 and 0 not in frame[1:-1]
    dec = FrameDecoder()
    got = dec.feed(frame)
    assert got == [msg]
    assert dec.stats.frames == 1 and dec.stats.errors == 0


@given(st.lists(any_message, min_size=1, max_size=6), st.data())
def test_any_chunking_gives_the_same_messages(msgs, data):
    stream = b"".join(encode_frame(m) for m in msgs)
    cuts = sorted(data.draw(st.lists(st.integers(0, len(stream)), max_size=8)))
    dec = FrameDecoder()
    got = []
    prev = 0
    for c in [*cuts, len(stream)]:
        got += dec.feed(stream[prev:c])
        prev = c
    assert got == msgs


@given(st.lists(any_message, min_size=2, max_size=6), st.data())
def test_one_damaged_byte_costs_at_most_its_own_frame(msgs, data):
    frames = [encode_frame(m) for m in msgs]
    victim = data.draw(st.integers(0, len(frames) - 1), label="victim")
    f = bytearray(frames[victim])
    kind = data.draw(st.sampled_from(["drop", "insert", "flip"]), label="kind")
    if kind == "insert":
        pos = data.draw(st.integers(0, len(f)), label="pos")
        byte = data.draw(st.integers(0, 255), label="byte")
        f.insert(pos, byte)
        # the new byte sits between the delimiters; a delimiter next to a delimiter only
        # adds an empty frame and leaves the body whole
        body_hit = 0 < pos < len(frames[victim]) and not (
            byte == 0 and pos in (1, len(frames[victim]) - 1))
    else:
        pos = data.draw(st.integers(0, len(f) - 1), label="pos")
        body_hit = 0 < pos < len(f) - 1
        if kind == "drop":
            del f[pos]
        else:
            f[pos] ^= data.draw(st.integers(1, 255), label="mask")
    frames[victim] = bytes(f)
    dec = FrameDecoder(report_errors=True)
    items = dec.feed(b"".join(frames))
    got = [m for m in items if isinstance(m, Message)]
    others = [m for i, m in enumerate(msgs) if i != victim]
    if body_hit:
        assert got == others  # every untouched frame decoded, the touched one rejected
        assert dec.stats.errors >= 1 and any(isinstance(m, FrameError) for m in items)
    else:
        assert got in (msgs, others)  # a damaged delimiter costs at most its own frame


@given(st.binary(max_size=5000))
def test_arbitrary_bytes_never_raise_and_memory_is_bounded(data):
    dec = FrameDecoder(max_encoded=256)
    for i in range(0, len(data), 97):
        dec.feed(data[i:i + 97])
        assert len(dec._buf) <= 256
    s = dec.stats
    assert s.bytes == len(data)


def test_oversize_frame_is_dropped_counted_and_the_next_one_decodes():
    dec = FrameDecoder()
    huge = b"\x00" + b"\x41" * (SPEC.max_encoded + 10) + b"\x00"
    ping = Message("ping", seq=3, nonce=1)
    assert dec.feed(huge[:7000]) == []
    assert dec.feed(huge[7000:] + encode_frame(ping)) == [ping]
    assert dec.stats.oversize == 1
    # memory stays bounded while the oversize frame streams in
    dec2 = FrameDecoder()
    for _ in range(100):
        dec2.feed(b"\x41" * 4096)
        assert len(dec2._buf) <= SPEC.max_encoded
    assert dec2.stats.oversize == 1


def test_unknown_type_and_wrong_version_are_reported_not_raised():
    dec = FrameDecoder(report_errors=True)
    items = dec.feed(encode_raw(0x55, 1, 0, b"xyz") + encode_raw(0x01, 2, 0, bytes(4), version=9)
                     + encode_frame(Message("ping", seq=3, nonce=7)))
    kinds = [i.kind if isinstance(i, FrameError) else i.name for i in items]
    assert kinds == ["unknown_type", "bad_version", "ping"]
    assert "type 0x55" in items[0].detail
    assert "version 9" in items[1].detail
    assert dec.stats.unknown_type == 1 and dec.stats.bad_version == 1


def test_payload_length_must_match_the_type():
    dec = FrameDecoder(report_errors=True)
    items = dec.feed(encode_raw(0x01, 1, 0, b"\x01\x02\x03"))
    assert isinstance(items[0], FrameError) and items[0].kind == "malformed"
    assert "ping" in items[0].detail


def test_waveform_samples_are_a_numpy_view_of_the_frame():
    samples = np.arange(4096, dtype="<u2")
    m = Message("waveform", seq=1, shot_id=3, timestamp=5, trigger_phase=2, n_average=4,
                pretrigger=10, sample_rate_div=1, sample_format=0, modality=1,
                triggers_skipped=0, adc_overruns=0, integrity_faults=0,
                sync_steps=0, sync_steps_a=0,
                samples=samples)
    (got,) = FrameDecoder().feed(encode_frame(m))
    assert got.samples.dtype == np.dtype("<u2") and got.samples.base is not None
    np.testing.assert_array_equal(got.samples, samples)
    m32 = Message("waveform", seq=1, shot_id=3, timestamp=5, trigger_phase=2, n_average=4,
                  pretrigger=10, sample_rate_div=1, sample_format=1, modality=1,
                  triggers_skipped=0, adc_overruns=0, integrity_faults=0,
                  sync_steps=0, sync_steps_a=0,
                  samples=samples.astype("u4") * 4)
    (got32,) = FrameDecoder().feed(encode_frame(m32))
    assert got32.samples.dtype == np.dtype("<u4")


def test_bad_messages_give_one_clear_error():
    with pytest.raises(MessageError, match="unknown message type 'pingg'"):
        Message("pingg")
    with pytest.raises(MessageError, match="missing nonce"):
        encode_frame(Message("ping"))
    with pytest.raises(MessageError, match="unknown bogus"):
        encode_frame(Message("ping", nonce=1, bogus=2))
    with pytest.raises(MessageError, match=r"set_config.n_samples=70000 does not fit u16"):
        encode_frame(Message("set_config", n_samples=70000, sample_rate_div=1, n_average=1,
                             pretrigger=0, trigger_edge=0, modality=0, sample_format=0,
                             trigger_timeout_ms=0))
    big = np.zeros(SPEC.max_payload, "<u2")
    with pytest.raises(MessageError, match="exceeds"):
        encode_frame(Message("waveform", shot_id=0, timestamp=0, trigger_phase=0, n_average=1,
                             pretrigger=0, sample_rate_div=1, sample_format=0, modality=0,
                             triggers_skipped=0, adc_overruns=0, integrity_faults=0,
                             sync_steps=0, sync_steps_a=0,
                             samples=big))


def test_largest_waveform_fits_the_hard_maximum():
    m = Message("waveform", shot_id=0, timestamp=0, trigger_phase=0, n_average=1,
                pretrigger=0, sample_rate_div=1, sample_format=0, modality=0,
                triggers_skipped=0, adc_overruns=0, integrity_faults=0,
                sync_steps=0, sync_steps_a=0,
                samples=np.full(8192, 0xFFFF, "<u2"))
    frame = encode_frame(m)
    assert len(frame) - 2 <= SPEC.max_encoded
    assert FrameDecoder().feed(frame) == [m]


def test_link_efficiency_of_an_8kib_waveform_is_at_least_99_percent_worst_case():
    # DESIGN.md: payload bytes (the message's fields and samples) per wire byte >= 99 %;
    # no zero bytes at all: COBS adds its full one byte per 254
    m = Message("waveform", shot_id=0, timestamp=0, trigger_phase=0, n_average=1,
                pretrigger=0, sample_rate_div=1, sample_format=0, modality=0,
                triggers_skipped=0, adc_overruns=0, integrity_faults=0,
                sync_steps=0, sync_steps_a=0,
                samples=np.full(4096, 0x0101, "<u2"))
    frame = encode_frame(m)
    payload = SPEC.by_name["waveform"].fixed.size + m.samples.nbytes
    assert payload / len(frame) >= 0.99
    # the samples alone: 8192 of 8278 bytes (docs/protocol.md, "Link budget"); a new field
    # in every waveform shows here
    assert len(frame) == 8192 + 42 + 9 + 33 + 2 and m.samples.nbytes / len(frame) > 0.9895
