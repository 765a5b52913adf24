"""A stage board's real firmware (an AVR ELF, e.g. Marlin built from our patch) under simavr,
through build/avr/stage_harness: UART0 on a pseudo-terminal the host opens like a board's
port, the step counts of each axis followed so the physics knows where the stage is."""

from __future__ import annotations

import collections
import os
import subprocess
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[3]
HARNESS = Path(os.environ.get("DMDSM_STAGE_HARNESS", REPO / "build/avr/stage_harness"))


class AvrStageError(RuntimeError):
    """The harness or the firmware could not be started; str() says what to do."""


def quit_harness(proc: subprocess.Popen) -> None:
    """Ask a running stage_harness to quit (stdin "quit"); kill it if it will not."""
    if proc.poll() is None:
        try:
            proc.stdin.write("quit\n")
            proc.stdin.flush()
            proc.wait(5)
        except (OSError, subprocess.TimeoutExpired):
            proc.kill()
            proc.wait(5)


def close_pipes(proc: subprocess.Popen) -> None:
    """Close the harness's pipes (a write still buffered to one that ended is dropped)."""
    for f in (proc.stdin, proc.stdout, proc.stderr):
        if f is not None:
            try:
                f.close()
            except OSError:
                pass


@dataclass(frozen=True)
class AxisPins:
    """One stepper axis: pins as port letter + bit ('F0'), endstop '-' if none; dir_inverted
    as Marlin's INVERT_x_DIR; the endstop reads triggered at counts <= trigger_steps, high or,
    with endstop_hit_low, low (Marlin's x_MIN_ENDSTOP_HIT_STATE LOW)."""

    name: str
    step: str
    dir: str
    endstop: str = "-"
    trigger_steps: int = 0
    dir_inverted: bool = False
    endstop_hit_low: bool = False

    def spec(self) -> str:
        """The harness's --axis argument."""
        end = ("!" if self.endstop_hit_low and self.endstop != "-" else "") + self.endstop
        return (f"{self.name}:{self.step}:{'!' if self.dir_inverted else ''}{self.dir}:"
                f"{end}:{self.trigger_steps}")


# RAMPS 1.4: X, Y, Z and E0 (the turntable, axis A)
RAMPS = (AxisPins("X", "F0", "F1", "E5"), AxisPins("Y", "F6", "F7", "J1"),
         AxisPins("Z", "L3", "L1", "D3"), AxisPins("A", "A4", "A6", "-"))


def chiron_axes(start_mm: tuple[float, float, float] = (30.0, 30.0, 10.0),
                steps_per_unit: tuple[float, ...] = (80, 100, 400)) -> tuple[AxisPins, ...]:
    """The Chiron's Trigorilla 1.4 as Marlin maps it (TRIGORILLA_MAPPING_CHIRON in
    pins_TRIGORILLA_14.h; INVERT_X/Y/Z_DIR true, X/Y endstops hit LOW, Z and Z2 HIGH in the
    Chiron example configuration): X D54/D55 stop D3, Y D60/D61 stop D42, Z D36/D34 stop D43,
    Z2 D46/D48 stop D18, A on E0 D26/D28. The carriage starts start_mm (X, Y, Z) above each
    min endstop, so the harness's counts read 0 where the stage was switched on."""
    trig = [-round(m * s) for m, s in zip(start_mm, steps_per_unit)]
    return (AxisPins("X", "F0", "F1", "E5", trig[0], True, True),
            AxisPins("Y", "F6", "F7", "L7", trig[1], True, True),
            AxisPins("Z", "C1", "C3", "L6", trig[2], True),
            AxisPins("Z2", "L3", "L1", "D3", trig[2], True),
            AxisPins("A", "A4", "A6", "-"))


class AvrStage:
    """A running harness: `port` for the host, `counts` (steps per axis) and `time_s`
    (simulated seconds) as last reported; close() stops it."""

    def __init__(self, elf: Path, axes: tuple[AxisPins, ...] = RAMPS, speed: float = 1.0,
                 harness: Path = HARNESS, start_timeout_s: float = 10.0) -> None:
        if not Path(harness).is_file():
            raise AvrStageError(f"{harness} is not built: run `make avr` (needs simavr, "
                                f"libsimavr-dev, gcc-avr)")
        if not Path(elf).is_file():
            raise AvrStageError(f"{elf}: no such firmware file")
        self.axes = axes
        self.counts = np.zeros(len(axes), np.int64)
        self.time_s = 0.0
        self.exit_state: int | None = None
        self.lock = threading.Lock()
        args = [str(harness), str(elf), "--speed", str(speed)]
        for a in axes:
            args += ["--axis", a.spec()]
        self.proc = subprocess.Popen(args, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, text=True)
        self.port = self._wait_for_pty(start_timeout_s)
        self.reader = threading.Thread(target=self._read, daemon=True)
        self.reader.start()
        self.errors: collections.deque[str] = collections.deque(maxlen=20)  # simavr's stderr
        threading.Thread(target=lambda: self.errors.extend(self.proc.stderr),
                         daemon=True).start()  # drained, or a chatty run would block on it

    def _wait_for_pty(self, timeout_s: float) -> str:
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            line = self.proc.stdout.readline()
            if not line:  # the harness ended before its pty was up
                err = self.proc.stderr.read().strip().splitlines()
                self.proc.wait(5)
                close_pipes(self.proc)
                raise AvrStageError((err or ["stage_harness ended at start"])[-1])
            if line.startswith("pty "):
                return line.split(None, 1)[1].strip()
        self.proc.kill()
        self.proc.wait(5)
        close_pipes(self.proc)
        raise AvrStageError(f"stage_harness gave no pty within {timeout_s:g} s")

    def _read(self) -> None:
        for line in self.proc.stdout:
            words = line.split()
            if words[:1] == ["t"] and len(words) == 2 + len(self.axes):
                with self.lock:
                    self.time_s = float(words[1])
                    self.counts = np.array([int(w) for w in words[2:]], np.int64)
            elif words[:1] == ["exit"]:
                self.exit_state = int(words[1])

    def positions(self, steps_per_unit: np.ndarray) -> np.ndarray:
        """Distance of each axis from its endstop trigger (mm, deg): the raw machine frame
        the physics uses (0 at the endstop)."""
        trig = np.array([a.trigger_steps for a in self.axes])
        with self.lock:
            return (self.counts - trig) / np.asarray(steps_per_unit, float)

    def close(self) -> None:
        """Stop the firmware and the harness."""
        quit_harness(self.proc)
        self.reader.join(2)
        close_pipes(self.proc)
