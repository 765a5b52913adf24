"""The Marlin emulator against the real Marlin on random G-code (`make check-marlin`): the
same lines go to both, in lock-step simulated time, and every reply line must match, beyond
the fixed cases of the conformance suite; then random joined moves go to both and their motion,
as counted from the STEP pins, must match. Prints each difference with the lines before it.

usage: python tests/stage/differential.py build/marlin/Marlin.elf [--lines 300] [--seed 1]
       [--motion 24]
"""

from __future__ import annotations

import argparse
import math
import random
import re
import sys
from dataclasses import dataclass, field

import numpy as np

from dmdsm.marlin_patch import checksum, load_machine
from dmdsm.sim.servers.runner import SimConfig, Simulation

BUSY = "echo:busy: processing"
STEP_S = 0.005


class Stage:
    """One stage (emulator, or firmware ELF) driven line by line in simulated time."""

    def __init__(self, elf: str) -> None:
        self.sim = Simulation(SimConfig(seed=1, stage_firmware=elf))
        self.buf = b""
        self.rec: Recording | None = None  # the motion part's record of the steps
        self.run(3.0)  # boot
        self.buf = b""

    def run(self, seconds: float) -> None:
        end = self.sim.t + seconds
        while self.sim.t < end:
            self.tick()

    def tick(self) -> None:
        """One STEP_S of simulated time; what the stage sent goes to buf."""
        self.sim.advance(STEP_S)
        self.buf += self.sim.read("stage")
        if self.rec is not None:
            self.rec.pull(self.sim.t)

    def lines(self) -> list[str]:
        """The whole lines received so far, taken from buf."""
        *lines, self.buf = self.buf.split(b"\n")
        return [x.decode(errors="replace").strip() for x in lines]

    def exchange(self, raw: str, n: int | None, timeout_s: float = 60.0) -> list[str]:
        """Send raw bytes; the reply lines up to and including this line's ok (`ok N<n>`,
        or a plain ok for an unnumbered line), busy lines left out: how many there are
        depends on how long a move takes, not on the dialect."""
        self.sim.write("stage", raw.encode())
        out: list[str] = []
        end = self.sim.t + timeout_s
        while self.sim.t < end:
            self.run(STEP_S * 4)
            while b"\n" in self.buf:
                line, self.buf = self.buf.split(b"\n", 1)
                text = line.decode(errors="replace").strip()
                if text != BUSY:
                    out.append(text)
                mine = text.startswith(f"ok N{n} ") if n is not None else \
                    text.startswith("ok") and not text.startswith("ok N")
                if mine:
                    self.run(0.05)  # anything a command prints after its ok
                    return out
        return out + ["(no ok)"]

    def close(self) -> None:
        self.sim.close()


def commands(rng: random.Random, n: int) -> list[tuple[str, bool]]:
    """n random lines as (command, numbered): moves in both modes (some past the soft
    endstops, some with F <= 0), positions, waits, unknown and lower-case commands, G92 on A;
    every line is short enough for Marlin."""
    out: list[tuple[str, bool]] = [("G28", True), ("G90", True)]
    for _ in range(n):
        k = rng.random()
        if k < 0.35:
            axes = rng.sample("XYZA", rng.randint(1, 3))
            words = []
            for a in axes:
                lo, hi = {"X": (-10, 410), "Y": (0, 410), "Z": (0, 60), "A": (-720, 720)}[a]
                if rng.random() < 0.1:  # past the soft endstops: Marlin clamps
                    lo, hi = lo - 50, hi + 50
                words.append(f"{a}{rng.uniform(lo, hi):.3f}")
            if rng.random() < 0.5:  # F <= 0 keeps the last feedrate
                words.append(f"F{rng.choice([600, 3000, 6000, 12000, 0, -100])}")
            out.append((f"G{rng.choice([0, 1])} " + " ".join(words), True))
        elif k < 0.45:
            out.append((rng.choice(["G90", "G91", "M400", "M114", "M114 D"]), True))
        elif k < 0.5:  # after M400: G92 prints the steppers' counts, which mid-move depend
            # on the stepper's own ramp timing (test_marlin_dialect checks that case)
            out += [("M400", True), (f"G92 A{rng.uniform(-90, 90):.2f}", True)]
        elif k < 0.55:
            out.append((f"G4 P{rng.randint(0, 300)}", True))
        elif k < 0.6:
            out.append((rng.choice(["G123", "M9999 S1", "g1 x5", "M105", "M17", "M84 X"]),
                        True))
        elif k < 0.7:
            out.append(("M114", False))
        else:
            out.append((rng.choice(["M400", "M114"]), True))
    out.append(("G90", True))
    return out


