"""Stage client for the patched Marlin: numbered lines, resends, ok counting, busy, safety.

Every line goes out as `N<n> <cmd>*<checksum>` and stays in the history until its `ok N<n>`
(ADVANCED_OK) arrives. `Resend: r` sends r and everything after it again; repeated requests
for the same r are ignored until r has been acknowledged (the lines already on the wire
produce them). Marlin silently drops a line number it has already seen, so after a timeout
the client never re-sends blindly: it probes with the next line number (M114, harmless, and
its `ok N` carries the number, where M105's `ok T:0` carries none), and Marlin's answer (an
`ok N`, or a Resend) tells which lines were really executed. Text printed before an `ok N`
belongs to the lines that ok acknowledges, so a lost ok loses no reply. A plain `ok` (an
unnumbered line's, or one Marlin adds after an error) never acknowledges a numbered line.

A stop (M410, through Marlin's emergency parser) drops the planned moves at once, but the lines
Marlin had not read yet run after its 1 s clean-up; so stop() quick-stops again after each of
them is acknowledged and returns only once the stage is proven standing (M114 R twice, no
planned block). Another terminal's `dmdsm stage stop` reaches the client through
stage_control's socket.
"""

from __future__ import annotations

import re
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass

from dmdsm.marlin_patch import QUICK_STOP_CLEAN_S, MachineLimits, load_machine, numbered

from . import stage_control
from .board_clock import BoardClock, Deadline
from .safety import UnsafeMove, check_target
from .transport import LinkError, open_port

OK_N = re.compile(r"^ok\s+N(\d+)(?:\s+P(\d+))?(?:\s+B(\d+))?")
RESEND = re.compile(r"^(?:Resend|rs):?\s*N?(\d+)", re.I)
POSITION = re.compile(r"([XYZA]):\s*(-?\d+(?:\.\d+)?)")
CHIRON = load_machine()  # the patch's settings: the serial facts below come from them
RX_BUFFER = CHIRON.rx_buffer_size - 1  # bytes Marlin's ring takes before the oldest line is read
LONG = ("G28", "M400", "G4", "G29")
MAX_LINE = CHIRON.max_cmd_size - 1     # MAX_CMD_SIZE less its terminator: Marlin cuts longer lines
PROBE = "M114"       # numbered, harmless, answered with `ok N`
MAX_FREE_BLOCKS = CHIRON.block_buffer_size - 1  # `ok ... P<n>` when no move is planned
STILL_S = 0.1        # two real-time positions this far apart (stage time) prove standing
BOOT_S = 3.0         # a board reset by the port opening: bootloader + boot banner
M110_RETRY_S = 1.0   # M110 again after this long without its ok


class StageError(LinkError):
    """The stage refused, halted or stopped answering; str() says what to do."""


class StageStopped(StageError):
    """A stop was asked from another terminal: this client's work on the stage has ended."""


def clean_gcode(cmd: str) -> str:
    """One G-code command as Marlin should see it: the `;` comment and outer blanks removed
    (Marlin strips from `;` on, so a checksum after a comment would never match). Characters
    that would end or break the numbered line are refused."""
    text = cmd.split(";", 1)[0].strip()
    bad = next((c for c in text if c in "*\n\r" or not " " <= c <= "~"), None)
    if bad is not None:
        raise StageError(f"G-code {text[:40]!r} holds {bad!r}, which Marlin's line format "
                         f"cannot carry: send printable ASCII without '*'")
    return text


@dataclass
class StageStats:
    """What the link had to do: lines sent, resends served, timeout probes, lost oks."""

    lines: int = 0
    resent: int = 0
    probes: int = 0
    busy: int = 0
    errors: int = 0


