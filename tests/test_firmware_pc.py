"""The PC build of the firmware core, driven as the SIL emulator drives it."""

import numpy as np

from dmdsm.protocol import FrameDecoder, Message, encode_frame, load_spec
from dmdsm.sim.boards.sensor.firmware_core import FirmwareCore

SPEC = load_spec()


def talk(dev, dec, msg):
    dev.rx(encode_frame(msg))
    out = []
    while chunk := dev.tx():
        out += dec.feed(chunk)
    return out


def test_pc_core_answers_and_averages_emulated_bursts():
    dev = FirmwareCore(name="SIL test", tick_hz=1_000_000)
    dec = FrameDecoder()
    (r,) = talk(dev, dec, Message("identify", seq=1))
    assert r.spec_hash == SPEC.hash and r.board == "SIL test"
    cfg = dict(n_samples=256, sample_rate_div=1, n_average=3, pretrigger=10, trigger_edge=0,
               modality=1, sample_format=0, trigger_timeout_ms=500)
    assert talk(dev, dec, Message("set_config", seq=2, **cfg))[0].name == "ack"
    assert talk(dev, dec, Message("arm", seq=3, n_shots=2))[0].name == "ack"
    rng = np.random.default_rng(3)
    bursts = rng.integers(0, 65536, (6, 256), dtype=np.uint16)
    t = 1000
    for b in bursts:
        assert dev.armed()["n_samples"] == 256
        t += 1000
        dev.set_ticks(t)
        dev.capture(b, edge_ticks=t - 3, phase_ticks=5)
    waves = [m for m in dec.feed(dev.tx()) + dec.feed(dev.tx()) if m.name == "waveform"]
    assert [w.shot_id for w in waves] == [0, 1]
    for w, group in zip(waves, (bursts[:3], bursts[3:])):
        expected = (group.astype(np.uint32).sum(0) + 1) // 3
        np.testing.assert_array_equal(w.samples, expected)
        assert w.modality == 1 and w.pretrigger == 10 and w.trigger_phase == 5
    assert waves[0].timestamp == 1997 and waves[1].timestamp == 4997
    assert dev.armed() is None and dev.state == 0
    dev.close()


def test_pc_core_times_out_without_edges():
    dev = FirmwareCore(tick_hz=1_000_000)
    dec = FrameDecoder()
    cfg = dict(n_samples=64, sample_rate_div=1, n_average=1, pretrigger=0, trigger_edge=0,
               modality=0, sample_format=0, trigger_timeout_ms=100)
    talk(dev, dec, Message("set_config", seq=1, **cfg))
    talk(dev, dec, Message("arm", seq=2, n_shots=5))
    dev.set_ticks(50_000)
    assert dev.armed() is not None
    dev.set_ticks(200_000)
    logs = [m for m in dec.feed(dev.tx()) if m.name == "log"]
    assert logs and logs[0].code == SPEC.enums["error"]["no_trigger"]
    assert dev.armed() is None
