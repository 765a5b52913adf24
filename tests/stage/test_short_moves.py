"""Moves too short for Marlin's planner, on the stage under test (the emulator, or the real
Marlin under simavr with DMDSM_STAGE_FIRMWARE, as `make check-marlin` runs it), read from the
STEP pins and M114: a block of fewer than MIN_STEPS_PER_SEGMENT (6) steps on every axis is
dropped, the planner keeps its position, and the steps go with the next move."""


import numpy as np
from pin_bench import PinBench, bench_fixture

from dmdsm.marlin_patch import load_machine

SPU = np.asarray(load_machine().steps_per_unit, float)


class Bench(PinBench):
    """The stage under test (pin_bench.PinBench) with this module's moves."""

    def where(self) -> tuple[str, dict[str, int]]:
        """M114: its logical part and its counts."""
        report = self.send("M114")[0]
        pos, _, cnt = report.partition(" Count ")
        return pos, {k: int(v) for k, v in (w.split(":") for w in cnt.split())}

    def moves(self, *cmds: str) -> list[int]:
        """The commands, then M400: the STEP pulses each axis gave meanwhile."""
        t0 = self.stage.sim.t
        for cmd in cmds:
            self.send(cmd)
        self.send("M400")
        for _ in range(4):  # the last step is before the M400's ok
            self.stage.tick()
        board = self.stage.sim.stage
        return [len(board.step_edges(a, t0, self.stage.sim.t)) for a in range(len(SPU))]

    def at_x100(self) -> None:
        """Stand at X100 Y100 Z10 A0 (counts X8000), idle, the planner's count the
        steppers'."""
        self.moves("G1 X100 Y100 Z10 A0 F6000")
        assert self.where()[1] == {"X": 8000, "Y": 10000, "Z": 4000, "A": 0}


bench = bench_fixture(Bench)


def test_a_move_under_six_steps_takes_no_step_and_m114_counts_the_planner(bench):
    """From X100, X100.04 (3 steps): no step; M114 shows the commanded X and the planner's
    count, still 8000."""
    bench.at_x100()
    assert bench.moves("G1 X100.04") == [0, 0, 0, 0]
    pos, count = bench.where()
    assert pos.startswith("X:100.04 ") and count["X"] == 8000


def test_the_dropped_steps_go_with_the_next_move(bench):
    """A turn of A after the dropped X100.04 takes the 3 X steps along with its 77; then a
    6-step move is kept, counted from the planner's 8003."""
    bench.at_x100()
    assert bench.moves("G1 X100.04", "G1 A-8.71 F3600") == [3, 0, 0, 77]
    assert bench.where()[1]["X"] == 8003
    assert bench.moves("G1 X100.115") == [6, 0, 0, 0]  # 8009.2 - 8003
    assert bench.where()[1]["X"] == 8009


def test_short_moves_in_a_row_count_from_the_planner_not_the_last_command(bench):
    """2, 4 and 5 steps from the planner's 8000 (each under 6 from it): none is taken, nor
    ever will be; 6 from it is, with all 6 steps."""
    bench.at_x100()
    assert bench.moves("G1 X100.03", "G1 X100.05", "G1 X100.06") == [0, 0, 0, 0]
    assert bench.where()[1]["X"] == 8000
    assert bench.moves("G1 X100.08") == [6, 0, 0, 0]
    assert bench.where()[1]["X"] == 8006


def test_g92_after_a_dropped_move_leaves_the_planner_and_the_owed_steps(bench):
    """G92 shifts the workspace only (the build has workspace offsets): its report and
    M114 keep the counts, M114 D shows the owed steps as the difference, and a move is
    still counted from the planner's position, not from the commanded one."""
    bench.at_x100()
    bench.send("G1 X100.04")
    g92 = bench.send("G92 X50")
    assert g92[0].startswith("X:50.00 ") and "Count X:8000 " in g92[0]
    pos, count = bench.where()
    assert pos.startswith("X:50.00 ") and count["X"] == 8000
    detail = bench.send("M114 D")
    assert any(x.startswith("Stepper: X:8000 ") for x in detail), detail
    assert any(x.startswith("Diff:    X:-0.040") for x in detail), detail
    assert bench.moves("G1 X50.02") == [0, 0, 0, 0]  # native 100.06: 5 steps from 8000
    assert bench.moves("G1 X50.04") == [6, 0, 0, 0]  # native 100.08: 6
    assert bench.where()[1]["X"] == 8006
    bench.send("G92 X100.08")  # back to the logical frame of the other tests


def test_homing_another_axis_counts_the_owed_steps_without_taking_them(bench):
    """G28 X re-syncs every axis's planner position and count from the commanded position
    (sync_plan_position): the 4 steps of a dropped A0.5 are counted, never taken; A0 is then
    4 steps from the planner's position, dropped too, and A2 takes 14, not 18."""
    bench.at_x100()
    bench.send("G1 A0.5")
    home = bench.send("G28 X")
    assert "Count X:-800 Y:10000 Z:4000 A:4" in home[0], home
    assert bench.where()[1]["A"] == 4
    assert bench.moves("G1 A0") == [0, 0, 0, 0]
    assert bench.where()[1]["A"] == 4
    assert bench.moves("G1 A2") == [0, 0, 0, 14]
    assert bench.where()[1]["A"] == 18
    bench.moves("G1 A0")  # the counts back to 0, the table 4 steps short of it
