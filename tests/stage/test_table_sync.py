"""The table's STEP line on the sensor's second sync input, against the stage under test (the
Marlin emulator in `make test`, the real Marlin under simavr in `make check-marlin`): one G1
that turns the table while X and Z move is one burst of table steps, and the table steps
counted before each shot place every axis of that move (Marlin steps them in proportion)."""

import os

import numpy as np
from fly_scan_helpers import TICK_HZ

from dmdsm.host.links.sensor import SPEC, SensorClient
from dmdsm.host.links.stage import StageClient
from dmdsm.host.scan.sweep import counted_steps, place_on_move

ELF = os.environ.get("DMDSM_STAGE_FIRMWARE", "")
SPEED = 1.0 if ELF else 4.0  # simavr runs Marlin at about twice real time at most
N_AVG = 8
TURN = np.array([2.0, 0.0, 1.5, 300.0])  # X, Y, Z (mm), A (deg): one G1, the table fastest


def test_one_helical_move_is_placed_at_every_shot_by_the_counted_table_steps(emulator):
    emu = emulator(speed=SPEED, scene="aluminium_block", seed=5, stage_firmware=ELF)
    sim = emu.sim
    steps = [{}]  # the steppers' logical positions (mm, deg) at each shot's tick, recorded
    pose = sim.pose
    origin = np.array([*sim.limits.min_pos[:3], 0.0])  # the stage counts from its endstops

    def recording(t):
        steps[0][round(t * TICK_HZ)] = sim.stage.position_at(t) + origin
        return pose(t)

    sim.sensor.pose = recording
    spu = np.array(sim.limits.steps_per_unit, float)
    with StageClient(emu.stage) as st, SensorClient(emu.sensor) as sc:
        st.home()
        start = np.array([200.0, 300.0, 20.0, 10.0])
        st.move(*start, feed_mm_min=6000)
        st.wait()
        sc.configure(n_samples=256, n_average=N_AVG)
        armed = sc.clock_exchanges(1)[0][1]  # device ticks: the bursts after it are the turn's
        sc.stream_start()
        # F is the linear axes' speed: 2.5 mm in ~4 s turns the table at 75 deg/s
        st.move(*(start + TURN), feed_mm_min=37.5)
        st.wait()
        sc.clock_exchanges(4, 0.01)  # past the table's sync_quiet_ms
        waves, _ = sc.stream_stop()
        bursts = [m for m in sc.motion_syncs if m.first_edge > armed]
    a_input = SPEC.enums["sync_input"]["a"]
    turn = [(m.first_edge, m.last_edge, m.edges) for m in bursts if m.input == a_input]
    n = np.round(TURN * spu).astype(int)
    # the table's steps, all reported (the move's slow start may split them into bursts)
    assert sum(e for _, _, e in turn) == n[3], turn
    period = TICK_HZ / 1000.0  # the laser at 1 kHz
    done = counted_steps([w.timestamp for w in waves], [w.sync_steps_a for w in waves],
                         N_AVG, period, turn, SPEC.sync_quiet_ms * 1e-3 * TICK_HZ)
    moving = (done > 0) & (done < n[3])
    assert moving.sum() > 200 and np.isfinite(done).mean() > 0.95
    placed = place_on_move(start, TURN, done[moving], n[3])
    truth = [np.mean([steps[0][int(w.timestamp) + k * round(period)] for k in range(N_AVG)],
                     axis=0) for w, m in zip(waves, moving) if m]
    # where the steppers stood before the move: the start as counted from the endstops
    # (the AVR Marlin's homing leaves X a step past its switch)
    rest = np.array(list(steps[0].values())[:N_AVG]).mean(axis=0)
    assert np.all(np.abs(rest - start) * spu <= 1.0 + 1e-9), (rest - start) * spu
    err = placed - (np.array(truth) - (rest - start))
    signed = np.array(err) * spu  # in steps of each axis
    err = np.abs(signed)
    # every axis within a step of where it was (Bresenham keeps each within one step of
    # its share of the counted one's): 12.5 um of X, 2.5 of Z, 0.11 deg of the table
    assert err[:, [0, 2, 3]].max() <= 1.0, err.max(axis=0)
    print(f"\nhelical move placed by the table's counted steps: X {err[:, 0].max():.2f}, "
          f"Z {err[:, 2].max():.2f}, A {err[:, 3].max():.2f} steps at worst; mean X "
          f"{signed[:, 0].mean():+.2f}, Z {signed[:, 2].mean():+.2f}")