NUMBER = re.compile(r"[ -]?\d+\.\d+")  # a sign or its space, then a decimal
COUNT = re.compile(r"(?<=[XYZA]:)-?\d+\b(?!\.)")  # a stepper count after "Count"


def same(emulator: list[str], marlin: list[str]) -> bool:
    """The same lines, but a decimal may differ by one unit of its last digit, and a stepper
    count by one step: Marlin parses with avr-libc's strtod and computes positions and
    steps in 32-bit floats (7.075 prints 7.08 there, 7.07 here; Y360.715 is 36071 steps
    there, 36072 here), which the emulator does not copy; everything else must match."""
    if len(emulator) != len(marlin):
        return False
    for a, b in zip(emulator, marlin):
        ca, cb = (x.split("Count")[1] if "Count" in x else "" for x in (a, b))
        if NUMBER.sub("#", a.split("Count")[0]) != NUMBER.sub("#", b.split("Count")[0]) or \
                COUNT.sub("#", ca) != COUNT.sub("#", cb):
            return False
        for x, y in zip(NUMBER.findall(a.split("Count")[0]), NUMBER.findall(b.split("Count")[0])):
            unit = 10.0 ** -len(y.split(".")[1])
            if abs(float(x) - float(y)) > 1.01 * unit:
                return False
        if any(abs(int(x) - int(y)) > 1 for x, y in zip(COUNT.findall(ca), COUNT.findall(cb))):
            return False
    return True


# ---------------------------------------------------------------------------- motion part
# Random joined moves, sent as the host sends them (each line once the last one's ok came),
# to both stages in lock-step; the steps each one takes are counted from its STEP pins (the
# emulator's step log, the AVR's pin edges in simavr) and compared in time.
MACHINE = load_machine()
MIN_STEPS_PER_SEGMENT = 6  # Marlin's Configuration_adv.h
SPU = np.asarray(MACHINE.steps_per_unit, float)
AXES = "XYZA"
SAMPLE_S = 0.0005  # position samples (s): both stages on the same grid from the first line
LO = np.array([0.0, 5.0, 2.0, -700.0])      # where the random moves stay (mm, deg): inside
HI = np.array([400.0, 400.0, 60.0, 700.0])  # the soft endstops, so neither stage clamps
HOME = np.array([-10.0, 0.0, 5.0, 0.0])     # the logical position after G28 (X min, Z raised)
FEEDS = (1500, 3000, 6000, 9000, 12000)  # mm/min
A_FEEDS = (1800, 3600, 5400)             # deg/min, moves of A alone


@dataclass
class Tolerance:
    """How far the emulator's motion may be from the real Marlin's, from what the real one
    under simavr does that the emulator leaves out (its stepper ISR). Marlin takes a block's
    first step one step period of its entry rate after the block starts (the emulator at the
    start), so from rest its first step comes 10 to 18 ms later (30 sequences). Each step
    falls on a timer tick, a ramp takes its rate from the step before, and at high rates the
    period comes from a table with two or four steps per interrupt, which makes a block up
    to about 4 % shorter or longer (measured: 3.5 % shorter at 12000 steps/s). So: the first
    step within start_s; each block's time (from the last step of the block before to its
    own last step) and each block's end (from the first step) within abs_s + rel x that
    time; positions at equal time from the first step within pos (mm, deg) + what the
    allowed time difference moves at the axis's top speed in the sequence. A planner with
    junction deviation off, 30 % less acceleration or one block of look-ahead is far
    outside (test_motion_differential.py)."""

    start_s: float = 0.020
    abs_s: float = 0.008
    rel: float = 0.04
    pos: tuple[float, ...] = (0.1, 0.1, 0.025, 0.2)


