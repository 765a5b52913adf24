"""Marlin stage-board emulator: the patched Marlin's serial dialect (docs/marlin.md) over bytes.

Driven by simulated time: `receive(data, now)` takes bytes from the host into a 128-byte RX
ring (bytes that do not fit are lost, as on the ATmega2560), `step(now)` runs the main loop
and returns what the board sends. Lines are checked (N…*checksum), queued into BUFSIZE slots
and executed in order; moves go to the trapezoidal planner of `motion.py`. Settings come from
firmware/marlin_patch/chiron_turntable.toml, like the real firmware's.
"""

from __future__ import annotations

import random
from dataclasses import dataclass

import numpy as np

from dmdsm.marlin_patch import (
    MINKILL_S,
    QUICK_STOP_CLEAN_S,
    MachineLimits,
    checksum,
    load_machine,
)

from .marlin_gcode import BUILT, FIRMWARE_NAME, GcodeMixin
from .motion import Planner


@dataclass
class StageFaults:
    """Stage-side faults: probabilities per line/command, extra busy seconds."""

    lost_ok: float = 0.0          # an `ok` is not sent
    spurious_resend: float = 0.0  # a good line is reported as corrupt and asked again
    busy_extra_s: float = 0.0     # blocking commands (G28, M400, G4) take this much longer
    lose_next_oks: int = 0        # the next this many `ok`s are not sent (tests)


TX_BUFFER_BYTES = 32  # the patch's TX_BUFFER_SIZE: a longer reply blocks until the rest fits
BYTE_S = 10 / 250000  # one byte on the wire at 250 kbaud, 8N1 (s)
READ_LAG_BYTES = 12  # bytes that arrive (at 250 kbaud, ~0.5 ms) before the main loop reads a
# finished line: a line error then flushes them, and the rest of a burst is read from mid-line


def banner(m: MachineLimits) -> list[str]:
    """What the patched Chiron build prints at power-up with a blank EEPROM (as the real one
    in simavr does): version, build, memory, the defaults stored, and the settings report."""
    def axes(values: tuple) -> str:
        return " ".join(f"{a}{v:.2f}" for a, v in zip(m.axes, values))
    return ["start", "PowerUp", FIRMWARE_NAME,
            "echo: Last Updated: 2024-10-21 | Author: (Nick Wells, Chiron Build)",
            f"echo: Compiled: {BUILT[:11]}", "echo: Free Memory: 5367  PlannerBufferBytes: 1264",
            "echo:EEPROM version mismatch (EEPROM=? Marlin=V90)",
            "//action:notification Hardcoded Default Settings Loaded",
            "echo:Hardcoded Default Settings Loaded",
            "//action:notification Hardcoded Default Settings Loaded",
            "echo:Hardcoded Default Settings Loaded", "echo:Settings Stored (637 bytes; crc 55472)",
            "//action:notification Settings Stored", "echo:; Linear Units:", "echo:  G21 ; (mm)",
            "echo:; Steps per unit:", f"echo:  M92 {axes(m.steps_per_unit)}",
            "echo:; Max feedrates (units/s):", f"echo:  M203 {axes(m.max_feedrate)}",
            "echo:EEPROM Initialized", "//action:prompt_end"]


