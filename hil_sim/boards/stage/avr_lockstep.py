"""The stage board as its real firmware (an AVR ELF, e.g. Marlin built from our patch) under
simavr, in lock-step with the simulation: the same receive/step/position_at/step_edges a
`MarlinEmulator` offers, so `dmdsm sim --stage-firmware ELF` swaps one for the other."""

from __future__ import annotations

import random
import subprocess
from pathlib import Path

import numpy as np

from dmdsm.marlin_patch import MachineLimits, load_machine

from .avr_pty import HARNESS, AvrStageError, AxisPins, chiron_axes, close_pipes, quit_harness
from .marlin import StageFaults

F_CPU_HZ = 16_000_000  # the Trigorilla's crystal
KEEP_S = 2.0  # step history kept for poses and the sync wire (the sensor asks for the present)


class AxisTrace:
    """One axis's steps: cycle-exact times (s) and the count after each, the recent ones."""

    def __init__(self) -> None:
        self.count = 0          # now
        self.base = 0           # before the first kept edge
        self.t = np.zeros(0)
        self.c = np.zeros(0, np.int64)
        self.runs: list[int] = []  # signed lengths of the runs of steps in one direction

    def add(self, signed_cycles: np.ndarray, now: float) -> None:
        """Steps of one run: cycle + 1, negative for a step down."""
        steps = np.sign(signed_cycles)
        turns = np.flatnonzero(np.diff(steps)) + 1
        for run in np.split(steps, turns):
            if self.runs and np.sign(self.runs[-1]) == run[0]:
                self.runs[-1] += int(run.sum())
            else:
                self.runs.append(int(run.sum()))
        t = (np.abs(signed_cycles) - 1) / F_CPU_HZ
        c = self.count + np.cumsum(steps)
        self.count = int(c[-1])
        self.t = np.concatenate([self.t, t])
        self.c = np.concatenate([self.c, c])
        old = np.searchsorted(self.t, now - KEEP_S)
        if old > 0:
            self.base = int(self.c[old - 1])
            self.t, self.c = self.t[old:], self.c[old:]

    def at(self, t: float) -> int:
        """The count at time t (s), as far back as the kept history."""
        i = np.searchsorted(self.t, t, side="right")
        return int(self.c[i - 1]) if i else self.base