@dataclass
class Group:
    """A sequence of joined moves from `start` (logical mm, deg): each a target, a feedrate
    (mm/min, None: the last one) and how long the host waits before sending it (s)."""

    kind: str
    start: np.ndarray
    moves: list[tuple[np.ndarray, int | None, float]] = field(default_factory=list)
    planner0: np.ndarray | None = None  # the planner's position at the start (steps; None:
    # start's): a move Marlin dropped (< MIN_STEPS_PER_SEGMENT) left steps owed

    @property
    def end(self) -> np.ndarray:
        """Where the last move ends."""
        return self.moves[-1][0] if self.moves else self.start

    def add(self, target: np.ndarray, feed: int | None = None, gap: float = 0.0) -> None:
        """Append a move to target (kept inside LO..HI, on the 0.01 grid); none if it is
        where the last one ended."""
        q = on_grid(np.clip(target, LO, HI))
        if np.any(to_steps(q) != to_steps(self.end)):
            self.moves.append((q, feed, gap))

    def lines(self) -> list[str]:
        """The G-code, naming only the axes that move."""
        out, prev = [], self.start
        for q, feed, _ in self.moves:
            words = [f"{a}{v:.2f}" for a, v, p in zip(AXES, q, prev) if round(v - p, 2)]
            out.append("G1 " + " ".join(words + ([f"F{feed}"] if feed else [])))
            prev = q
        return out

    def planner_path(self) -> np.ndarray:
        """(moves + 1, axes): the planner's position (steps) at the start and after each
        move: a move of fewer than MIN_STEPS_PER_SEGMENT steps on every axis is dropped and
        leaves it, its steps going with the next move."""
        p = to_steps(self.start) if self.planner0 is None else self.planner0.copy()
        out = [p]
        for q, _, _ in self.moves:
            if np.max(np.abs(to_steps(q) - p)) >= MIN_STEPS_PER_SEGMENT:
                p = to_steps(q)
            out.append(p)
        return np.array(out)

    def block_steps(self) -> np.ndarray:
        """(moves, axes): the steps of each move (absolute), as both stages count them (none
        for a dropped move)."""
        return np.abs(np.diff(self.planner_path(), axis=0))


def to_steps(p: np.ndarray) -> np.ndarray:
    """Logical position to stepper counts (X's min -10 is count -800 on both)."""
    return np.rint(np.asarray(p, float) * SPU).astype(np.int64)


def on_grid(p: np.ndarray) -> np.ndarray:
    """p on a 0.01 grid, A moved off a half step: Marlin rounds 32-bit floats, so at a half
    step the two could count one step apart (X Y Z on the grid are never near one)."""
    q = np.round(np.asarray(p, float), 2)
    while abs((q[3] * SPU[3]) % 1.0 - 0.5) < 0.05:
        q[3] = round(q[3] + 0.01, 2)
    return q


def unit(v: np.ndarray) -> np.ndarray:
    """v / |v| (v nonzero)."""
    return v / float(np.linalg.norm(v))


def turned(rng: random.Random, d: np.ndarray, degrees: float) -> np.ndarray:
    """The XYZ direction d turned by `degrees` towards a random direction."""
    r = np.array([rng.gauss(0, 1) for _ in range(3)])
    r -= np.dot(r, d) * d
    if np.linalg.norm(r) < 1e-6:
        return d
    t = math.radians(degrees)
    return unit(math.cos(t) * d + math.sin(t) * unit(r))


