"""Protocol conformance of the sensor firmware, run against QEMU or a real board by port name."""

import numpy as np
import pytest

from dmdsm.protocol import encode_frame, encode_raw, load_spec
from dmdsm.protocol.messages import Message

SPEC = load_spec()
CFG = dict(n_samples=1024, sample_rate_div=1, n_average=16, pretrigger=0, trigger_edge=0,
           modality=0, sample_format=0, trigger_timeout_ms=2000)


def configure(dut, **changes):
    r = dut.request("set_config", **{**CFG, **changes})
    assert r.name == "ack", r
    return r


def test_ping_echoes_the_nonce(dut):
    r = dut.request("ping", nonce=0xC0FFEE)
    assert r.name == "pong" and r.nonce == 0xC0FFEE and r.is_response


def test_identify_reports_this_spec(dut):
    r = dut.request("identify")
    assert r.name == "identify_reply"
    assert r.protocol_version == SPEC.version
    assert r.spec_hash == SPEC.hash, "firmware built from another messages.toml"
    assert r.tick_hz > 0 and r.max_samples >= 1024 and r.board


def test_config_round_trip(dut):
    configure(dut, n_samples=2048, n_average=4, pretrigger=100, trigger_edge=1, modality=1)
    got = dut.request("get_config")
    assert got.name == "config"
    assert got.fields == {**CFG, "n_samples": 2048, "n_average": 4, "pretrigger": 100,
                          "trigger_edge": 1, "modality": 1}


@pytest.mark.parametrize("change,detail", [
    ({"n_samples": 8}, 1), ({"n_average": 0}, 3), ({"pretrigger": 1024}, 4),
    ({"trigger_edge": 7}, 5), ({"sample_format": 1, "n_samples": 8192}, 7),
])
def test_bad_config_is_naked_and_changes_nothing(dut, change, detail):
    configure(dut)
    r = dut.request("set_config", **{**CFG, **change})
    assert r.name == "nak" and r.error == SPEC.enums["error"]["out_of_range"]
    assert r.detail == detail
    assert dut.request("get_config").fields == CFG


def _expected_pattern(k0: int, n_avg: int, n: int) -> np.ndarray:
    """Mean over shots k0..k0+n_avg-1 of the QEMU test pattern (i + k) mod 4096, rounded."""
    i = np.arange(n)[None, :]
    k = np.arange(k0, k0 + n_avg)[:, None]
    s = ((i + k) & 0xFFF).sum(axis=0)
    return ((s + n_avg // 2) // n_avg).astype(np.uint16)


def test_arm_n_shots_gives_consecutive_ids_and_averaged_samples(dut):
    configure(dut)
    assert dut.request("arm", n_shots=20).name == "ack"
    waves = dut.waveforms(20)
    assert [w.shot_id for w in waves] == list(range(20))
    assert all(w.n_average == 16 and w.samples.size == 1024 for w in waves)
    ts = [w.timestamp for w in waves]
    assert ts == sorted(ts) and len(set(ts)) == 20
    assert dut.waveforms(1, timeout=0.3) == []  # exactly n_shots
    status = dut.request("get_status")
    assert status.state == SPEC.enums["state"]["idle"]
    if "QEMU" in dut.request("identify").board:
        for w in waves[:3]:
            k0 = (int(w.samples[0]) - 8) % 4096  # mean of k0..k0+15 is k0 + 7.5 -> k0 + 8
            np.testing.assert_array_equal(w.samples, _expected_pattern(k0, 16, 1024))


def test_u32_sums_keep_every_bit(dut):
    configure(dut, sample_format=1, n_average=64, n_samples=512)
    dut.request("arm", n_shots=2)
    waves = dut.waveforms(2)
    assert [w.samples.dtype for w in waves] == [np.dtype("<u4")] * 2
    assert all(w.samples.max() <= 64 * 0xFFFF for w in waves)


def test_disarm_mid_burst_stops_the_stream(dut):
    configure(dut, n_average=4)
    dut.request("arm", n_shots=0)
    assert len(dut.waveforms(3)) >= 3
    assert dut.request("disarm").name == "ack"
    dut.pump(0.3)  # frames already queued may still arrive
    dut.unsolicited.clear()
    assert dut.waveforms(1, timeout=0.5) == []
    assert dut.request("get_status").state == SPEC.enums["state"]["idle"]


def test_garbage_is_counted_and_the_link_recovers(dut):
    before = dut.request("get_status")
    good = bytearray(encode_frame(Message("ping", seq=5000, nonce=1)))
    good[6] ^= 0x20
    dut.send_raw(b"\x00\x07\x07\x07\x00" + bytes(good) + b"\x00\x05\x41\x00")
    after = dut.request("get_status")
    assert after.rx_crc_errors == before.rx_crc_errors + 1
    assert after.rx_malformed >= before.rx_malformed + 2
    assert dut.request("ping", nonce=2).nonce == 2


def test_retransmitted_command_runs_once(dut):
    configure(dut, n_average=8)
    a = dut.request("arm", seq=4242, n_shots=3)
    # the ack was "lost": the same bytes again, flagged as a retransmission
    b = dut.request("arm", seq=4242, flags=SPEC.flags["retransmit"], n_shots=3)
    assert a.name == b.name == "ack"
    waves = dut.waveforms(6, timeout=2.0)
    assert [w.shot_id for w in waves] == [0, 1, 2]


def test_a_new_client_at_an_old_seq_gets_its_own_answer(dut):
    """Only a retransmission is answered from the cache (issue 19): a ping at the seq of the
    last command, unflagged, is executed and answered with its own pong."""
    a = dut.request("get_status", seq=4343)
    b = dut.request("ping", seq=4343, nonce=77)
    assert a.name == "status" and b.name == "pong" and b.seq == 4343 and b.nonce == 77


def test_unknown_and_wrong_version_frames_are_naked(dut):
    dut.send_raw(encode_raw(0x7E, 777, 0, b""))
    r = dut.pump(1.0)
    naks = [m for m in r if getattr(m, "name", "") == "nak"]
    assert naks and naks[0].seq == 777 and naks[0].error == SPEC.enums["error"]["unknown_type"]
    dut.send_raw(encode_raw(0x01, 778, 0, bytes(4), version=2))
    r = dut.pump(1.0)
    naks = [m for m in r if getattr(m, "name", "") == "nak"]
    assert naks and naks[0].error == SPEC.enums["error"]["bad_version"]


@pytest.mark.parametrize("n, samples, average", [(40, 4096, 1), (9, 1024, 3), (25, 128, 1)])
def test_an_arm_for_n_sends_n_waveforms_without_gaps(dut, n, samples, average):
    """At 1 kHz the laser outruns the link at these settings: the board skips the triggers it
    has no slot for and still sends exactly n waveforms, ids 0..n-1 (issue 37)."""
    configure(dut, n_average=average, n_samples=samples)
    before = dut.request("get_status")
    dut.request("arm", n_shots=n)
    waves = dut.waveforms(n + 1, timeout=3.0)  # one more than asked: none may come
    assert [w.shot_id for w in waves] == list(range(n))
    assert all(w.n_average == average and len(w.samples) == samples for w in waves)
    after = dut.request("get_status")
    assert after.shots_sent - before.shots_sent == n and after.shots_remaining == 0
    skipped = after.triggers_skipped - before.triggers_skipped
    assert waves[-1].triggers_skipped - before.triggers_skipped == skipped
    faults = (after.adc_overruns - before.adc_overruns
              + after.integrity_faults - before.integrity_faults)
    assert after.triggers - before.triggers == n * average + skipped + faults


