"""Every emulated board offers what Simulation drives: its Protocol's members, with the same
parameters (hil_sim/boards/interface.py). A board that renames or drops one fails here."""

import inspect

import numpy as np
import pytest

from dmdsm.sim.boards.interface import SensorBoardInterface, StageBoardInterface
from dmdsm.sim.boards.sensor.core_board import SensorBoard
from dmdsm.sim.boards.sensor.rehost.board import RehostedSensor
from dmdsm.sim.boards.stage.avr_lockstep import AvrStageBoard
from dmdsm.sim.boards.stage.marlin import MarlinEmulator
from dmdsm.sim.servers.runner import SimConfig, Simulation


def members(protocol: type) -> dict[str, inspect.Signature | None]:
    """The Protocol's methods (name -> signature) and attributes (name -> None)."""
    out: dict[str, inspect.Signature | None] = {}
    for klass in protocol.__mro__:
        if klass is object or not getattr(klass, "_is_protocol", False):
            continue
        for name, value in vars(klass).items():
            if callable(value) and not name.startswith("_"):
                out.setdefault(name, inspect.signature(value))
        for name in getattr(klass, "__annotations__", {}):
            out.setdefault(name, None)
    return out


def params(sig: inspect.Signature) -> list[str]:
    return [p.name for p in sig.parameters.values() if p.name != "self"]


BOARDS = [(SensorBoardInterface, SensorBoard), (SensorBoardInterface, RehostedSensor),
          (StageBoardInterface, MarlinEmulator), (StageBoardInterface, AvrStageBoard)]


@pytest.mark.parametrize("protocol, board", BOARDS, ids=lambda x: x.__name__)
def test_each_board_has_its_interface_methods_with_the_same_parameters(protocol, board):
    for name, sig in members(protocol).items():
        if sig is None:
            continue
        assert callable(getattr(board, name, None)), f"{board.__name__} lacks {name}()"
        assert params(inspect.signature(getattr(board, name))) == params(sig), (board, name)


def test_the_interfaces_declare_what_the_simulation_calls():
    assert set(members(SensorBoardInterface)) == {"receive", "step", "sampling",
                                                  "link_blocked"}
    assert set(members(StageBoardInterface)) == {"receive", "step", "position_at",
                                                 "step_edges"}


def test_the_default_boards_carry_the_declared_attributes():
    sim = Simulation(SimConfig(seed=0))
    for protocol, board in ((SensorBoardInterface, sim.sensor), (StageBoardInterface,
                                                                 sim.stage)):
        for name in members(protocol):
            assert hasattr(board, name), (type(board).__name__, name)
    sim.close()


def test_a_board_without_a_method_fails_the_check():
    class Broken:
        def receive(self, data: bytes, now: float) -> None: ...
        def step(self, when: float) -> bytes: ...  # renamed parameter

    with pytest.raises(AssertionError):
        test_each_board_has_its_interface_methods_with_the_same_parameters(
            StageBoardInterface, Broken)


def test_the_sensor_emulator_computes_samples_only_for_the_shots_its_core_averages(
        monkeypatch):
    """At the link's limit the core skips ~9 laser shots in 10 (no free slot); the emulator
    asks the core first (dmdsm_core_takes_shot) and computes no waveform for those, yet the
    core counts them as before and sends the same stream."""
    from dmdsm.protocol import FrameDecoder, Message, encode_frame
    from dmdsm.sim.boards.sensor import core_board

    computed = []
    real = core_board.synthesize
    monkeypatch.setattr(core_board, "synthesize",
                        lambda *a, **k: computed.append(1) or real(*a, **k))
    sim = Simulation(SimConfig(seed=1))
    sim.write("sensor", encode_frame(Message("arm", seq=1, n_shots=0)))
    decoder, waves = FrameDecoder(), []
    for _ in range(100):  # 1 s of simulated time
        sim.advance(0.01)
        waves += [m for m in decoder.feed(sim.read("sensor")) if m.name == "waveform"]
    assert len(waves) >= 80  # ~95/s at 2 Mbaud
    assert [w.shot_id for w in waves] == list(range(len(waves)))
    n_average = int(waves[-1].n_average)
    skipped = int(waves[-1].triggers_skipped)
    assert skipped > 5 * len(waves)  # the link, not the laser, sets the rate
    # the shots of every waveform sent were computed; beyond them only those of the
    # waveforms still waiting in the board's two slots and of one open average
    assert len(waves) * n_average <= len(computed) <= (len(waves) + 3) * n_average


def test_an_averaged_waveform_takes_its_full_time_on_the_wire_after_its_last_shot():
    """With 16 shots averaged the link idles ~6 ms between waveforms; an idle UART saves no
    time, so each frame's last byte leaves no sooner than its bytes' time at 2 Mbaud after
    the last averaged shot (the live bench's latency beyond the wire was negative when the
    emulator let a frame start on credit saved while idle)."""
    from dmdsm.protocol import FrameDecoder, Message, encode_frame
    from dmdsm.sim.boards.sensor.core_board import TICK_HZ

    sim = Simulation(SimConfig(seed=2))
    decoder = FrameDecoder()

    def ask(msg: Message, want: str) -> Message:
        sim.write("sensor", encode_frame(msg))
        for _ in range(100):
            sim.advance(0.001)
            got = [m for m in decoder.feed(sim.read("sensor")) if m.name == want]
            if got:
                return got[0]
        raise AssertionError(f"no {want}")

    cfg = ask(Message("get_config", seq=1), "config")
    fields = {k: getattr(cfg, k) for k in ("n_samples", "sample_rate_div", "pretrigger",
                                           "trigger_edge", "modality", "sample_format",
                                           "trigger_timeout_ms")}
    fields.update(n_samples=1024, n_average=16)
    ask(Message("set_config", seq=2, **fields), "ack")
    sim.write("sensor", encode_frame(Message("arm", seq=3, n_shots=0)))
    late = []
    while len(late) < 20:
        sim.advance(2e-4)
        for m in decoder.feed(sim.read("sensor")):
            if m.name == "waveform":
                wire = len(encode_frame(m)) / 200_000.0
                last_shot = m.timestamp / TICK_HZ + 15e-3
                late.append(sim.t - last_shot - wire)
    late_ms = np.array(late[1:]) * 1e3
    assert late_ms.min() >= -0.3, late_ms  # never ahead of the wire (a step's slack)
    assert late_ms.max() <= 1.5, late_ms  # and not held back beyond one shot period
