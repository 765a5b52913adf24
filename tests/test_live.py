"""`live()` against the emulator: one record per waveform in order, distances and host stamps
against the emulator's truth, every loss passed on, the board disarmed however it ends."""

import itertools
from contextlib import closing

import numpy as np
import pytest
from stamp_helpers import child_emulator

from dmdsm.host.links.sensor import SensorClient
from dmdsm.host.links.stage import StageClient
from dmdsm.host.ranging.procedure import calibrate_range
from dmdsm.host.robotics.live import LiveRecord, live
from dmdsm.protocol import load_spec

IDLE = load_spec().enums["state"]["idle"]


def in_front_of_the_block(child) -> tuple:
    """Home, stand 7 mm in front of the aluminium block; (a ranging calibration there, the
    true distance there in mm, read from the emulator)."""
    with StageClient(child.stage) as st:
        st.home()
        st.move(x=235, y=266, z=20, wait=True)
        st.wait()
        truth_mm = child.distance_mm()
        with SensorClient(child.sensor) as sc:
            setup, _ = calibrate_range(st, sc, {"X": 235, "Y": 266, "Z": 20}, truth_mm,
                                       steps=6, step_mm=1.0, shots=2, fit_c=False, lateral=5)
        st.move(x=235, y=266, z=20, wait=True)
        st.wait()
    return setup, truth_mm


@pytest.mark.realtime
def test_every_waveform_once_in_order_distances_and_stamps_against_the_truth():
    """The emulator in its own process, as `dmdsm sim` runs it: in the test's process its
    loop shared the interpreter lock with the ranging, and on a loaded machine (CI) it read
    the board's clock ms late, off its own pacing (the truth here): RMS z 11.5."""
    with child_emulator(seed=3) as (port, child):
        setup, truth_mm = in_front_of_the_block(child)
        sc = SensorClient(port)
        sc.configure(n_samples=1024, n_average=4)
        recs: list[LiveRecord] = []
        backlog = []
        lag0 = child.truth().receives
        with closing(live(sc, setup)) as g:
            for r in itertools.islice(g, 250):
                recs.append(r)
                backlog.append(len(sc.stream))
        assert sc.stream is None and sc.status()["state"] == IDLE  # closed: disarmed
        # the truth's lag is the one while the board streams (from the arm on: after
        # get_config, 16 clock exchanges and get_status)
        times = child.truth(lag0 + 18)
        sc.close()
    # one record per waveform, in order, none lost on the link or on the board
    assert [r.seq for r in recs] == list(range(250))
    assert all(r.lost_before == 0 and r.device_lost == 0 for r in recs)
    assert max(backlog) < 50  # taken as they come: the client's list never grows
    # distances: the block's face where the truth puts it, within the sigma reported
    for m in ("oa", "us"):
        d = np.array([r.distance_mm[m] for r in recs], dtype=float)
        sd = np.array([r.distance_std_mm[m] for r in recs], dtype=float)
        assert np.isfinite(d).mean() > 0.95, m
        z = (d - truth_mm) / sd
        assert np.sqrt(np.nanmean(z ** 2)) < 3.0, (m, np.nanmean(d), truth_mm, np.nanmean(sd))
        snr = np.array([r.snr_db[m] for r in recs], dtype=float)
        assert np.nanmedian(snr) > 10
    # stamps: the laser edge on the host's clock, against the emulator's truth, with the
    # uncertainty reported holding. The truth is known to within the emulator's lag
    # scatter (ChildTimes.lag_sigma_s: 0.66 ms on an idle machine, its loop's steps; 8-140
    # ms with two busy loops beside it), and the host's sigma grows with the scatter it
    # sees in the exchanges (the link-limit test below checks the sigma more closely)
    err = np.array([r.host_s for r in recs]) - times.laser_s([r.device_ticks for r in recs])
    std = np.array([r.host_std_s for r in recs])
    what = (err.mean(), err.std(), np.median(std), std.max(), times.lag_sigma_s)
    assert np.all(std > 0) and np.all(std < 5e-3 + 4 * times.lag_sigma_s), what
    # no larger than the sigma reported and the truth's own allow; the sigma not inflated
    rms_z = float(np.sqrt(np.mean(err ** 2 / (std ** 2 + times.lag_sigma_s ** 2))))
    assert rms_z < 2.5, (rms_z, *what)
    assert float(np.sqrt(np.mean((err / std) ** 2))) > 0.3, what
    # stamps never go back, whatever the refits did
    assert np.all(np.diff([r.host_s for r in recs]) > 0)
    # the epoch form differs from the monotonic one by one constant
    off = np.array([r.unix_s - r.host_s for r in recs])
    assert np.ptp(off) < 1e-6
    # each record was taken in after its frame left the board
    sent = np.array([times.sent[r.device_ticks] for r in recs])
    assert np.all(np.array([r.received_s for r in recs]) >= sent)


