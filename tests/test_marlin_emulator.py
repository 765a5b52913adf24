"""The Marlin emulator's byte-level behaviour where the real firmware's timing shows: a line
error in the middle of a burst flushes only the bytes that had arrived, so the rest of the
burst is read from mid-line (issue 20, item 11)."""

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
    out = m.step(0.002).decode().splitlines()
    errors = [x for x in out if x.startswith("Error:")]
    assert errors[0] == "Error:checksum mismatch, Last Line: 1"
    assert all(x == "Resend: 2" for x in out if x.startswith("Resend"))
    # 3 and 4 were not run out of order; a tail read after the drain has no number, and
    # Marlin checks no checksum on an unnumbered line (queue.cpp): it runs as it is (issue 29)
    assert [n for n, _ in m.executed if n is not None] == [1]
    tails = [cmd for n, cmd in m.executed if n is None]
    assert tails and all(f'echo:Unknown command: "{cmd}"' in out for cmd in tails)


def test_a_quiet_line_after_the_error_is_read_whole():
    m = MarlinEmulator()
    m.step(0.0)
    m.receive(numbered(1, "G90").encode() + numbered(2, "G91", good=False).encode(), 0.001)
    m.step(0.002)
    m.receive(numbered(2, "G91").encode(), 0.003)  # the resend, after the flush
    out = m.step(0.004).decode().splitlines()
    assert out[-1].startswith("ok N2") and [n for n, _ in m.executed] == [1, 2]