class AvrStageBoard:
    """A stage firmware ELF in build/avr/stage_harness --lockstep, stepped by the caller."""

    def __init__(self, elf: str | Path, limits: MachineLimits | None = None, seed: int = 0,
                 faults: StageFaults | None = None, axes: tuple[AxisPins, ...] | None = None,
                 harness: Path = HARNESS) -> None:
        self.limits = limits or load_machine()
        self.faults = faults or StageFaults()
        if self.faults.spurious_resend or self.faults.busy_extra_s:
            raise AvrStageError("with a real stage firmware only the stage.lost_ok fault is "
                                "emulated (the others would have to change the firmware)")
        self.rng = random.Random(seed)
        self.axes = axes or chiron_axes(steps_per_unit=tuple(self.limits.steps_per_unit[:3]))
        if not Path(harness).is_file():
            raise AvrStageError(f"{harness} is not built: run `make avr` (needs simavr, "
                                f"libsimavr-dev, gcc-avr)")
        if not Path(elf).is_file():
            raise AvrStageError(f"{elf}: no such stage firmware file (build it: docs/marlin.md)")
        args = [str(harness), str(elf), "--lockstep"]
        for a in self.axes:
            args += ["--axis", a.spec()]
        self.proc = subprocess.Popen(args, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, text=True, bufsize=1)
        self.traces = [AxisTrace() for _ in self.axes]
        names = [a.name for a in self.axes]
        self._index = [names.index(n) for n in self.limits.axes]  # X Y Z A, Z2 left out
        self._trigger = np.array([self.axes[i].trigger_steps for i in self._index], float)
        self._trigger[3:] = 0.0  # no endstop on A: degrees from where it was switched on
        self.spu = np.asarray(self.limits.steps_per_unit, float)
        self.now = 0.0
        self.cycle = 0
        self.partial = b""  # output after the last newline (lost_ok works on whole lines)
        self.out_buffer = b""  # output not yet collected by step()
        self.booting_until = 0.0  # the bootloader's time after a reset (s)
        try:
            self._command("r 0")
        except AvrStageError:
            self.close()
            raise

    # ------------------------------------------------------------------ the harness
    def _command(self, line: str) -> bytes:
        try:
            self.proc.stdin.write(line + "\n")
            self.proc.stdin.flush()
        except (BrokenPipeError, OSError):
            raise AvrStageError(self._died()) from None
        out = b""
        while True:
            reply = self.proc.stdout.readline()
            if not reply:
                raise AvrStageError(self._died())
            kind = reply[:2]
            if kind == "u ":
                out += bytes.fromhex(reply[2:].strip())
            elif kind == "e ":
                words = reply.split()
                self.traces[int(words[1])].add(np.array(words[2:], np.int64), self.now)
            elif kind == "d ":
                _, cycle, state = reply.split()
                self.cycle = int(cycle)
                if int(state) in (6, 7):  # cpu_Done, cpu_Crashed (enum in simavr/sim_avr.h)
                    raise AvrStageError(f"the stage firmware stopped (simavr state {state}) "
                                        f"at {self.cycle / F_CPU_HZ:.3f} s")
                return out

    def _died(self) -> str:
        self.proc.wait(5)
        err = (self.proc.stderr.read() or "").strip().splitlines()
        return (err or [f"stage_harness ended with {self.proc.returncode}"])[-1]

    # ------------------------------------------------------------------ the board interface
    def receive(self, data: bytes, now: float) -> None:
        """Bytes from the host into UART0 (fed as fast as the UART takes them)."""
        self._run_to(now)  # the firmware runs up to the moment the bytes arrive
        if data and now >= self.booting_until:
            try:
                self.proc.stdin.write("w " + data.hex() + "\n")
            except (BrokenPipeError, OSError):
                raise AvrStageError(self._died()) from None

    def step(self, now: float) -> bytes:
        """Run the firmware up to `now` (s); returns what it sent on UART0."""
        self._run_to(now)
        data, self.out_buffer = self.out_buffer, b""
        return self._drop_oks(data)

    def _run_to(self, now: float) -> None:
        if now <= self.now:
            return
        if now < self.booting_until:  # held by the bootloader: Marlin's code does not run
            self.now = now
            return
        if self.now < self.booting_until:  # the hold ends: Marlin starts once, from reset
            self._command(f"h {round(self.booting_until * F_CPU_HZ)}")
        self.now = now
        self.out_buffer += self._command(f"r {round(now * F_CPU_HZ)}")

    def _drop_oks(self, data: bytes) -> bytes:
        """The stage.lost_ok fault: whole `ok` lines vanish on their way to the host."""
        f = self.faults
        if not (f.lost_ok or f.lose_next_oks):
            data, self.partial = self.partial + data, b""
            return data
        *lines, self.partial = (self.partial + data).split(b"\n")
        kept = []
        for x in lines:
            if x.startswith(b"ok") and f.lose_next_oks > 0:
                f.lose_next_oks -= 1
            elif not (x.startswith(b"ok") and f.lost_ok and self.rng.random() < f.lost_ok):
                kept.append(x)
        return b"".join(x + b"\n" for x in kept)

    def reset(self, now: float, boot_s: float = 0.0) -> None:
        """The DTR reset of opening the port: the bootloader holds the chip for boot_s and
        takes what the host sends meanwhile, then the firmware restarts (the carriage stays)."""
        self._run_to(now)
        self.booting_until = now + boot_s
        self._command("reset")  # the bytes sent meanwhile are lost; the hold ends in _run_to

    def position_at(self, t: float) -> np.ndarray:
        """Where the carriage was at time t (s): X, Y, Z from their min endstops (mm) and A
        from where the stage was switched on (deg), from the counted STEP pulses."""
        counts = np.array([self.traces[i].at(t) for i in self._index], float)
        return (counts - self._trigger) / self.spu

    def position(self) -> np.ndarray:
        """Where the carriage is now (mm, deg)."""
        return self.position_at(self.now)

    def step_edges(self, axis: int, t_from: float, t_to: float) -> np.ndarray:
        """Times (s) of the STEP pulses of axis (X=0, ...) in (t_from, t_to], in order."""
        tr = self.traces[self._index[axis]]
        return tr.t[(tr.t > t_from) & (tr.t <= t_to)]

    def close(self) -> None:
        """Stop the harness."""
        quit_harness(self.proc)
        close_pipes(self.proc)