def random_direction(rng: random.Random) -> np.ndarray:
    """A direction in one, two or all three of X Y Z (mostly flat: Z is slow)."""
    v = np.zeros(3)
    while np.linalg.norm(v) < 1e-3:
        for a in rng.sample(range(3), rng.randint(1, 3)):
            v[a] = rng.gauss(0, 0.3 if a == 2 else 1.0)
    return unit(v)


def polyline(rng: random.Random, start: np.ndarray) -> Group:
    """Moves of any length in X Y Z (some with A turning along): straight on, small and
    large turns, reversals, A alone, and blocks too short for Marlin to keep (< 6 steps)."""
    g = Group("polyline", start)
    d, a_rate = random_direction(rng), 0.0
    for i in range(rng.randint(3, 14)):
        kind = rng.choices(["straight", "small", "large", "reverse", "new", "A"],
                           [3, 3, 2, 1, 2, 1])[0]
        f = rng.choice(FEEDS) if i == 0 or rng.random() < 0.3 else None
        if kind == "A":
            g.add(g.end + np.array([0, 0, 0, rng.choice([-1, 1]) * rng.uniform(2, 90)]),
                  rng.choice(A_FEEDS))
            continue
        if kind == "small":
            d = turned(rng, d, rng.uniform(1, 30))
        elif kind == "large":
            d = turned(rng, d, rng.uniform(45, 150))
        elif kind == "reverse":
            d = -d
        elif kind == "new":
            d = random_direction(rng)
            a_rate = rng.choice([0.0, 0.0, rng.uniform(-5, 5)])  # deg per mm
        length = rng.choices([rng.uniform(0.03, 0.07), rng.uniform(0.2, 1.0),
                              rng.uniform(1, 20), rng.uniform(20, 80)], [1, 3, 5, 3])[0]
        step = np.append(d * length, a_rate * length)
        out = (g.end + step < LO) | (g.end + step > HI)
        step[out] = -step[out]  # turn back from a limit
        d = unit(step[:3]) if np.linalg.norm(step[:3]) > 0 else d
        g.add(g.end + step, f)
    return g


def runup(rng: random.Random, start: np.ndarray) -> Group:
    """An auto scan's line: a run-up cut into 8 mm pieces along X (Z climbing in some of
    them), the line itself, and a run-out."""
    g = Group("run-up", start)
    sx = 1.0 if start[0] < 200 else -1.0
    feed = rng.choice(FEEDS[2:])
    pieces = rng.randint(3, 6)
    climb = rng.random() < 0.6
    first = start.copy()
    first[1] = rng.uniform(LO[1], HI[1])  # to the line's start, then along it
    first[2] = rng.uniform(LO[2], 30.0)
    g.add(first, feed)
    for i in range(pieces):
        dz = rng.uniform(0.2, 2.0) if climb and 0 < i < pieces - 1 else 0.0
        g.add(g.end + np.array([8.0 * sx, 0.0, dz, 0.0]))
    g.add(g.end + np.array([sx * rng.uniform(10, 150), 0, 0, 0]))
    for _ in range(rng.randint(0, 2)):
        g.add(g.end + np.array([8.0 * sx, 0.0, 0.0, 0.0]))
    return g


def xy_line(rng: random.Random, start: np.ndarray) -> Group:
    """A line that follows an outline: 8 mm in X per move, Y changing a little each time."""
    g = Group("xy-line", start)
    sx = 1.0 if start[0] < 200 else -1.0
    g.add(start + np.array([0.0, 0.0, 0.0, 0.0]), rng.choice(FEEDS[1:4]))
    dy = rng.uniform(-0.5, 0.5)
    for _ in range(rng.randint(6, 24)):
        dy = float(np.clip(dy + rng.uniform(-0.3, 0.3), -1.0, 1.0))
        if not LO[1] < g.end[1] + dy < HI[1]:
            dy = -dy
        g.add(g.end + np.array([8.0 * sx, dy, 0.0, 0.0]), None)
    return g


