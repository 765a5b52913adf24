"""The emulator's Marlin planner where it once parted from the real Marlin under simavr
(`make check-marlin`'s motion differential): the first step's delay, the hand-over between a
turntable block and an XYZ block, and the reverse pass that stops early."""

import math

import numpy as np
import pytest

from dmdsm.marlin_patch import MINIMAL_STEP_RATE, load_machine
from dmdsm.sim.boards.stage.motion import Planner

M = load_machine()
SPU = np.asarray(M.steps_per_unit, float)
X, Z, A = M.axis("X"), M.axis("Z"), M.axis("A")


def run(moves: list[tuple[list[float], float]], start: list[float]) -> tuple[Planner, list]:
    """All the moves (target mm/deg, feed mm/s) queued at once from `start`, run to the end."""
    p = Planner(M)
    p.steps = p.pos = p.to_steps(start)
    blocks = [p.line_to(0.0, p.to_steps(q), f) for q, f in moves]
    p.update(100.0)
    return p, blocks


def test_a_block_from_rest_starts_at_one_steps_average_speed_and_steps_one_period_in():
    """Marlin 2.1's minimum planner speed, sqrt(a / 2 / steps_per_mm): X from rest starts at
    sqrt(350 * 80 / 2) = 118 steps/s, and the stepper's first pulse comes one period of that
    rate after the block starts (measured on the AVR: 8.5 ms), its last at the block's end."""
    p, (b,) = run([([150, 100, 10, 0], 100.0)], [100, 100, 10, 0])
    want = math.sqrt(0.5 * M.default_acceleration * SPU[X])
    assert b.r0 == pytest.approx(want) and b.r2 == pytest.approx(want)
    e = p.step_edges(X, -1.0, 100.0) - b.t0
    assert len(e) == 50 * SPU[X]
    assert e[0] == pytest.approx(1.0 / want) and e[-1] == pytest.approx(b.duration)
    assert 8.0e-3 < e[0] < 9.0e-3 and want > 3 * MINIMAL_STEP_RATE


def test_an_xyz_block_after_the_turntable_steps_at_its_own_rate_not_the_turntables():
    """The hand-over that made `make check-marlin` fail (182 ms on the emulator against 164
    on Marlin): A decelerates to a few steps/s (8.9 steps per degree), but the XYZ block after
    it enters at the junction speed in its own steps (Z: 400 per mm), so its first step comes
    2.3 ms after A's last (Marlin under simavr: 2.29 ms), not one slow A period later."""
    p, blocks = run([([100, 100, 10, 47], 90.0), ([100.39, 100.08, 9.54, 47], 150.0)],
                    [100, 100, 10, 0])
    a_last = p.step_edges(A, -1.0, 100.0)[-1]
    z = p.step_edges(Z, -1.0, 100.0)
    assert z[0] - a_last == pytest.approx(1.0 / blocks[1].r0, rel=1e-6)
    assert 1.5e-3 < z[0] - a_last < 3.0e-3
    assert blocks[1].r0 > 10 * blocks[0].r2


def test_a_block_whose_entry_cannot_rise_ends_the_reverse_pass_as_in_marlin():
    """Marlin's reverse pass stops at the first block whose entry it cannot raise: a long X
    move after a turntable turn carrying three owed X steps enters at its own minimum speed,
    which is already its junction limit, so the turn keeps the entry it got as the newest
    block (able to stop within itself: 571 steps/s) while its exit rises to its nominal rate
    (800). Marlin under simavr: first A period 1.75 ms, last 1.25 ms; a full re-plan would
    have run it at 800 steps/s throughout (133 ms against the emulator's 114)."""
    p = Planner(M)
    p.steps = p.pos = p.to_steps([253.69, 294.90, 30.28, 0.0])
    p.line_to(0.0, p.to_steps([257.40, 294.82, 30.52, 0.0]), 200.0)  # waiting: never re-planned
    turn = p.line_to(0.0, p.to_steps([257.44, 294.82, 30.52, -10.24]), 60.0)  # 3 X, 91 A steps
    line = p.line_to(0.0, p.to_steps([313.15, 303.40, 31.40, -10.24]), 200.0)
    assert line.max_entry == pytest.approx(line.min_speed)  # its junction limit is its floor
    k = turn.n / turn.length  # steps per mm of the turn's X travel
    stop_within = math.sqrt(2 * turn.a * turn.length + turn.min_speed ** 2) * k
    assert turn.r0 == pytest.approx(stop_within, rel=1e-6) and 560 < turn.r0 < 580
    assert turn.r2 == pytest.approx(turn.r1) == pytest.approx(90 * SPU[A], rel=1e-3)
    p.update(100.0)
    period = np.diff(p.step_edges(A, -1.0, 100.0))
    assert period[0] == pytest.approx(1.75e-3, abs=0.05e-3)
    assert period[-1] == pytest.approx(1.25e-3, abs=0.02e-3)
