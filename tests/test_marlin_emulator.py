"""The Marlin emulator's fine points, where the real firmware's details show.

A line error in the middle of a burst flushes only the bytes that had arrived, so the rest of
the burst is read from mid-line (issue 20, item 11). A move of fewer than MIN_STEPS_PER_SEGMENT
steps on every axis is dropped by the planner, which keeps its own position in steps (M114's
Count), so its steps go with the next move (tests/stage/test_short_moves.py runs the same
cases on the real Marlin)."""

from dmdsm.marlin_patch import checksum
from dmdsm.sim.boards.stage.marlin import MarlinEmulator


def numbered(n, cmd, good=True):
    body = f"N{n} {cmd}"
    return f"{body}*{checksum(body) ^ (0 if good else 0x55)}\n"


def test_an_error_mid_burst_reads_the_rest_from_mid_line():
    m = MarlinEmulator()
    m.step(0.0)  # the boot banner
    burst = numbered(1, "G90") + numbered(2, "G91", good=False) + numbered(3, "G90") + \
        numbered(4, "G91")
    m.receive(burst.encode(), 0.001)
    # a line error's Resend and ok leave after its drain (40 us for the second one's)
    out = (m.step(0.002) + m.step(0.003)).decode().splitlines()
    errors = [x for x in out if x.startswith("Error:")]
    assert errors[0] == "Error:checksum mismatch, Last Line: 1"
    assert all(x == "Resend: 2" for x in out if x.startswith("Resend"))
    # 3 and 4 were not run out of order; a tail read after the drain has no number, and
    # Marlin checks no checksum on an unnumbered line (queue.cpp): it runs as it is (issue 29)
    assert [n for n, _ in m.executed if n is not None] == [1]
    tails = [cmd for n, cmd in m.executed if n is None]
    assert tails and all(f'echo:Unknown command: "{cmd}"' in out for cmd in tails)


def test_a_line_errors_ok_leaves_after_its_drain_so_the_resend_is_never_lost():
    """A line error's drain drops what arrives while the error goes out; its Resend and ok
    come after the drain, so a host's resend sent on that ok is read whole - however soon
    the emulator is stepped (a loaded machine once stepped it within the drain, the resend
    was dropped and the host waited in vain)."""
    m = MarlinEmulator()
    m.step(0.0)
    m.receive(numbered(1, "G90").encode() + numbered(2, "M117 " + "x" * 120).encode(), 0.001)
    t, out = 0.001, []
    while not any(x.startswith("ok") for x in out[1:]):
        t += 1e-6  # stepped every microsecond of simulated time
        out += m.step(t).decode().splitlines()
    assert out[-3].startswith("Error:No Checksum") and out[-2:] == ["Resend: 2", "ok"]
    m.receive(numbered(2, "G90").encode(), t)  # at once, as soon as the ok came
    out = m.step(t + 0.001).decode().splitlines()
    assert out[-1].startswith("ok N2") and [n for n, _ in m.executed] == [1, 2]


def test_a_quiet_line_after_the_error_is_read_whole():
    m = MarlinEmulator()
    m.step(0.0)
    m.receive(numbered(1, "G90").encode() + numbered(2, "G91", good=False).encode(), 0.001)
    m.step(0.002)
    m.receive(numbered(2, "G91").encode(), 0.003)  # the resend, after the flush
    out = m.step(0.004).decode().splitlines()
    assert out[-1].startswith("ok N2") and [n for n, _ in m.executed] == [1, 2]



class Host:
    """Numbered lines to an emulator, each once the last one's ok came, in simulated time."""

    def __init__(self) -> None:
        self.m = MarlinEmulator()
        self.m.step(0.0)  # the boot banner
        self.n, self.t = 0, 0.0

    def send(self, cmd: str) -> list[str]:
        """The replies up to the line's ok (busy lines left out)."""
        self.n += 1
        self.m.receive(numbered(self.n, cmd).encode(), self.t)
        got: list[str] = []
        deadline = self.t + 60.0
        while not any(x.startswith(f"ok N{self.n} ") for x in got):
            self.t += 0.01
            assert self.t < deadline, (cmd, got)
            got += [x for x in self.m.step(self.t).decode().splitlines()
                    if x != "echo:busy: processing"]
        return got

    def where(self) -> tuple[str, dict[str, int]]:
        """M114: the logical part and the counts."""
        (report, _) = self.send("M114")
        pos, _, cnt = report.partition(" Count ")
        return pos, {k: int(v) for k, v in (w.split(":") for w in cnt.split())}

    def steps(self, axis: int, since: float) -> int:
        """STEP pulses of an axis since a time (s)."""
        return len(self.m.step_edges(axis, since, self.t))


def at_x100() -> Host:
    """An emulator standing at X100 (count 8000), idle."""
    h = Host()
    h.send("G1 X100 F6000")
    h.send("M400")
    assert h.where()[1]["X"] == 8000
    return h