def short_arc(rng: random.Random, start: np.ndarray) -> Group:
    """Pieces under 1 mm turning a few degrees each in X Y (an arc of short blocks)."""
    g = Group("short-arc", start)
    d = unit(np.array([rng.gauss(0, 1), rng.gauss(0, 1), 0.0]))
    sign = rng.choice([-1, 1])
    feed = rng.choice(FEEDS[1:5])
    for i in range(rng.randint(8, 24)):
        t = math.radians(sign * rng.uniform(1, 15))
        d = np.array([math.cos(t) * d[0] - math.sin(t) * d[1],
                      math.sin(t) * d[0] + math.cos(t) * d[1], 0.0])
        step = np.append(d * rng.uniform(0.3, 0.95), 0.0)
        if np.any((g.end + step < LO) | (g.end + step > HI)):
            d, step = -d, -step
        g.add(g.end + step, feed if i == 0 else None)
    return g


def back_and_forth(rng: random.Random, start: np.ndarray) -> Group:
    """Scan lines joined by reversals and by right angles (a Y step between two lines)."""
    g = Group("back-forth", start)
    length = rng.uniform(5, 60)
    sx = 1.0 if start[0] < 200 else -1.0
    feed = rng.choice(FEEDS[2:])
    for i in range(rng.randint(2, 6)):
        g.add(g.end + np.array([sx * length, 0, 0, 0]), feed if i == 0 else None)
        if rng.random() < 0.5:
            dy = rng.uniform(0.5, 5) * (1 if g.end[1] < 200 else -1)
            g.add(g.end + np.array([0, dy, 0, 0]))
        sx = -sx
    return g


PATTERNS = (polyline, polyline, runup, xy_line, short_arc, back_and_forth)


def motion_groups(rng: random.Random, n: int) -> list[Group]:
    """n sequences, each starting where the last one ended (the first at HOME); in some the
    host waits before one of the lines, so the queue may have run down to the running block."""
    out, at = [], HOME.copy()
    while len(out) < n:
        g = PATTERNS[len(out) % len(PATTERNS)](rng, at)
        if not g.moves:
            continue
        if rng.random() < 0.2 and len(g.moves) > 1:
            i = rng.randrange(1, len(g.moves))
            q, f, _ = g.moves[i]
            g.moves[i] = (q, f, rng.uniform(0.05, 0.6))
        if out:
            g.planner0 = out[-1].planner_path()[-1]
        out.append(g)
        at = g.end
    return out


def send_both(stages: list[Stage], cmd: str, n: int, gap: float = 0.0,
              timeout_s: float = 120.0) -> list[list[str]]:
    """After `gap` s, the numbered line to both at the same instant; both run in lock-step
    until each has answered it. Returns each one's replies (busy lines left out)."""
    for _ in range(round(gap / STEP_S)):
        for s in stages:
            s.tick()
    body = f"N{n} {cmd}"
    raw = f"{body}*{checksum(body)}\n".encode()
    for s in stages:
        s.sim.write("stage", raw)
    replies: list[list[str]] = [[] for _ in stages]
    done = [False] * len(stages)
    for _ in range(round(timeout_s / STEP_S)):
        for i, s in enumerate(stages):
            s.tick()
            for text in s.lines():
                if text != BUSY:
                    replies[i].append(text)
                done[i] = done[i] or text.startswith(f"ok N{n} ")
        if all(done):
            return replies
    return [r + ([] if d else ["(no ok)"]) for r, d in zip(replies, done)]


def align(stages: list[Stage]) -> None:
    """Run the stage that is behind up to the other's time (on the same STEP_S grid)."""
    ahead = max(s.sim.t for s in stages)
    for s in stages:
        while s.sim.t < ahead - STEP_S / 2:
            s.tick()


