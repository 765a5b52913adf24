"""The exact NUCLEO ELF on the rehosted H743: boot, identify, waveforms, integrity, faults."""

import numpy as np
import pytest

from dmdsm.protocol import FrameDecoder, Message, encode_frame, load_spec
from dmdsm.sim.boards.sensor.rehost.board import RehostedSensor
from dmdsm.sim.servers.runner import SimConfig, Simulation

SPEC = load_spec()
CFG = dict(n_samples=1024, sample_rate_div=1, n_average=4, pretrigger=16, trigger_edge=0,
           modality=0, sample_format=0, trigger_timeout_ms=2000)


class Host:
    """Commands over the simulated link, in simulated time."""

    def __init__(self, sim: Simulation) -> None:
        self.sim, self.dec, self.seq, self.other = sim, FrameDecoder(), 10, []

    def request(self, name: str, **fields) -> Message:
        self.seq += 1
        self.sim.write("sensor", encode_frame(Message(name, seq=self.seq, **fields)))
        for _ in range(100):
            self.sim.advance(0.005)
            for m in self.dec.feed(self.sim.read("sensor")):
                if m.is_response and m.seq == self.seq:
                    return m
                self.other.append(m)
        assert self.sim.sensor.violation is None, str(self.sim.sensor.violation)
        raise TimeoutError(name)

    def collect(self, seconds: float) -> list[Message]:
        self.sim.advance(seconds)
        self.other += self.dec.feed(self.sim.read("sensor"))
        out, self.other = self.other, []
        return out


def start(rev: str = "V", faults: tuple[str, ...] = (), seconds: float = 0.02) -> Host:
    sim = Simulation(SimConfig(sensor_firmware="nucleo"))
    if rev != "V" or faults:
        sim.sensor = RehostedSensor(sim.scene, sim.pose, sim.model, rev=rev, faults=faults)
    sim.advance(seconds)
    return Host(sim)


@pytest.mark.parametrize("rev,tick_hz", [("V", 240_000_000), ("Y", 200_000_000)])
def test_boots_without_breaking_a_rule_and_identifies(rev, tick_hz):
    host = start(rev)
    r = host.request("identify")
    assert host.sim.sensor.violation is None
    assert r.board.startswith("NUCLEO-H743ZI") and f"rev {rev}" in r.board
    assert r.tick_hz == tick_hz and r.spec_hash == SPEC.hash
    assert abs(r.adc_rate_hz - 1e9 / 300) < 1  # 300 ns pacing on both revisions
    mcu = host.sim.sensor.mcu
    assert mcu.pwr.vos() == (0 if rev == "V" else 1)
    assert mcu.rcc.cpu_hz() == (480e6 if rev == "V" else 400e6)


def test_heartbeat_led_blinks_at_1_hz():
    host = start(seconds=1.6)
    ld1 = [(t, level) for t, pin, level in host.sim.sensor.mcu.gpio["B"].log if pin == 0]
    times = [t for t, level in ld1 if level == 1]
    assert len(times) >= 1 and host.sim.sensor.violation is None
    gaps = np.diff([t for t, _ in ld1])
    assert gaps.size and np.allclose(gaps, 0.5, atol=0.01)


def test_waveforms_are_the_physics_seen_from_the_edge():
    """The transmit bang lies at the model's t0 after the laser edge, once the firmware's
    pretrigger and trigger phase are applied; the pretrigger holds the noise of n_average
    shots. (Nothing is in the beam at the start pose, so the bang is the only signal.)"""
    host = start()
    # 16 shots (16 ms) per waveform: the 2 Mbaud link carries a 2 kB frame in 10 ms
    assert host.request("set_config", **{**CFG, "n_average": 16}).name == "ack"
    assert host.request("arm", n_shots=3).name == "ack"
    waves = [m for m in host.collect(0.1) if m.name == "waveform"]
    assert [w.shot_id for w in waves] == [0, 1, 2]
    model = host.sim.model
    fs = 1e9 / 300
    for w in waves:
        x = w.samples.astype(float) - model.baseline
        t_us = (np.arange(x.size) - w.pretrigger) / fs * 1e6 + w.trigger_phase / 240.0
        assert abs(t_us[np.argmax(np.abs(x))] - model.t0_us_us) < 0.5
        noise = x[:w.pretrigger].std()
        assert 0.5 < noise / (model.noise_counts / np.sqrt(w.n_average)) < 2.0
        assert 1 <= w.trigger_phase <= 72
    status = host.request("get_status")
    assert status.integrity_faults == 0 and status.adc_overruns == 0
    assert host.sim.sensor.violation is None