def test_a_move_under_six_steps_takes_no_step_and_keeps_the_planners_count():
    """Marlin drops a block of fewer than MIN_STEPS_PER_SEGMENT (6) steps on every axis and
    keeps its planner position: from X100, X100.04 (3 steps) takes none; M114 shows the
    commanded X, and the count of the planner, which did not move."""
    h = at_x100()
    t = h.t
    h.send("G1 X100.04")
    h.send("M400")
    pos, count = h.where()
    assert pos.startswith("X:100.04 ") and count["X"] == 8000
    assert h.steps(0, t) == 0 and h.m.position()[0] == 110.0  # raw: X100 is raw 110


def test_the_dropped_steps_go_with_the_next_move():
    """After the dropped X100.04, an A turn carries the 3 X steps (Bresenham along A's 77);
    a 6-step move is kept; and every later move counts from the planner's position."""
    h = at_x100()
    h.send("G1 X100.04")
    t = h.t
    h.send("G1 A-8.71 F3600")
    h.send("M400")
    assert (h.steps(0, t), h.steps(3, t)) == (3, 77)
    assert h.where()[1]["X"] == 8003 and h.m.position()[0] == 110.0 + 3 / 80
    t = h.t
    h.send("G1 X100.115")  # 8009.2: 6 steps from 8003, kept
    h.send("M400")
    assert h.steps(0, t) == 6 and h.where()[1]["X"] == 8009


def test_a_dropped_move_at_the_end_is_never_taken():
    h = at_x100()
    t = h.t
    for x in ("100.03", "100.05", "100.06"):  # 2, 4, 5 steps from the planner's 8000
        h.send(f"G1 X{x}")
    h.send("M400")
    assert h.steps(0, t) == 0 and h.where()[1]["X"] == 8000
    t = h.t
    h.send("G1 X100.08")  # 6 steps: all of them now
    h.send("M400")
    assert h.steps(0, t) == 6 and h.where()[1]["X"] == 8006


def test_g92_after_a_dropped_move_shifts_the_workspace_and_leaves_the_steps_owed():
    """G92 (with workspace offsets, as the build has them) sets the logical position only:
    the planner keeps its count, its report prints the steppers' count, M114 D shows the
    owed steps as the difference, and the next move still counts from the planner."""
    h = at_x100()
    h.send("G1 X100.04")
    g92 = h.send("G92 X50")
    assert g92[0].startswith("X:50.00 ") and "Count X:8000 " in g92[0]
    pos, count = h.where()
    assert pos.startswith("X:50.00 ") and count["X"] == 8000
    detail = h.send("M114 D")
    assert any(x.startswith("Stepper: X:8000 ") for x in detail)
    assert any(x.startswith("Diff:    X:-0.040") for x in detail), detail
    t = h.t
    h.send("G1 X50.02")  # native 100.06: 5 steps from 8000, still dropped
    h.send("M400")
    assert h.steps(0, t) == 0 and h.where()[1]["X"] == 8000
    h.send("G1 X50.04")  # native 100.08: 6 steps
    h.send("M400")
    assert h.steps(0, t) == 6 and h.where()[1]["X"] == 8006


def test_a_quick_stop_takes_the_planners_position_from_the_steppers():
    """M410 mid-move (quickstop_stepper: set_current_from_steppers, sync_plan_position): the
    planner's count is where the steppers stopped, not the dropped move's target, so a move
    3 steps on from there is dropped too."""
    h = at_x100()
    h.send("G1 X200 F600")
    h.m.receive(b"M410\n", h.t + 1.0)
    h.t += 1.0
    h.send("G4 P0")
    pos, count = h.where()
    stopped = count["X"]
    assert 8000 < stopped < 16000 and abs(float(pos.split()[0][2:]) - stopped / 80) < 0.006
    t = h.t
    h.send(f"G1 X{(stopped + 3.2) / 80:.4f}")
    h.send("M400")
    assert h.steps(0, t) == 0 and h.where()[1]["X"] == stopped


def test_homing_another_axis_counts_the_owed_steps_without_taking_them():
    """G28 X re-syncs the planner's position (and the counts) of every axis from the
    commanded one (sync_plan_position): A0.5 (4 steps, dropped) is then counted, never
    taken, and the table stays 4 steps short of the counts from there on."""
    h = at_x100()
    h.send("G1 A0.5")
    assert "Count X:-800 " in h.send("G28 X")[0] and h.where()[1]["A"] == 4
    assert h.m.position()[3] == 0.0  # the table did not turn
    t = h.t
    h.send("G1 A0")  # 4 steps back from the planner's 4: dropped again
    h.send("M400")
    assert h.steps(3, t) == 0 and h.where()[1]["A"] == 4
    h.send("G1 A2")  # 17.8 -> 18: 14 steps from 4
    h.send("M400")
    assert h.steps(3, t) == 14 and h.where()[1]["A"] == 18
    assert h.m.position()[3] == 14 / h.m.planner.spu[3]
    assert h.send("M114 R")[0].startswith("X:-10.00 Y:0.00 Z:0.00 A:2.02 ")  # from counts