def test_ctrl_c_and_close_disarm_the_board_and_the_next_stream_starts_from_zero(emulator):
    emu = emulator(speed=2.0)
    with SensorClient(emu.sensor) as sc:
        sc.configure(n_samples=256, n_average=1)
        g = live(sc)  # no ranging: records with samples and stamps only
        first = next(g)
        assert first.seq == 0 and first.distance_mm == {} and first.samples.size == 256
        with pytest.raises(KeyboardInterrupt):
            g.throw(KeyboardInterrupt)  # Ctrl-C while the generator waits for waveforms
        assert sc.stream is None and sc.status()["state"] == IDLE
        with closing(live(sc)) as g2:
            assert [r.seq for r in itertools.islice(g2, 5)] == list(range(5))
        assert sc.status()["state"] == IDLE
    # a port name: live() opens the client and closes it with the generator
    with closing(live(emu.sensor)) as g3:
        assert next(g3).seq == 0
    with SensorClient(emu.sensor) as sc:
        assert not sc.took_over and sc.status()["state"] == IDLE


def test_losses_on_the_link_are_passed_on_as_gaps(emulator):
    emu = emulator(speed=2.0, faults="sensor.drop=2e-5", seed=7)
    with SensorClient(emu.sensor) as sc:
        sc.configure(n_samples=512, n_average=1)
        with closing(live(sc)) as g:
            recs = list(itertools.islice(g, 400))
    seqs = np.array([r.seq for r in recs])
    gaps = np.diff(seqs) - 1
    assert np.all(np.diff(seqs) > 0)
    assert sum(r.lost_before for r in recs) == gaps.sum() + seqs[0] > 0
    assert all(r.lost_before == g for r, g in zip(recs[1:], gaps))
    # triggers the board skipped while the link was busy are counted, not lost
    assert recs[-1].counters["triggers_skipped"] > 0 and recs[-1].device_lost == 0


def test_with_a_model_every_ranged_record_names_the_material(emulator, tmp_path):
    from collections import Counter

    from dmdsm.host.commands.cli import main
    from dmdsm.sim.data.dataset import make_database, true_setup

    make_database(tmp_path / "db", points=24, seed=1)
    model = tmp_path / "m.model"
    assert main(["classify", "train", "--db", str(tmp_path / "db"), "-o", str(model),
                 "--json"]) == 0
    emu = emulator(speed=2.0, seed=4)
    with StageClient(emu.stage) as st:
        st.home()
        st.move(x=235, y=266, z=20, wait=True)
        st.wait()
    truth = emu.sim.truth()["material"]
    with SensorClient(emu.sensor) as sc:
        sc.configure(n_samples=1024, n_average=16)
        with closing(live(sc, true_setup(emu.sim.model), model)) as g:
            recs = list(itertools.islice(g, 40))
    named = [r for r in recs if r.material is not None]
    assert len(named) >= 0.9 * len(recs)
    for r in named:
        assert r.material in r.probabilities
        assert sum(r.probabilities.values()) == pytest.approx(1.0, abs=1e-4)
        assert r.probabilities[r.material] == max(r.probabilities.values())
    assert Counter(r.material for r in named).most_common(1)[0][0] == truth


