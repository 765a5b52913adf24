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
from dmdsm.marlin_patch.settings import load_settings
from dmdsm.sim.boards.stage.avr_lockstep import F_CPU_HZ

ELF = os.environ.get("DMDSM_STAGE_FIRMWARE", "")
SPEED = 1.0 if ELF else 4.0  # simavr runs Marlin at about twice real time at most
N_AVG = 8
TURN = np.array([2.0, 0.0, 1.5, 300.0])  # X, Y, Z (mm), A (deg): one G1, the table fastest
# the AVR Marlin polls its endstops in the temperature ISR (F_CPU / 16384, 977 Hz), so the
# slow re-bump of homing runs past its switch by up to one poll period of steps (and one
# more before the stepper ISR drops the move) and calls that point 0
ENDSTOP_POLL_HZ = F_CPU_HZ / 0x4000


def homing_overshoot_steps(limits) -> np.ndarray:
    """Most steps each axis (X, Y, Z, A) may stop past its switch after G28: the re-bump's
    speed (homing feedrate / HOMING_BUMP_DIVISOR) over one endstop poll, plus one."""
    (divisor,) = [e["value"] for e in load_settings()["edit"]
                  if e["name"] == "HOMING_BUMP_DIVISOR"]
    divisor = np.array(divisor.strip("{} ").split(","), float)
    rate = np.array(limits.homing_feedrate_mm_m, float) / 60.0 / divisor  # mm/s (A: deg/s)
    return np.ceil(rate * np.array(limits.steps_per_unit, float) / ENDSTOP_POLL_HZ) + 1


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
    # (the AVR Marlin's homing stops X, Y, Z up to a few steps past their switches, which
    # then read 0; A has no switch and 10 deg is 88.9 of its steps)
    rest = np.array(list(steps[0].values())[:N_AVG]).mean(axis=0)
    within = np.maximum(homing_overshoot_steps(sim.limits), 1.0)
    within[3] = 1.0  # A is never homed: only its 10 deg rounded to steps
    assert np.all(np.abs(rest - start) * spu <= within + 1e-9), ((rest - start) * spu, within)
    err = placed - (np.array(truth) - (rest - start))
    signed = np.array(err) * spu  # in steps of each axis
    err = np.abs(signed)
    # every axis within a step of where it was (Bresenham keeps each within one step of
    # its share of the counted one's): 12.5 um of X, 2.5 of Z, 0.11 deg of the table
    assert err[:, [0, 2, 3]].max() <= 1.0, err.max(axis=0)
    print(f"\nhelical move placed by the table's counted steps: X {err[:, 0].max():.2f}, "
          f"Z {err[:, 2].max():.2f}, A {err[:, 3].max():.2f} steps at worst; mean X "
          f"{signed[:, 0].mean():+.2f}, Z {signed[:, 2].mean():+.2f}")