def run_group(stages: list[Stage], group: Group, n: int) -> tuple[list[Recording], int,
                                                                    list[str]]:
    """Send the group's lines and an M400, recording both stages' steps from the first line
    on. Returns the recordings, the last line number and any reply that was not a bare ok."""
    align(stages)
    for s in stages:
        s.rec = Recording(s.sim.stage, s.sim.t)
    odd = []
    for line, (_, _, gap) in list(zip(group.lines(), group.moves)) + [("M400", (0, 0, 0.0))]:
        n += 1
        for who, r in zip(("emulator", "Marlin"), send_both(stages, line, n, gap)):
            if len(r) != 1 or not r[0].startswith(f"ok N{n} "):
                odd.append(f"{who} to N{n} {line}: {r}")
    for _ in range(4):  # the last step is before the M400's ok
        for s in stages:
            s.tick()
    recs = [s.rec for s in stages]
    for s in stages:
        s.rec = None
    return recs, n, odd


class Recording:
    """One stage's STEP edges per axis and its position on the sample grid, from t0 on."""

    def __init__(self, board: object, t0: float) -> None:
        self.board = board
        self.t0 = self.last = t0
        self.start = np.asarray(board.position_at(t0), float)
        self.edges: list[list[np.ndarray]] = [[] for _ in AXES]
        self.seen = [t0] * len(AXES)  # the last edge taken per axis
        self.pos: list[np.ndarray] = []
        self.k = 1  # next sample (k * SAMPLE_S after t0)

    def pull(self, now: float) -> None:
        """The edges up to now and the samples up to the tick before: the emulator starts a
        block whose third block came at the last tick at that very instant (Marlin's ISR
        takes it a moment later), so that tick is looked at again."""
        for a in range(len(AXES)):
            e = self.board.step_edges(a, self.last - STEP_S, now)
            e = e[e > self.seen[a]]
            if len(e):
                self.seen[a] = float(e[-1])
                self.edges[a].append(e - self.t0)
        while self.t0 + self.k * SAMPLE_S <= self.last:
            self.pos.append(np.asarray(self.board.position_at(self.t0 + self.k * SAMPLE_S))
                            - self.start)
            self.k += 1
        self.last = now

    def axis_edges(self, a: int) -> np.ndarray:
        """Times of the axis's STEP edges (s after t0)."""
        return np.concatenate(self.edges[a]) if self.edges[a] else np.zeros(0)

    def positions(self) -> np.ndarray:
        """(samples, axes): where it was k * SAMPLE_S after t0, from where it started."""
        return np.array(self.pos)

    def block_ends(self, steps: np.ndarray) -> np.ndarray | None:
        """When each block took its last step (s after t0), from the steps each block makes
        (both stages step each block's steps in one direction); None if the edges counted
        are not the blocks' steps."""
        edges = [self.axis_edges(a) for a in range(len(AXES))]
        cum = np.cumsum(steps, axis=0)
        if any(len(e) != c for e, c in zip(edges, cum[-1])):
            return None
        out, end = [], 0.0
        for k in range(len(steps)):  # a dropped move (no steps) ends with the one before
            end = max((edges[a][cum[k, a] - 1] for a in range(len(AXES)) if steps[k, a]),
                      default=end)
            out.append(end)
        return np.array(out)

    def counts(self) -> list[int]:
        """STEP edges per axis."""
        return [len(self.axis_edges(a)) for a in range(len(AXES))]


@dataclass
class Figures:
    """The emulator against Marlin on one group (times in s, Marlin's minus the emulator's):
    first step, each block's time, each block's end; the largest position difference per
    axis beyond the time allowance (mm, deg); and what failed."""

    start_diff: float
    block_diff: np.ndarray
    end_diff: np.ndarray
    total: tuple[float, float]
    pos_diff: np.ndarray
    pos_raw: np.ndarray
    failures: list[str]