def test_a_lost_adc_trigger_drops_that_burst_and_is_counted():
    """A conversion the ADC never made shifts the DMA's ring position by one sample: the
    burst after it is dropped (not averaged, not sent), counted in status and in every later
    waveform, and pacing is re-synchronised so the bursts after that are good again."""
    host = start()
    # 256 samples, 4 shots per waveform: the link carries every waveform (none skipped)
    host.request("set_config", **{**CFG, "n_samples": 256, "n_average": 4})
    before = host.request("get_status")
    host.request("arm", n_shots=0)
    host.collect(0.0105)
    host.sim.sensor.mcu.adc.miss_trigger_after(host.sim.t)
    waves = [m for m in host.collect(0.03) if m.name == "waveform"]
    host.request("disarm")
    after = host.request("get_status")
    assert host.sim.sensor.mcu.adc.ignored == 1
    assert after.integrity_faults - before.integrity_faults == 1
    assert after.last_error == SPEC.enums["error"]["sample_integrity"]
    assert after.triggers_skipped == before.triggers_skipped and after.adc_overruns == 0
    assert waves[-1].integrity_faults - before.integrity_faults == 1
    edges = after.triggers - before.triggers
    sent = after.shots_sent - before.shots_sent
    assert edges >= 35 and abs(sent - (edges - 1) // 4) <= 1  # only the one burst is lost
    assert [w.n_average for w in waves] == [4] * len(waves)


@pytest.mark.parametrize("fault,code", [("hse", "clock_failure"), ("pll", "clock_failure"),
                                        ("vos", "power_failure"), ("adc", "adc_failure")])
def test_a_start_up_failure_is_logged_named_and_blinked(fault, code):
    """A part that never becomes ready (the model's fault) ends every wait in bounded time:
    the board still answers, sends one error log naming the step, says so in its name, and
    blinks LD3 (PB14)."""
    host = start(faults=(fault,), seconds=0.3)
    logs = [m for m in host.collect(0.05) if m.name == "log"]
    errors = SPEC.enums["error"]
    assert any(m.code == errors[code] and m.level == SPEC.enums["log_level"]["error"]
               for m in logs), logs
    ident = host.request("identify")
    assert code in ident.board
    host.collect(2.5)
    red = [level for _, pin, level in host.sim.sensor.mcu.gpio["B"].log if pin == 14]
    assert red.count(1) >= 2  # a blink code, not a steady light
    assert host.sim.sensor.violation is None


def test_the_x_step_line_is_time_stamped_by_tim2_ch2_and_reported_as_one_burst():
    host = start()
    host.request("identify")
    sim = host.sim
    sim.write("stage", b"G1 X0 F3000\n")  # 800 steps of X from rest (X -10 at power-up)
    msgs = host.collect(1.0)
    assert sim.sensor.violation is None, str(sim.sensor.violation)
    syncs = [m for m in msgs if m.name == "motion_sync"]
    assert len(syncs) == 1 and syncs[0].edges == 800
    edges = sim.stage.planner.step_edges(0, 0.0, 10.0)
    span = (edges[-1] - edges[0]) * 240e6
    assert abs((syncs[0].last_edge - syncs[0].first_edge) - span) <= 2  # ticks


def test_the_table_step_line_is_time_stamped_by_tim2_ch3_and_reported_as_its_own_burst():
    """The turntable's STEP line on PB10 (TIM2 CH3): its burst comes with input a, X's with
    input x, each time-stamped to the tick; a waveform armed meanwhile counts the table's
    steps (sync_steps_a) and not X's."""
    host = start()
    host.request("identify")
    sim = host.sim
    host.request("set_config", **{**CFG, "n_samples": 256})
    host.request("arm", n_shots=0)
    sim.write("stage", b"G91\nG1 A45 F2700\nG4 P100\nG1 X2 F3000\n")
    msgs = host.collect(2.5)
    assert sim.sensor.violation is None, str(sim.sensor.violation)
    syncs = [m for m in msgs if m.name == "motion_sync"]
    inputs = SPEC.enums["sync_input"]
    assert [(m.input, m.edges) for m in syncs] == [(inputs["a"], 400), (inputs["x"], 160)]
    edges = sim.stage.planner.step_edges(3, 0.0, 10.0)
    assert len(edges) == 400
    span = (edges[-1] - edges[0]) * 240e6  # TIM2 started at boot: spans, not origins
    assert abs((syncs[0].last_edge - syncs[0].first_edge) - span) <= 2  # ticks
    x = sim.stage.planner.step_edges(0, 0.0, 10.0)
    assert abs((syncs[1].first_edge - syncs[0].last_edge) - (x[0] - edges[-1]) * 240e6) <= 2
    waves = [m for m in msgs if m.name == "waveform"]
    turning = [w for w in waves if syncs[0].first_edge <= w.timestamp < syncs[0].last_edge]
    assert len(turning) > 50
    assert all(w.sync_steps == 0 for w in turning)
    counts = [w.sync_steps_a for w in turning]
    assert counts == sorted(counts) and counts[-1] > 0
