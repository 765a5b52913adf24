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


def test_the_physics_database_averages_shots_as_the_core_does():
    """`averaged_shots` (the classification database's and the calibration rig's waveforms)
    equals the firmware core fed the same shots: each shot from its own sampling phase,
    summed and rounded, the trigger phase the phases' rounded mean. Given one phase for all
    shots, as it once was, the database's pulses were sharper than the board's and a
    classifier trained on them misread the board's (issue 33: the bottle's material)."""
    from dmdsm.sim.boards.sensor.core_board import ADC_RATE_HZ, TICK_HZ, averaged_shots
    from dmdsm.sim.physics.objects import household
    from dmdsm.sim.physics.scene import Scene
    from dmdsm.sim.physics.signals import SensorModel, synthesize, to_adc

    scene = Scene(objects=household("plastic_bottle"))
    model = SensorModel()
    hit = scene.cast(scene.X_R - 60.0 * scene.v / np.linalg.norm(scene.v)
                     + np.array([0.0, 0.0, 60.0]), 0.0)
    n, avg, period = 512, 12, int(round(TICK_HZ / ADC_RATE_HZ))
    wave, phase = averaged_shots(hit, model, n, avg, np.random.default_rng(5), seed=1)

    rng = np.random.default_rng(5)  # the same draws, fed to the real core one shot at a time
    phases = rng.integers(1, period + 1, size=avg)
    assert len(set(phases.tolist())) > 1
    dev = FirmwareCore(tick_hz=TICK_HZ)
    dec = FrameDecoder()
    cfg = dict(n_samples=n, sample_rate_div=1, n_average=avg, pretrigger=0, trigger_edge=0,
               modality=1, sample_format=0, trigger_timeout_ms=500)
    assert talk(dev, dec, Message("set_config", seq=1, **cfg))[0].name == "ack"
    assert talk(dev, dec, Message("arm", seq=2, n_shots=1))[0].name == "ack"
    for k, p in enumerate(phases):
        t_us = (np.arange(n) / ADC_RATE_HZ + int(p) / TICK_HZ) * 1e6
        shot = to_adc(synthesize(hit, model, t_us, rng, 1), model)
        dev.set_ticks(1000 + 240_000 * (k + 1))
        dev.capture(shot, edge_ticks=240_000 * (k + 1), phase_ticks=int(p))
    (w,) = [m for m in dec.feed(dev.tx()) + dec.feed(dev.tx()) if m.name == "waveform"]
    np.testing.assert_array_equal(wave, w.samples)
    assert phase == w.trigger_phase and w.n_average == avg
    dev.close()