@pytest.mark.realtime
def test_stamps_at_the_link_limit_against_the_truth_within_their_sigma():
    """At the link limit (1024 samples, no averaging) the wire is always busy and nearly
    every clock_sync reply waits behind a 10.4 ms waveform frame: the stamps still land
    within a fraction of a millisecond of the emulator's truth (its own process, as `dmdsm
    sim`), and the sigma reported is their scale. The earlier fit (midpoints of the quickest
    exchanges) had a median sigma of 0.61 ms, an error std of 1.09 ms, RMS z 0.61 (and once
    the board kept the wire always busy, no quick exchange at all: errors of 17 ms)."""
    with child_emulator(seed=3) as (port, child):
        sc = SensorClient(port)
        sc.configure(n_samples=1024, n_average=1)
        recs: list[LiveRecord] = []
        with closing(live(sc)) as g:
            for r in g:
                recs.append(r)
                if r.received_s - recs[0].received_s > 20.0:  # ~1900 records; 200 exchanges
                    break
        sc.close()
        times = child.truth()
    err = np.array([r.host_s for r in recs]) - times.laser_s([r.device_ticks for r in recs])
    std = np.array([r.host_std_s for r in recs])
    rms_z = float(np.sqrt(np.mean((err / std) ** 2)))
    what = (rms_z, err.mean() * 1e3, err.std() * 1e3, np.median(std) * 1e3, len(recs))
    assert len(recs) > 1000 and np.all(std > 0), what
    assert np.all(np.diff([r.host_s for r in recs]) > 0), what  # a refit never steps back
    # 0.13-0.2 ms on an idle machine, 0.46 ms with two benchmarks beside it (the emulator's
    # loop, the truth here, then reads its clock late too); a stamp held on a drifting
    # floor gave 1.6 ms, the earlier fit 1.1 ms (17 ms)
    assert np.sqrt(np.mean(err ** 2)) < 0.8e-3, what
    assert np.median(std) < 0.3e-3, what               # was 0.61 ms
    # one run's errors are strongly correlated (one line, refitted slowly): over runs of
    # 20-120 s RMS z came out 0.7-1.4, pooled over runs ~1.0, so the band is wide
    assert 0.5 < rms_z < 2.2, what


def test_a_clock_window_where_every_reply_waited_stamps_by_the_request_s_send_time():
    """A stream at the link's limit: every reply waits up to a frame's time (10.4 ms) behind
    a waveform frame, but the board stamps the request when it arrives, shortly after it
    was sent: the fit through the send times stamps within a fraction of a millisecond,
    leaves out a stalled exchange, and leaves the idle exchanges made before the arm once
    the stream has its own."""
    from dmdsm.host.robotics.live import clock_fit

    rng = np.random.default_rng(5)
    hz, off = 240e6, 5e6

    def exchanges(t0: np.ndarray, wait: np.ndarray) -> list[tuple[float, float, float]]:
        up = 1e-4 + rng.normal(0, 3e-5, t0.size)  # the request's way to the board
        rtt = up + wait + 1.5e-4 + rng.uniform(0, 5e-5, t0.size)  # the reply's way back
        ticks = (t0 + up) * hz + off
        return list(zip(t0 + rtt / 2, ticks, rtt))

    before = exchanges(90.0 + np.arange(16) * 0.025, np.zeros(16))
    idle = float(np.median([e[2] for e in before]))
    during = exchanges(100.0 + np.arange(400) * 0.1, rng.uniform(0, 10.4e-3, 400))
    during[17] = (during[17][0], during[17][1] - 6e-3 * hz, during[17][2])  # a stall
    fit = clock_fit(before, during, idle)
    assert not fit.before_arm and 390 <= fit.sync.n < 400  # the stall left out
    t, sd = fit.stamp(off + 140.0 * hz)
    assert abs(t - 140.0) < 1e-4 and 1e-5 < sd < 1e-4
    # before the stream has MIN_FIT_EXCHANGES of its own, the idle ones carry the line
    early = clock_fit(before, during[:3], idle)
    assert early.before_arm and early.sync.n == 19