def compare(group: Group, recs: list[Recording], tol: Tolerance) -> Figures:
    """The emulator's recording (recs[0]) against Marlin's (recs[1])."""
    steps = group.block_steps()
    lines = group.lines()
    fails = []
    first = [min((float(e[0]) for e in (r.axis_edges(a) for a in range(len(AXES))) if len(e)),
                 default=0.0) for r in recs]
    last = [max((float(e[-1]) for e in (r.axis_edges(a) for a in range(len(AXES))) if len(e)),
                default=0.0) for r in recs]
    if abs(first[1] - first[0]) > tol.start_s:
        fails.append(f"the first step {first[0]:.4f} s after the first line on the emulator, "
                     f"{first[1]:.4f} s on Marlin")
    ends = [r.block_ends(steps) for r in recs]
    block_diff = end_diff = np.zeros(0)
    if ends[0] is None or ends[1] is None:
        fails.append(f"STEP edges per axis: emulator {recs[0].counts()}, Marlin "
                     f"{recs[1].counts()}, the moves' {steps.sum(axis=0).tolist()}")
    else:
        ends = [e - f for e, f in zip(ends, first)]  # from the first step
        end_diff = ends[1] - ends[0]
        durs = [np.diff(np.concatenate([[0.0], e])) for e in ends]
        block_diff = durs[1] - durs[0]
        for k in np.flatnonzero(np.abs(block_diff) > tol.abs_s + tol.rel * durs[1]):
            fails.append(f"block {k + 1} ({lines[k]}) takes {1e3 * durs[0][k]:.1f} ms on the "
                         f"emulator, {1e3 * durs[1][k]:.1f} ms on Marlin")
        for k in np.flatnonzero(np.abs(end_diff) > tol.abs_s + tol.rel * ends[1]):
            fails.append(f"block {k + 1} ({lines[k]}) ends {ends[0][k]:.4f} s after the first "
                         f"step on the emulator, {ends[1][k]:.4f} s on Marlin")
    took = [y - x for x, y in zip(first, last)]
    if abs(took[1] - took[0]) > tol.abs_s + tol.rel * took[1]:
        fails.append(f"the sequence takes {took[0]:.4f} s on the emulator, {took[1]:.4f} s on "
                     f"Marlin")
    shift = [int(round(f / SAMPLE_S)) for f in first]  # the samples from each first step on
    pos = [r.positions()[max(k - 1, 0):] for r, k in zip(recs, shift)]
    m = max(len(p) for p in pos)
    pos = [np.concatenate([p, np.repeat(p[-1:], m - len(p), axis=0)]) for p in pos]
    t = SAMPLE_S * np.arange(m)
    v_top = np.abs(np.diff(pos[1], axis=0)).max(axis=0) / SAMPLE_S  # the axes' top speeds
    lag = tol.abs_s + tol.rel * t
    diff = np.abs(pos[1] - pos[0])
    over = diff - lag[:, None] * v_top[None, :]  # beyond what the allowed lag explains
    pos_diff = over.max(axis=0)
    for a in np.flatnonzero(pos_diff > np.array(tol.pos)):
        k = int(np.argmax(over[:, a]))
        fails.append(f"{AXES[a]} apart by {diff[k, a]:.4f} {t[k]:.4f} s after the first step "
                     f"(emulator "
                     f"{pos[0][k, a]:+.4f}, Marlin {pos[1][k, a]:+.4f} from the start)")
    return Figures(first[1] - first[0], block_diff, end_diff, (took[0], took[1]),
                   pos_diff, diff.max(axis=0), fails)