class StageClient:
    """A Marlin board on a serial port (or pty / URL); satisfies links.interfaces.Stage."""

    def __init__(self, port: str, baudrate: int = CHIRON.baudrate, timeout_s: float = 5.0,
                 window: int = 1, stop_first: bool = False,
                 limits: MachineLimits | None = None) -> None:
        self.port_name = port
        # every absolute move is checked against this envelope before it is sent, whoever
        # asks for it (a command, a procedure, the API): the last guard before the wire
        self.limits = limits or load_machine()
        self.ser = open_port(port, baudrate)
        self.board_clock = BoardClock(port)  # an emulated board's own time, if published
        self.timeout_s = timeout_s
        # one line in flight (ping-pong, as OctoPrint): a line error makes Marlin drain its
        # receive ring, and the tail of a line behind it that arrives after the drain has no
        # number, so Marlin runs it unchecked - a move ran twice under faults with 4 in flight
        # (issue 29). Moves are long next to the ok's round trip: no throughput is lost
        self.window = window
        self.next_n = 1
        self.unacked: OrderedDict[int, str] = OrderedDict()  # n -> full line, in send order
        self.replies: dict[int, list[str]] = {}              # lines printed before ok N
        self.pending_text: list[str] = []
        self.buf = b""
        self.ignore_resend_of: int | None = None
        self.plain_oks_expected = 0  # oks of unnumbered lines (emergency M410)
        self.stats = StageStats()
        self.last_position: dict[str, float] | None = None  # from M114 or M154 reports
        self.last_free_blocks: int | None = None           # P of the latest `ok N P B`
        self.halted = False
        self.busy_at_connect = False  # the board was still running an earlier client's lines
        self._wlock = threading.Lock()   # one writer at a time: a stop never splits a line
        self._io = threading.RLock()     # one reader: the caller's operation or a stop
        self._stop_request = threading.Event()
        self._stopper: int | None = None  # thread running a stop asked from elsewhere
        self._connecting = False
        self.server: stage_control.StopServer | None = None
        if stop_first:  # M410 acts on receipt (emergency parser): before anything can queue
            self._quick_stop()
        try:
            self._reset_line_numbers()
        except BaseException:
            self.ser.close()
            raise
        stage_control.clear_halted(port)
        try:
            self.server = stage_control.StopServer(port, self._remote_stop)
        except OSError:
            self.server = None  # no runtime folder: stops from other terminals unavailable

    def close(self) -> None:
        """Close the port (after a stop asked from elsewhere has finished)."""
        if self.server is not None:
            self.server.close()
            self.server = None
        with self._io:
            self.ser.close()

    def __enter__(self) -> StageClient:
        return self

    def __exit__(self, exc_type: type | None, exc: BaseException | None, tb: object) -> None:
        """On Ctrl-C or an error during motion: quick-stop (M410), then close."""
        if exc_type is not None and not self.halted and not self._stop_request.is_set():
            try:
                self._write("M410\n")
            except StageError:
                pass
        self.close()

    # ------------------------------------------------------------------ wire
    def _write(self, text: str) -> None:
        try:
            with self._wlock:
                self.ser.write(text.encode())
        except (OSError, ValueError, TypeError) as e:
            raise StageError(f"lost the stage on {self.port_name}: {e}") from None

    def _send_line(self, n: int, cmd: str, line: str | None = None) -> None:
        """Send `N<n> cmd*<checksum>` (line: that text, already made) and keep it for resends."""
        if line is None:
            line = numbered(n, cmd)
        self.unacked[n] = line
        self._write(line)
        self.stats.lines += 1

    def _bytes_in_flight(self) -> int:
        return sum(len(x) for x in self.unacked.values())

    def _read_lines(self) -> list[str]:
        try:
            data = self.ser.read(1)  # returns at the first byte, or after the port timeout
            if data:
                data += self.ser.read(self.ser.in_waiting)
            self.buf += data
        except (OSError, ValueError) as e:
            raise StageError(f"lost the stage on {self.port_name}: {e}") from None
        lines = []
        while b"\n" in self.buf:
            raw, self.buf = self.buf.split(b"\n", 1)
            lines.append(raw.decode(errors="replace").strip())
        return [x for x in lines if x]

    def _handle(self, line: str) -> None:
        """Account for one line from the board."""
        if line.startswith("ok"):
            m = OK_N.match(line)
            if m:
                n = int(m.group(1))
                if m.group(2) is not None:
                    self.last_free_blocks = int(m.group(2))
                if n in self.unacked:
                    # in order: all up to n; an earlier line whose ok was lost printed its
                    # text before this ok too, so every line acknowledged here keeps it
                    for k in [k for k in self.unacked if k <= n]:
                        self.unacked.pop(k)
                        self.replies[k] = list(self.pending_text)
                    self.pending_text = []
                if self.ignore_resend_of is not None and n >= self.ignore_resend_of:
                    self.ignore_resend_of = None
            elif self.plain_oks_expected:
                self.plain_oks_expected -= 1
            return
        m = RESEND.match(line)
        if m:
            self._resend_from(int(m.group(1)))
            return
        if line.startswith("echo:busy"):
            self.stats.busy += 1
            return
        if "Printer halted" in line or "kill() called" in line or "Homing Failed" in line:
            self.halted = True
            return
        if line.startswith("Error:"):
            self.stats.errors += 1
            return
        if line.startswith("X:") and "Count" in line:
            self.last_position = {k: float(v) for k, v in POSITION.findall(
                line.split("Count")[0])}
        self.pending_text.append(line)

    def _resend_from(self, r: int) -> None:
        if r == self.ignore_resend_of:
            return  # a stale request from lines that were already on the wire
        if r not in self.unacked:
            return  # for a line already acknowledged: nothing to do
        self.ignore_resend_of = r
        self.stats.resent += 1
        for n in sorted(self.unacked):
            if n >= r:
                self._write(self.unacked[n])

    def _pump(self, deadline: Deadline, done: callable) -> None:
        """Read and handle lines until done() or the deadline (host and board time); busy
        lines extend it."""
        while not done():
            self._check_usable()
            if deadline.passed():
                raise TimeoutError
            busy_before = self.stats.busy
            for line in self._read_lines():
                self._handle(line)
            if self.stats.busy != busy_before:
                deadline = Deadline(self.timeout_s, self.board_clock)
                if self._connecting:
                    self.busy_at_connect = True

    # ------------------------------------------------------------------ commands
    def _reset_line_numbers(self) -> None:
        self._write("\n")  # end any partial line left on the wire
        self.unacked.clear()
        self.next_n = 1
        self.ignore_resend_of = None
        line = numbered(0, "M110 N0")
        self.unacked[0] = line
        self._connecting = True
        try:
            # opening the port may reset the board (DTR: bootloader ~1-2 s, then its banner);
            # an M110 sent meanwhile is lost, so it goes again until acknowledged. A board
            # still running an earlier client's moves says `busy`: the M110 waits behind
            # them, and so will every line after it, in order, so the link is usable now
            end = Deadline(self.timeout_s + BOOT_S, self.board_clock)
            while True:
                self._write(line)
                try:
                    self._pump(Deadline(M110_RETRY_S, self.board_clock),
                               lambda: 0 not in self.unacked or self.busy_at_connect)
                    break
                except TimeoutError:
                    if end.passed():
                        note = stage_control.halted_note(self.port_name)
                        if note:
                            raise StageError(
                                f"the stage on {self.port_name} is halted ({note.get('how')} "
                                f"sent at {note.get('at')} by pid {note.get('pid')}): press "
                                f"the board's reset button or power-cycle it, then home "
                                f"again") from None
                        raise StageError(f"the stage on {self.port_name} does not answer "
                                         f"(M110): check the cable and that it runs the "
                                         f"dmdsm Marlin (docs/marlin.md); a board halted "
                                         f"by M112 answers nothing until it is reset") from None
        except StageError:
            if self._is_sensor_board():
                raise StageError(f"{self.port_name} is the dmdsm sensor board, not the stage "
                                 f"(Marlin): swap the two port names") from None
            raise
        finally:
            self._connecting = False

    def _is_sensor_board(self) -> bool:
        """True if a dmdsm protocol ping gets a pong (the ports were swapped)."""
        from dmdsm.protocol import FrameDecoder, Message, encode_frame
        self._write("\n")
        self.ser.write(b"\x00" + encode_frame(Message("ping", seq=1, nonce=0x57A6E)))
        dec = FrameDecoder()
        end = time.monotonic() + 1.0
        while time.monotonic() < end:
            for m in dec.feed(self.ser.read(256)):
                if m.name == "pong":
                    return True
        return False

    def _wait_acked(self, n: int, timeout_s: float) -> None:
        self._await(lambda: n not in self.unacked, timeout_s, f"line {n} not acknowledged")

    def _await(self, done: callable, timeout_s: float, what: str) -> None:
        """Pump until done(); after a silent timeout probe (up to 3 times), then give up."""
        for attempt in range(4):
            try:
                self._pump(Deadline(timeout_s, self.board_clock), done)
                return
            except TimeoutError:
                if attempt == 3:
                    break
                self._probe()
        if b"\x00" in self.buf or any(b > 0x7F for b in self.buf[-64:]):
            raise StageError(f"{self.port_name} does not look like a Marlin board (it sends "
                             f"binary data: is it the sensor board?)")
        raise StageError(f"the stage on {self.port_name} stopped answering ({what}): check "
                         f"the cable and that it runs the dmdsm Marlin (docs/marlin.md)")

    def _probe(self) -> None:
        """After a timeout: a harmless line with the next number shows what Marlin has."""
        self.stats.probes += 1
        self.ignore_resend_of = None  # a Resend answering the probe is never stale
        n = self.next_n
        self.next_n += 1
        self._send_line(n, PROBE)

    def _check_usable(self) -> None:
        if self._stop_request.is_set() and threading.get_ident() != self._stopper:
            raise StageStopped(f"the stage on {self.port_name} was stopped from another "
                               f"terminal: nothing more is sent on this connection")
        if self.halted:
            raise StageError("the stage firmware is halted (M112 or kill()): press the "
                             "board's reset button or power-cycle it, then home again")

    def send(self, cmd: str, timeout_s: float | None = None, wait: bool = True) -> list[str]:
        """Send one command (its `;` comment dropped); with wait, return the lines it printed
        before its ok. A command Marlin could not take whole is refused unsent."""
        cmd = clean_gcode(cmd)
        if not cmd:
            return []
        with self._io:
            self._check_usable()
            # a line that can never fit Marlin's line or receive ring is refused before any
            # wait for room (the numbers probes may take meanwhile are counted in)
            longest = len(numbered(self.next_n + 8, cmd)) - 1
            if longest > MAX_LINE or longest + 13 > RX_BUFFER:
                raise StageError(f"G-code line too long for Marlin ({longest} > {MAX_LINE} "
                                 f"characters): {cmd[:40]}...; split it")
            return self._send_locked(cmd, timeout_s, wait)

    def _send_locked(self, cmd: str, timeout_s: float | None, wait: bool) -> list[str]:
        # flow control: command slots and the firmware's 128-byte receive ring
        self._await(lambda: len(self.unacked) < self.window
                    and self._bytes_in_flight() + len(cmd) + 12 <= RX_BUFFER,
                    self.timeout_s, "no room in the command buffer")
        n = self.next_n  # numbered only now: probes while waiting take numbers too
        line = numbered(n, cmd)
        self.next_n += 1
        self._send_line(n, cmd, line)
        if not wait:
            return []
        long_cmd = cmd.split()[0].upper() in LONG
        self._wait_acked(n, timeout_s or (self.timeout_s * (4 if long_cmd else 1)))
        return self.replies.pop(n, [])

    def drain(self, timeout_s: float | None = None) -> None:
        """Wait until every line sent has been acknowledged."""
        with self._io:
            if self.unacked:
                self._wait_acked(next(reversed(self.unacked)), timeout_s or self.timeout_s)

    # ------------------------------------------------------------------ operations
    def home(self, axes: str = "XYZ") -> dict[str, float]:
        """G28 for X Y Z (A has no endstop); returns the position after homing."""
        self.drain()
        self.send("G28 " + " ".join(a.upper() for a in axes if a.upper() in "XYZ"),
                  timeout_s=120)
        return self.where()

    def move(self, x: float | None = None, y: float | None = None, z: float | None = None,
             a: float | None = None, feed_mm_min: float | None = None,
             relative: bool = False, wait: bool = False) -> None:
        """G1 to X Y Z (mm) and A (deg); queued unless wait. A target that is not a finite
        number, or (absolute) outside the machine envelope, raises UnsafeMove unsent."""
        check_target(dict(zip("XYZA", (x, y, z, a))), self.limits, envelope=not relative)
        if feed_mm_min is not None and not 0 < feed_mm_min < float("inf"):
            raise UnsafeMove(f"feedrate {feed_mm_min} mm/min: give a positive number (Marlin "
                             f"would keep its last one)")
        fastest = 60.0 * max(self.limits.max_feedrate)
        if feed_mm_min is not None and feed_mm_min > fastest:
            raise UnsafeMove(f"feedrate {feed_mm_min:g} mm/min is above the machine's fastest "
                             f"axis ({fastest:g} mm/min): give at most that")
        words = [f"{k}{v:.4f}" for k, v in zip("XYZA", (x, y, z, a)) if v is not None]
        if feed_mm_min:
            words.append(f"F{feed_mm_min:.0f}")
        if relative:
            self.send("G91", wait=False)
        self.send("G1 " + " ".join(words), wait=wait)
        if relative:
            self.send("G90", wait=False)

    def wait(self, timeout_s: float = 600.0) -> None:
        """M400: return when every queued move has finished."""
        self.send("M400", timeout_s=timeout_s)

    def where(self) -> dict[str, float]:
        """M114: the position of the last queued move (mm, deg)."""
        with self._io:
            self.drain()
            pos, _ = self._report("M114")
            return pos

    def _report(self, cmd: str) -> tuple[dict[str, float], str]:
        lines = self.send(cmd)
        reports = [x for x in lines if x.startswith("X:")]
        if not reports:
            raise StageError(f"{cmd} gave no position: is this the dmdsm Marlin?")
        pos = {k: float(v) for k, v in POSITION.findall(reports[-1].split("Count")[0])}
        self.last_position = pos
        return pos, reports[-1].split("Count", 1)[-1]

    def live(self) -> tuple[dict[str, float], bool]:
        """Where the steppers are now (M114 R, mm and deg) and whether the stage is moving:
        a move is planned (`ok ... P` below the empty planner's) or the position changed
        over STILL_S."""
        with self._io:
            first, counts = self._report("M114 R")
            if self.last_free_blocks is not None and self.last_free_blocks < MAX_FREE_BLOCKS:
                return first, True
            time.sleep(STILL_S)
            second, counts2 = self._report("M114 R")
            planned = self.last_free_blocks is not None and \
                self.last_free_blocks < MAX_FREE_BLOCKS
            return second, planned or counts2 != counts

    def stop(self) -> dict[str, float]:
        """Quick-stop (M410, emergency parser) and return the position once the stage is
        proven standing. Lines Marlin had not read yet run after its clean-up, so each one
        acknowledged is answered with another M410; 0 moves run after this returns."""
        self._quick_stop()
        with self._io:
            return self._settle_stop()

    def _quick_stop(self) -> None:
        """Write an unnumbered M410: the emergency parser acts on its bytes, and the line
        itself later gets a plain `ok`."""
        self.plain_oks_expected += 1
        self._write("M410\n")

    def _settle_stop(self) -> dict[str, float]:
        limit = Deadline((len(self.unacked) + 3) * (QUICK_STOP_CLEAN_S + self.timeout_s),
                         self.board_clock)
        while self.unacked:
            oldest = next(iter(self.unacked))
            try:
                self._pump(limit, lambda: oldest not in self.unacked)  # noqa: B023
            except TimeoutError:
                raise StageError(f"the stage on {self.port_name} did not acknowledge the "
                                 f"lines sent before the stop: it may still move; press "
                                 f"its reset button") from None
            self._quick_stop()  # a line just run: drop its move before it steps
        for _ in range(int(30 / STILL_S)):  # proof: nothing planned, counts unchanged
            pos, moving = self.live()
            if not moving:
                return pos
        raise StageError(f"the stage on {self.port_name} kept moving after the stop: "
                         f"press its reset button")

    def _remote_stop(self) -> str:
        """A stop asked from another terminal (stage_control): quick-stop at once, end the
        owner's operation on the stage, prove standing, and say where."""
        self._stop_request.set()
        self._quick_stop()
        with self._io:  # the owner's pump raises StageStopped and lets go
            self._stopper = threading.get_ident()
            try:
                pos = self._settle_stop()
            finally:
                self._stopper = None
        return " ".join(f"{k}:{v:.3f}" for k, v in pos.items())

    def emergency_stop(self) -> str:
        """M112: the firmware halts until its reset button is pressed."""
        self._write("M112\n")
        self.halted = True
        stage_control.note_halted(self.port_name, "M112")
        return ("emergency stop sent: the stage firmware is halted; press the board's reset "
                "button (or power-cycle it), then home again")

    def firmware_info(self) -> str:
        """The M115 FIRMWARE_NAME line."""
        lines = self.send("M115")
        return next((x for x in lines if x.startswith("FIRMWARE_NAME")), "")