class MarlinEmulator(GcodeMixin):
    """One emulated Chiron stage board (Marlin with the turntable as axis A)."""

    def __init__(self, limits: MachineLimits | None = None, seed: int = 0,
                 faults: StageFaults | None = None) -> None:
        self.limits = limits or load_machine()
        self.faults = faults or StageFaults()
        self.rng = random.Random(seed)
        self.reset(0.0)

    # ------------------------------------------------------------------ state
    def reset(self, now: float, boot_s: float = 0.0) -> None:
        """Hardware reset: everything lost; the bootloader ignores the serial line for boot_s
        (opening the port toggles DTR, which resets a real ATmega2560), then the banner."""
        n = len(self.limits.axes)
        self.planner = Planner(self.limits)
        self.rx = bytearray()
        self.line = bytearray()
        self.queue: list[tuple[str, int | None]] = []  # (command, line number or None)
        self.out: list[str] = []
        self.last_n = 0
        self.killed = False
        self.killed_at = 0.0       # when M112 arrived: the steppers run on for MINKILL_S
        self.frozen = False        # minkill's cli(): nothing moves or answers any more
        # M410 (emergency parser): quickstop_stepper() flushes the planner, then waits in
        # idle() for the 1 s clean-up; idle() still reads the serial port into free command
        # slots but runs none. An M410 arriving meanwhile sets quickstop_flag: once the pause
        # ends, the main loop runs one command, then the next idle() stops again.
        self.paused_until: float | None = None
        self.quickstop_flag = False
        self.relative = False
        self.feed_mm_s = 50.0
        # at power-up Marlin takes the carriage to be at its home position: X Y Z at their min
        # positions (the Chiron: X -10, `X:-10.00 ... Count X:-800`), A at 0
        home = np.array([self.limits.min_pos[i] if a in "XYZ" else 0.0
                         for i, a in enumerate(self.limits.axes)], float)
        self.current = home.copy()  # logical position of the last queued move (mm, deg)
        self.offset = home.copy()   # logical - raw (homing's min position + G92 shift)
        self.native0 = home.copy()  # native - raw: the min position once an axis is homed
        self.homed = [False] * n
        self.blocking: dict | None = None  # the command in progress that holds the queue
        self.auto_report_s = 0.0
        self.next_report = 0.0
        self.emergency = bytearray()
        self.discard = 0           # received bytes a line error's drain still takes
        self.discard_until = 0.0
        self.held_from: int | None = None  # out's lines from here wait for the drain's end
        self.executed: list[tuple[int | None, str]] = []  # ground truth: (N, command) in order
        self.now = now
        self.booting_until = now + boot_s
        self.banner_due = True
        self._boot(now)

    def _boot(self, now: float) -> None:
        """The boot banner, once the bootloader has passed control to Marlin."""
        if self.banner_due and now >= self.booting_until:
            self.banner_due = False
            self.out += banner(self.limits)

    def position(self) -> np.ndarray:
        """Ground truth: where the stage is now (mm, deg), in raw machine coordinates."""
        self._advance_motion(self.now)
        return self.planner.position()

    def _advance_motion(self, t: float) -> None:
        """Step the planner to t (s); after M112 the steppers stop for good MINKILL_S on."""
        if self.killed and not self.frozen and t >= self.killed_at + MINKILL_S:
            self.planner.quick_stop(self.killed_at + MINKILL_S)  # minkill: cli()
            self.frozen = True
        if not self.frozen:
            self.planner.update(t)

    # ------------------------------------------------------------------ bytes in/out
    def position_at(self, t: float) -> np.ndarray:
        """Where the steppers were at time t (s), from the endstops (mm, deg)."""
        return self.planner.position_at(t)

    def step_edges(self, axis: int, t_from: float, t_to: float) -> np.ndarray:
        """Times (s) of the STEP pulses of `axis` in (t_from, t_to]."""
        return self.planner.step_edges(axis, t_from, t_to)

    def receive(self, data: bytes, now: float) -> None:
        """Bytes from the host; the emergency parser sees them at once."""
        if now < self.booting_until:
            return  # the bootloader is not Marlin: the bytes are gone
        self._run(now)
        behind = None  # bytes arrived since the oldest unread newline
        for b in data:
            self._emergency(b, now)
            if len(self.rx) >= self.limits.rx_buffer_size or (behind or 0) >= READ_LAG_BYTES:
                self._run(now)  # the main loop reads the ring while bytes keep arriving
                behind = None
            if self.discard and now <= self.discard_until:
                self.discard -= 1  # drained after a line error (_line_error)
                continue
            if len(self.rx) < self.limits.rx_buffer_size:
                self.rx.append(b)  # else lost, as on the ATmega2560 (command slots full)
            if behind is not None:
                behind += 1
            elif b in (10, 13):
                behind = 0
        self._run(now)

    def step(self, now: float) -> bytes:
        """Run the main loop up to `now` (s); returns the bytes the board sends. A line
        error's Resend and ok leave only once its drain is over (the error line blocks the
        TX until it is out, and the flush comes before them), so a host's answer to them
        always arrives after the drain, as on the board."""
        self._run(now)
        if self.held_from is not None and self.now > self.discard_until:
            self.held_from = None
        n = len(self.out) if self.held_from is None else self.held_from
        send, self.out = self.out[:n], self.out[n:]
        if self.held_from is not None:
            self.held_from = 0
        return "".join(line + "\n" for line in send).encode()

    def _run(self, now: float) -> None:
        target = max(self.now, now)
        self._boot(target)
        if self.killed or target < self.booting_until:
            self.now = target
            self._advance_motion(target)
            return
        while self.paused_until is not None and self.paused_until <= target:
            t = self.paused_until  # the clean-up ends: quickstop_stepper() returns
            self.now = t
            self.planner.update(t)
            self.paused_until = None
            if self.quickstop_flag:  # another M410 came meanwhile: one command, then stop
                self.quickstop_flag = False
                self._loop_once()
                if not self.killed:
                    self._quick_stop(t)
        self.now = target
        self._advance_motion(target)
        if self.paused_until is not None:  # idle() inside the stop: reads, runs nothing
            self._read_serial(self.limits.bufsize - (1 if self.blocking else 0))
        else:
            for _ in range(64):  # bounded work per call
                if not self._loop_once():
                    break
        if self.auto_report_s and self.now >= self.next_report and not self.killed:
            self.out.append(self._position_line())
            self.next_report = self.now + self.auto_report_s

    def _loop_once(self) -> bool:
        """One pass of Marlin's loop(): finish the command that holds the queue, or run the
        next one; False when there was nothing to do."""
        if self.blocking is not None:
            if not self._blocking_done():
                # lines keep coming in while a command waits (the real Marlin's `ok` of
                # an M400 counts a line sent meanwhile in B: issue 20's differential run)
                self._read_serial(self.limits.bufsize - 1)
                return False
            return True
        self._read_serial()
        if not self.queue:
            return False
        cmd, n = self.queue.pop(0)
        self._execute(cmd, n)
        return not self.killed

    def _quick_stop(self, t: float) -> None:
        """quickstop_stepper(): drop every planned block, stand, and pause the loop 1 s."""
        self.planner.quick_stop(t)
        self._sync_current_from_steppers()
        self.paused_until = t + QUICK_STOP_CLEAN_S

    def _emergency(self, b: int, now: float) -> None:
        """M112 / M410 act as soon as their bytes arrive, before the queue sees them."""
        if b in (10, 13):
            word = self.emergency.decode(errors="replace").strip()
            if word.startswith("N"):
                word = word.split(" ", 1)[1] if " " in word else ""
            word = word.split("*")[0].strip()
            if word == "M112" and not self.killed:
                self.out += ["echo:M112 Shutdown", "Error:Printer halted. kill() called!",
                             "//action:poweroff"]
                self.planner.update(now)
                self.killed, self.killed_at = True, now  # the steppers run MINKILL_S more
            elif word == "M410" and not self.killed:
                if self.paused_until is None:
                    self._quick_stop(now)
                else:
                    self.quickstop_flag = True
            self.emergency.clear()
        elif len(self.emergency) < 16:
            self.emergency.append(b)

    # ------------------------------------------------------------------ line protocol
    def _read_serial(self, slots: int | None = None) -> None:
        """Move complete lines from the RX ring into free command slots (Marlin's get_serial);
        `slots` of them (fewer while the command being run holds one)."""
        slots = self.limits.bufsize if slots is None else slots
        while self.rx and len(self.queue) < slots:
            b = self.rx.pop(0)
            if b not in (10, 13):
                if len(self.line) < self.limits.max_cmd_size - 1:
                    self.line.append(b)
                continue
            text = self.line.decode(errors="replace").split(";")[0]
            self.line.clear()
            if text:  # blanks only: Marlin runs "" (`echo:Unknown command: ""`, then ok)
                self._accept(text.strip())

    def _line_error(self, message: str) -> None:
        error = f"Error:{message}, Last Line: {self.last_n}"
        self.out.append(error)
        # gcode_line_error prints the error first (blocking while it does not fit the TX
        # buffer), then drains the RX ring: what arrives while the line goes out is lost too
        self.rx.clear()
        self.line.clear()
        self.discard = max(0, len(error) + 1 - TX_BUFFER_BYTES)
        self.discard_until = self.now + self.discard * BYTE_S
        self.held_from = len(self.out) if self.discard else None  # the latest error's
        self.out += [f"Resend: {self.last_n + 1}", "ok"]

    def _accept(self, text: str) -> None:
        n = None
        if text.startswith("N"):
            head, _, rest = text[1:].partition(" ")
            try:
                n = int(head)
            except ValueError:
                n = None
            body = text.split("*")[0]
            is_m110 = "M110" in body
            if n is None:
                self._line_error("Line Number is not Last Line Number+1")
                return
            if n != self.last_n + 1 and not is_m110:
                if n in (self.last_n, self.last_n - 1):
                    return  # a duplicate: dropped without an ok, as Marlin does
                self._line_error("Line Number is not Last Line Number+1")
                return
            if "*" not in text:
                self._line_error("No Checksum with line number")
                return
        if "*" in text:
            body, _, cs = text.rpartition("*")
            if n is not None:  # only a numbered line's checksum is checked (queue.cpp);
                try:           # an unnumbered one, e.g. a burst's tail after a flush, runs
                    ok = int(cs) == checksum(body)
                except ValueError:
                    ok = False
                if not ok:
                    self._line_error("checksum mismatch")
                    return
            text = body
        if n is not None and self.faults.spurious_resend and \
                self.rng.random() < self.faults.spurious_resend:
            self._line_error("checksum mismatch")
            return
        if n is not None:
            self.last_n = n
            text = text.split(" ", 1)[1] if " " in text else ""
        self.queue.append((text.strip(), n))

    def _ok(self, n: int | None) -> None:
        if self.faults.lose_next_oks > 0:
            self.faults.lose_next_oks -= 1
            return
        if self.faults.lost_ok and self.rng.random() < self.faults.lost_ok:
            return
        free_p = self.limits.block_buffer_size - len(self.planner.queue) - 1
        free_b = self.limits.bufsize - len(self.queue) - 1  # this command still holds a slot
        self.out.append(f"ok{f' N{n}' if n is not None else ''} P{max(free_p, 0)} B{free_b}")

    # ------------------------------------------------------------------ blocking commands
    def _block(self, kind: str, until: float, n: int | None, **extra: object) -> None:
        """Hold the queue until `until` (s), sending busy lines meanwhile."""
        self.blocking = {"kind": kind, "until": until + self.faults.busy_extra_s, "n": n,
                         "busy_at": self.now + self.limits.keepalive_interval_s, **extra}

    def _blocking_done(self) -> bool:
        b = self.blocking
        assert b is not None
        if b["kind"] == "move":  # waiting for a free planner block
            if self.planner.free_blocks() <= 0:
                return self._busy(b)
            self.planner.line_to(self.now, *b["args"])
        elif b["kind"] == "sync":  # M400 / G4 / G28: wait for time to pass
            if self.now < max(b["until"], self.planner.busy_until(self.now)):
                return self._busy(b)
            if b.get("then"):
                b["then"]()
        self.blocking = None
        self._ok(b["n"])
        return True

    def _busy(self, b: dict) -> bool:
        while self.now >= b["busy_at"]:
            self.out.append("echo:busy: processing")
            b["busy_at"] += self.limits.keepalive_interval_s
        return False
