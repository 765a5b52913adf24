"""The turntable's STEP line on the sensor board's second sync input (SIL: the firmware core
fed by the Marlin emulator): its bursts are reported apart from X's, and every waveform
carries the table steps made before its shots, as the truth has them."""

import numpy as np
import pytest

from dmdsm.protocol import FrameDecoder, Message, encode_frame, load_spec
from dmdsm.sim.servers.runner import SimConfig, Simulation

SPEC = load_spec()
INPUT = SPEC.enums["sync_input"]
TICK_HZ = 240e6
N_AVG = 8


def run_turn(sync_wire: str = "xa") -> tuple[Simulation, list[Message], float]:
    """Arm continuous acquisition, turn the table 90 deg while X moves 5 mm in one block,
    dwell 0.1 s and turn it 45 deg more alone; returns (sim, messages, time the turn was
    sent)."""
    sim = Simulation(SimConfig(scene="aluminium_block", seed=7, sync_wire=sync_wire))
    dec, out = FrameDecoder(), []

    def run(seconds: float) -> None:
        for _ in range(round(seconds / 0.01)):
            sim.advance(0.01)
            sim.read("stage")
            out.extend(m for m in dec.feed(sim.read("sensor")) if isinstance(m, Message))

    run(2.0)  # Marlin's boot
    sim.write("sensor", encode_frame(Message(
        "set_config", seq=1, n_samples=256, sample_rate_div=1, n_average=N_AVG,
        pretrigger=16, trigger_edge=0, modality=0, sample_format=0, trigger_timeout_ms=0)))
    run(0.05)
    sim.write("sensor", encode_frame(Message("arm", seq=2, n_shots=0)))
    run(0.05)
    sent = sim.t
    sim.write("stage", b"G91\nG1 X5 A90 F3000\nG4 P100\nG1 A45 F2700\n")
    run(3.0)
    return sim, out, sent


def test_the_table_turn_is_its_own_burst_and_every_waveform_counts_its_steps():
    sim, msgs, sent = run_turn()
    a_axis = sim.limits.axis("A")
    spu = sim.limits.steps_per_unit[a_axis]
    bursts = [m for m in msgs if m.name == "motion_sync"]
    xs = [m for m in bursts if m.input == INPUT["x"]]
    turns = [m for m in bursts if m.input == INPUT["a"]]
    # X's 5 mm (80 steps/mm): X steps at half the table's rate in that block and may be
    # quiet for a sync_quiet_ms at its start (the bursts of an axis that is not a block's
    # fastest may split); the table's two moves, a dwell apart, are two bursts
    assert sum(m.edges for m in xs) == 400
    assert [m.edges for m in turns] == [round(90 * spu), round(45 * spu)]
    truth = sim.stage.step_edges(a_axis, sent, sim.t)
    assert len(truth) == sum(m.edges for m in turns)
    for m, (lo, hi) in zip(turns, ((0, turns[0].edges - 1), (turns[0].edges, len(truth) - 1))):
        assert abs(m.first_edge - truth[lo] * TICK_HZ) <= 1
        assert abs(m.last_edge - truth[hi] * TICK_HZ) <= 1
    assert not {m.burst_id for m in turns} & {m.burst_id for m in xs}
    # each waveform: the steps of the table's open burst made before each of its shots'
    # laser edges, summed (waveforms whose shots all fall within a burst)
    waves = [m for m in msgs if m.name == "waveform"]
    checked = 0
    for w in waves:
        shots = w.timestamp / TICK_HZ + np.arange(N_AVG) / 1000.0  # the laser at 1 kHz
        for m in turns:
            first, last = m.first_edge / TICK_HZ, m.last_edge / TICK_HZ
            if first <= shots[0] and shots[-1] <= last + 0.01:
                mine = truth[(truth >= first - 0.5 / TICK_HZ) & (truth <= last + 0.5 / TICK_HZ)]
                want = sum(int(np.sum(mine <= t + 0.5 / TICK_HZ)) for t in shots)
                assert w.sync_steps_a == want
                # and the counted angle is where the table was, within one step
                t_mid = shots.mean()
                a0 = sim.stage.position_at(first - 1e-4)[a_axis]
                counted = a0 + w.sync_steps_a / N_AVG / spu
                mean_truth = np.mean([sim.stage.position_at(t)[a_axis] for t in shots])
                assert abs(counted - mean_truth) <= 1.0 / spu, t_mid
                checked += 1
    assert checked > 100


@pytest.mark.parametrize("wire,want", [("x", {0}), ("", set())])
def test_an_unplugged_step_line_reports_no_burst(wire, want):
    _, msgs, _ = run_turn(wire)
    assert {m.input for m in msgs if m.name == "motion_sync"} == want
    assert all(m.sync_steps_a == 0 for m in msgs if m.name == "waveform")


def test_a_sync_wire_naming_no_step_line_is_refused_in_one_line():
    with pytest.raises(ValueError, match="sync_wire must name the STEP lines wired"):
        Simulation(SimConfig(sync_wire="xz"))
