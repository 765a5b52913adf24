"""hil_sim in time: a fly line's waveforms do not depend on how the emulator is stepped (shots
cast in batches, coarse or fine steps), and the keyed noise is the distribution it claims."""

import numpy as np
from scipy import stats

from dmdsm.protocol import FrameDecoder, Message, encode_frame
from dmdsm.sim.physics.scene import hash_noise, keyed_laplace, keyed_normal
from dmdsm.sim.servers.runner import SimConfig, Simulation


def fly_line_waveforms(chunk_s: float) -> list[tuple[int, int, bytes]]:
    """(shot id, timestamp, samples) of every waveform streamed while X moves 40 mm at
    83 mm/s, the emulator advanced in chunks of chunk_s seconds."""
    sim = Simulation(SimConfig(scene="aluminium_block", seed=5))
    dec = FrameDecoder()
    out = []

    def run(seconds: float) -> None:
        for _ in range(round(seconds / chunk_s)):
            sim.advance(chunk_s)
            sim.read("stage")
            out.extend(m for m in dec.feed(sim.read("sensor"))
                       if isinstance(m, Message) and m.name in ("waveform", "motion_sync"))

    sim.write("stage", b"G28\n")
    run(12.0)
    sim.write("stage", b"G1 X210 Y266 Z32 F12000\n")
    run(3.0)
    sim.write("sensor", encode_frame(Message(
        "set_config", seq=1, n_samples=1024, sample_rate_div=1, n_average=12, pretrigger=64,
        trigger_edge=0, modality=0, sample_format=0, trigger_timeout_ms=0)))
    run(0.1)
    sim.write("sensor", encode_frame(Message("arm", seq=2, n_shots=0)))
    sim.write("stage", b"G1 X250 F5000\n")
    run(1.5)
    return [(int(m.fields["shot_id"]), int(m.fields["timestamp"]),
             np.asarray(m.fields["samples"]).tobytes()) if m.name == "waveform" else
            (m.fields["burst_id"], m.fields["first_edge"], m.fields["last_edge"],
             m.fields["edges"]) for m in out]


def test_a_fly_line_gives_the_same_waveforms_and_step_burst_however_the_emulator_is_stepped():
    fine = fly_line_waveforms(0.001)   # one shot per step
    coarse = fly_line_waveforms(0.02)  # batches of shots cast together
    assert fine == coarse
    waves = [m for m in fine if len(m) == 3]
    assert len(waves) > 60  # 83 waveforms/s while the line runs
    # the stage moved: the waveforms differ from one another (not one pose repeated)
    assert len({w[2] for w in waves}) == len(waves)
    # the line's X steps (40 mm, 80 steps/mm) are one motion_sync, after the first waveform
    # (the burst before it is homing and the approach)
    bursts = [m for m in fine if len(m) == 4]
    assert len(bursts) == 2 and bursts[-1][3] == 3200
    assert bursts[-1][1] > waves[0][1]


def test_keyed_noise_is_normal_and_laplace_with_the_stated_scale_and_repeatable():
    keys = [f"S[{i * 0.0125:.3f} 266.000 32.000]".encode() for i in range(4000)]
    g = np.array([keyed_normal(k, 0.002) for k in keys])
    lap = np.array([keyed_laplace(k, 0.05) for k in keys])
    assert stats.kstest(g / 0.002, "norm").pvalue > 1e-3
    assert stats.kstest(lap / 0.05, "laplace").pvalue > 1e-3
    assert keyed_normal(keys[7], 0.002) == g[7]  # the same position, the same offset
    a = hash_noise("A90.0", 0.01, 3, seed=4)
    assert np.array_equal(a, hash_noise("A90.0", 0.01, 3, seed=4))
    assert not np.array_equal(a, hash_noise("A90.0", 0.01, 3, seed=5))
    assert len(set(a)) == 3  # three independent values, not one repeated
