"""The board's own time for a link's timeouts: an emulator serving a port publishes its
board's clock, so the host gives up on a reply only once the board, too, had that long.

A real board keeps wall time, and there a timeout is plain wall time. An emulated board (the
NUCLEO firmware rehosted on unicorn, Marlin under simavr) runs as fast as the CPU lets it:
on a loaded machine 1 s of the board's time took 10-100 s of the wall, and a 0.5 s reply
timeout fired while the reply was still being computed. The emulator therefore writes the
board's seconds into a small file named after the port's real path (`<runtime dir>/
dmdsm-<uid>/clock-<hash>`, beside the stage's stop socket); a `Deadline` has passed when
its time has gone by on the host's clock and on the board's. Nothing is published for a real
board, so there both clocks are the wall's.

File layout (little-endian, 32 bytes): u32 writer pid, u32 0, f64 board seconds, f64 the same
again (a reader takes a value only when both copies agree: no torn read), f64 0.
"""

from __future__ import annotations

import mmap
import os
import struct
import time
from pathlib import Path

from .stage_control import port_key, state_dir

LAYOUT = struct.Struct("<II3d")
POLL_S = 0.05  # how often a wait that is over on the wall looks at the board's clock again


def clock_path(port: str) -> Path:
    """Where the emulator serving `port` publishes its board's clock."""
    return state_dir() / f"clock-{port_key(port)}"


class ClockPublisher:
    """The emulator's side: board seconds for one port, written on every step."""

    def __init__(self, port: str) -> None:
        self.path = clock_path(port)
        tmp = self.path.with_name(self.path.name + f".{os.getpid()}.tmp")
        tmp.write_bytes(LAYOUT.pack(os.getpid(), 0, 0.0, 0.0, 0.0))
        tmp.replace(self.path)
        self._file = open(self.path, "r+b")  # noqa: SIM115 (held for the mapping's life)
        self._map = mmap.mmap(self._file.fileno(), LAYOUT.size)

    def publish(self, board_s: float) -> None:
        """Write the board's time (s)."""
        struct.pack_into("<2d", self._map, 8, board_s, board_s)

    def close(self) -> None:
        """Unmap and remove the file (a reader falls back to the wall clock)."""
        try:
            self._map.close()
            self._file.close()
        finally:
            self.path.unlink(missing_ok=True)


class BoardClock:
    """The host's side: the board's seconds on `port`, or None for a board that keeps wall
    time (no emulator publishes one, or the one that did has exited)."""

    def __init__(self, port: str) -> None:
        self._map: mmap.mmap | None = None
        self._pid = 0
        try:
            with open(clock_path(port), "rb") as f:
                self._map = mmap.mmap(f.fileno(), LAYOUT.size, access=mmap.ACCESS_READ)
            self._pid = LAYOUT.unpack_from(self._map)[0]
        except (OSError, ValueError, struct.error):
            self._map = None

    def now(self) -> float | None:
        """Board seconds now, or None when the board keeps wall time."""
        if self._map is None:
            return None
        try:
            os.kill(self._pid, 0)
        except ProcessLookupError:  # the emulator is gone: nothing is slower than the wall
            self._map = None
            return None
        except PermissionError:
            pass
        for _ in range(100):
            a, b = struct.unpack_from("<2d", self._map, 8)
            if a == b:
                return a
        return None


class Deadline:
    """`timeout_s` from now on the host's clock and on the board's; passed when both are."""

    def __init__(self, timeout_s: float, clock: BoardClock | None = None) -> None:
        self.timeout_s = timeout_s
        self.wall_end = time.monotonic() + timeout_s
        self.clock = clock
        start = clock.now() if clock is not None else None
        self.board_end = None if start is None else start + timeout_s

    def left(self) -> float:
        """Wall seconds to wait before asking again; 0 once the deadline has passed."""
        wall_left = self.wall_end - time.monotonic()
        if wall_left > 0:
            return wall_left
        if self.board_end is None or self.clock is None:
            return 0.0
        now = self.clock.now()
        if now is None or now >= self.board_end:
            return 0.0
        return min(POLL_S, self.board_end - now)

    def passed(self) -> bool:
        """True once timeout_s has gone by on both clocks."""
        return self.left() <= 0.0