def motion(stages: list[Stage], groups: list[Group], tol: Tolerance,
           verbose: bool = True) -> list[Figures]:
    """Home both, then run each group on both and compare; prints each group's figures."""
    n = 0
    for cmd in ("G28", "G90", "M400"):
        n += 1
        send_both(stages, cmd, n)
    out = []
    for i, g in enumerate(groups):
        recs, n, odd = run_group(stages, g, n)
        f = compare(g, recs, tol)
        f.failures = odd + f.failures
        out.append(f)
        if verbose:
            worst = [float(np.max(np.abs(x))) if len(x) else math.nan
                     for x in (f.block_diff, f.end_diff)]
            print(f"motion {i + 1:3d} {g.kind:10s} {len(g.moves):2d} moves "
                  f"{f.total[0]:6.3f} s, Marlin {1e3 * (f.total[1] - f.total[0]):+6.2f} ms; "
                  f"start {1e3 * f.start_diff:+5.2f} ms, blocks within {1e3 * worst[0]:5.2f} "
                  f"ms, ends within {1e3 * worst[1]:5.2f} ms; |dpos| "
                  + " ".join(f"{a}{v:.3f}" for a, v in zip(AXES, f.pos_raw)))
            for x in f.failures:
                print(f"    {x}")
            if f.failures:
                print("    lines: " + " | ".join(g.lines()))
    return out


def summary(figs: list[Figures], groups: list[Group]) -> str:
    """The motion part's largest differences over all groups."""
    def worst(xs: list[np.ndarray]) -> float:
        xs = [np.abs(x) for x in xs if len(x)]
        return 1e3 * float(max(x.max() for x in xs)) if xs else math.nan
    pos = np.max([f.pos_raw for f in figs], axis=0)
    start = [1e3 * f.start_diff for f in figs]
    return (f"motion: {len(groups)} sequences, {sum(len(g.moves) for g in groups)} moves, "
            f"{sum(f.total[1] for f in figs):.1f} s; Marlin minus emulator: first step "
            f"{min(start):+.1f}..{max(start):+.1f} ms, block times within "
            f"{worst([f.block_diff for f in figs]):.1f} ms, block ends "
            f"within {worst([f.end_diff for f in figs]):.1f} ms, sequences within "
            f"{worst([np.array([f.total[1] - f.total[0]]) for f in figs]):.1f} ms; positions "
            f"apart by at most " + " ".join(f"{a}{v:.3f}" for a, v in zip(AXES, pos))
            + f"; {sum(bool(f.failures) for f in figs)} sequences outside the tolerance")


def main() -> int:
    """Run both, print the differences; exit 1 if any."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("elf")
    ap.add_argument("--lines", type=int, default=300)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--motion", type=int, default=30,
                    help="sequences of joined moves whose motion is compared (0: none)")
    args = ap.parse_args()
    stages = [Stage(""), Stage(args.elf)]
    for s in stages:
        s.exchange(f"N0 M110 N0*{checksum('N0 M110 N0')}\n", 0)
    n, diffs, history = 0, 0, []
    try:
        for cmd, numbered in commands(random.Random(args.seed), args.lines):
            if numbered:
                n += 1
                body = f"N{n} {cmd}"
                raw = f"{body}*{checksum(body)}\n"
            else:
                raw = cmd + "\n"
            emu, real = (s.exchange(raw, n if numbered else None) for s in stages)
            history.append(raw.strip())
            if not same(emu, real):
                diffs += 1
                print(f"--- after: {' | '.join(history[-4:-1])}\n>>> {raw.strip()}\n"
                      f"  emulator: {emu}\n  Marlin:   {real}")
                for s in stages:  # both idle again before the next line
                    s.exchange("M400\n", None)
    finally:
        for s in stages:
            s.close()
    print(f"{len(history)} lines, {diffs} with different replies")
    bad = 0
    if args.motion > 0:
        groups = motion_groups(random.Random(args.seed), args.motion)
        stages = [Stage(""), Stage(args.elf)]  # from power-up again, both in step
        try:
            figs = motion(stages, groups, Tolerance())
        finally:
            for s in stages:
                s.close()
        bad = sum(bool(f.failures) for f in figs)
        print(summary(figs, groups))
    return 1 if diffs or bad else 0


if __name__ == "__main__":
    sys.exit(main())
