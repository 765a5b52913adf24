"""Table sweeps: the turns, and each shot placed by the table's counted steps.

A sweep (plan mode "sweep") is how turntable scanners scan: the sensor stands outside the
object's bounding cylinder, its beam through the table axis, and the table turns under it,
one turn per G1 at one height (a ring, step_mm above the last), so the laser is idle only
while the table reverses. Its shots are placed by the table's steps.

The sensor board counts the STEP pulses of the stage's X and table (A) lines on two sync
inputs; each waveform carries, per input, the pulses of the open burst made before each of
its shots (summed over its n_average shots), and each burst is reported once its line has
been quiet for sync_quiet_ms (docs/protocol.md, motion_sync). Two facts make a move of
several axes placeable from one count:

- Marlin steps every axis of one G1 in proportion (Bresenham: each axis within one step of
  its share of the block's step events), so the share of one moving axis's steps done
  gives the position of all of them along the move;
- a move that starts slowly can be quiet on an input for longer than sync_quiet_ms between
  its first steps (a table turn from rest: sqrt(a / 2 * steps_per_deg) = 30 steps/s with the
  path's acceleration shared with X and Z), so one move may be reported as several bursts;
  `counted_steps` adds the bursts before the one a waveform falls in, and leaves out (NaN)
  a waveform whose shots straddle the start or end of a burst, where the board's per-shot
  count is not known from the sum.

Plain functions on numpy arrays: no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .plan import Point, ScanPlan, waveforms_per_turn


def counted_steps(timestamps: np.ndarray, sync_steps: np.ndarray, n_average: int,
                  period_ticks: float, bursts: Sequence[tuple[int, int, int]],
                  quiet_ticks: float, at_rest: bool = True) -> np.ndarray:
    """Each waveform's mean count of one input's steps since the first of `bursts` began.

    timestamps: device ticks of each waveform's first shot; sync_steps: that input's count
    of each waveform (summed over its n_average shots, `waveform.sync_steps` or
    `sync_steps_a`); period_ticks: ticks between laser shots; bursts: (first_edge,
    last_edge, edges) of that input's bursts since the arm, in ticks; quiet_ticks: the
    board's sync_quiet_ms in ticks. Placed: a waveform whose shots all fall before the
    first burst, within one burst (from its first edge to half the quiet time after its
    last), or after one and before the next (the axis at rest; unless at_rest is False: a
    sweep's table rests while Z steps to the next ring); NaN otherwise (its shots straddle a
    burst's start, or its end and the board's closing of it)."""
    ts = np.asarray(timestamps, dtype=np.float64)
    counts = np.asarray(sync_steps, dtype=np.float64)
    out = np.full(len(ts), np.nan)
    if not len(bursts):
        return np.where(counts == 0, 0.0, np.nan)  # no steps counted: none made
    b = np.array(sorted(bursts), dtype=np.float64).reshape(-1, 3)
    first, last, edges = b[:, 0], b[:, 1], b[:, 2]
    prior = np.concatenate([[0.0], np.cumsum(edges)[:-1]])  # steps of the bursts before
    end = ts + (n_average - 1) * period_ticks  # the waveform's last shot
    k = np.searchsorted(first, ts, side="right") - 1  # the burst begun by the first shot
    before = (k < 0) & (end < first[0]) & (counts == 0)
    out[before] = 0.0
    ok = k >= 0
    kk = np.clip(k, 0, None)
    nxt = np.where(kk + 1 < len(first), first[np.minimum(kk + 1, len(first) - 1)], np.inf)
    inside = ok & (end <= last[kk] + quiet_ticks / 2) & (end < nxt)
    out[inside] = prior[kk[inside]] + counts[inside] / n_average
    # at rest after a burst (before the next): every shot counts the whole burst while it
    # is open and nothing once it is closed, and the steps made are the burst's all along
    rest = ok & ~inside & (ts >= last[kk]) & (end < nxt) & at_rest
    whole = np.isclose(np.mod(counts, np.maximum(edges[kk], 1)), 0)
    rest &= whole & (counts <= n_average * edges[kk])
    out[rest] = prior[kk[rest]] + edges[kk[rest]]
    return out


def place_on_move(start: np.ndarray, delta: np.ndarray, steps_done: np.ndarray,
                  steps_total: int) -> np.ndarray:
    """Positions (one row per waveform; mm and deg as `start`) along one linear move from
    `start` by `delta`, from the counted steps of one of its moving axes (steps_done of
    steps_total): Marlin keeps every axis within one step of its share."""
    f = np.asarray(steps_done, dtype=np.float64)[:, None] / float(steps_total)
    return np.asarray(start, dtype=np.float64)[None, :] + f * np.asarray(delta)[None, :]


# ---------------------------------------------------------------------------- the sweep plan


@dataclass(frozen=True)
class Turn:
    """One turn of a sweep: the sensor at (x, y) mm (the stage frame) while Z goes from z0 to
    z1 mm (a sweep's rings: z0 == z1) and the table turns from a0 to a1 deg, in one G1
    (docs/scanning.md); pitch: the heights (mm) a ring stands for, z0 +- pitch / 2; offset:
    its pass's, mm across the beam from the table axis (plan.offsets_mm)."""

    index: int
    x: float
    y: float
    z0: float
    z1: float
    a0: float
    a1: float
    pitch: float = 0.0
    offset: float = 0.0

    def steps(self, spu: Sequence[float]) -> tuple[int, int]:
        """(Z steps, table steps) of the move, as Marlin rounds each end to whole steps."""
        return (abs(round(self.z1 * spu[2]) - round(self.z0 * spu[2])),
                abs(round(self.a1 * spu[3]) - round(self.a0 * spu[3])))


def sweep_turns(plan: ScanPlan, v: np.ndarray, X_R: np.ndarray,
                n: np.ndarray | None = None) -> list[Turn]:
    """The sweep's turns: the sensor standoff_mm outside the bounding cylinder, its beam
    through the table axis; one flat turn (a ring) every step_mm at most (a whole number of
    them, each standing for pitch mm of height: rings at the middles of equal slices) over
    the heights that put the beam on every surface between the cylinder and the axis within
    the band of levels_mm (a beam that dips or climbs along the table axis n meets a surface
    at the axis that much below or above the sensor: the rings start and end so much later;
    one ring with one level and a level beam); the table from 0 to 360 deg and back, turn
    after turn (A stays within one revolution), Z stepping to the next ring while the table
    reverses. Rings, not a helix: a helix that reverses leaves its turns 2 x step_mm apart
    where it reverses (the pear's foot had 4 mm gaps there), rings step_mm everywhere. One
    pass per offset in plan.offsets_mm (mm): the sensor moved that far across the beam in
    the table plane (+: to the beam's left seen from above), the passes climbing and
    descending in turn, so one pass ends where the next begins but for the offset (a move
    across the beam, outside the cylinder)."""
    v = np.asarray(v, float) / np.linalg.norm(v)
    n = np.array([0.0, 0.0, 1.0]) if n is None else np.asarray(n, float) / np.linalg.norm(n)
    vxy = v[:2] / np.linalg.norm(v[:2])
    left = np.array([-vxy[1], vxy[0]])
    base = np.asarray(X_R, float)[:2] - (plan.radius_mm + plan.standoff_mm) * vxy
    rise = float(v @ n)  # the beam's rise (mm along n) a mm along it
    near, far = plan.standoff_mm, plan.standoff_mm + plan.radius_mm
    lo = min(plan.levels_mm) - max(rise * near, rise * far)  # low enough at every depth,
    hi = max(plan.levels_mm) - min(rise * near, rise * far)  # high enough at every depth
    k = max(math.ceil((hi - lo) / plan.step_mm - 1e-9), 1)
    pitch = (hi - lo) / k if hi > lo else 0.0
    z = float(X_R[2]) + lo
    turns: list[Turn] = []
    for p, d in enumerate(plan.offsets_mm):
        x, y = base + float(d) * left
        for j in range(k):
            ring = j if p % 2 == 0 else k - 1 - j  # a descending pass starts at the top
            zr = z + (ring + 0.5) * pitch
            i = len(turns)
            turns.append(Turn(i, float(x), float(y), zr, zr, 0.0 if i % 2 == 0 else 360.0,
                              360.0 if i % 2 == 0 else 0.0, pitch, float(d)))
    return turns


def passes(turns: list[Turn]) -> list[list[Turn]]:
    """The turns grouped into passes: runs of turns at one (x, y)."""
    out: list[list[Turn]] = []
    for t in turns:
        if out and (out[-1][-1].x, out[-1][-1].y) == (t.x, t.y):
            out[-1].append(t)
        else:
            out.append([t])
    return out


def sweep_points(plan: ScanPlan, turns: list[Turn], a_max_deg_s: float) -> list[Point]:
    """The sweep's planned points: one per waveform the laser gives while a turn runs at its
    pass's speed (plan.waveforms_per_turn, the table at most a_max_deg_s; where they are
    expected: the stored ones are placed by the counts)."""
    pts: list[Point] = []
    for t in turns:
        per = waveforms_per_turn(plan, a_max_deg_s, t.offset)
        for c in range(per):
            f = c / per
            pts.append(Point(len(pts), t.x, t.y, t.z0 + f * (t.z1 - t.z0),
                             t.a0 + f * (t.a1 - t.a0), t.index, c, 0, line=t.index))
    return pts


def sweep_feed_mm_min(turn: Turn, speed_deg_s: float) -> float:
    """G1's F (mm/min) for a turn at speed_deg_s: Marlin's F is the linear axes' speed
    when any moves (Z's climb over the turn's time), else the table's in deg/min."""
    t = abs(turn.a1 - turn.a0) / speed_deg_s
    dz = abs(turn.z1 - turn.z0)
    return max(dz / t * 60.0, 1.0) if dz > 0 else speed_deg_s * 60.0


# ---------------------------------------------------------------------------- coverage


def beam_heights_mm(S: np.ndarray, v: np.ndarray, n: np.ndarray, X_R: np.ndarray,
                    radius_mm: float) -> tuple[float, float]:
    """Heights (mm, object frame: along the table axis n from X_R) at which the beam from the
    stage position S along v enters the bounding cylinder (radius_mm about the axis) and
    passes the axis (closest approach): a surface the beam meets lies between the two."""
    S, v, n, X_R = (np.asarray(a, float) for a in (S, v, n, X_R))
    v, n = v / np.linalg.norm(v), n / np.linalg.norm(n)
    w = S - X_R
    b, d, e = float(v @ n), float(v @ w), float(n @ w)
    den = 1.0 - b * b
    t = (b * e - d) / den if den > 1e-12 else 0.0  # along the beam to the axis
    t_in = t - radius_mm / math.sqrt(max(den, 1e-12))  # across the radius, off the axis
    return float(n @ (w + t_in * v)), float(n @ (w + t * v))


def sweep_coverage(points_mm: dict[str, np.ndarray], radius_mm: float, height_mm: float,
                   band_mm: tuple[float, float], spacing_mm: float) -> dict[str, float]:
    """What a sweep covered of its band, from its own object-frame points (mm, per modality).

    The outline r(phi, z) they measure (outline_from_points: 5 deg by spacing_mm cells, a gap
    of up to two cells in a row closed between measured ones) over the rows whose middle lies
    in band_mm (the heights the beam crossed at every radius; the row nearest its middle if
    none); a cell the sweep passed between (its rings are up to step_mm apart in height)
    takes the radius of the nearest closed cell above or below it. Per
    modality: the share of the band's cells whose surface point has a point of that
    modality within spacing_mm, a direction with no echo at any height counted as not
    covered; `directions`: the share of the 5 deg directions about the axis in which the
    sweep found the surface in the band. Cells are 5 deg of azimuth: a share of directions
    about the axis, not of area."""
    from .coverage import covered_mask
    from .outline import outline_from_points

    pts = {m: np.asarray(p, float).reshape(-1, 3) for m, p in points_mm.items()}
    out = outline_from_points(np.vstack([np.empty((0, 3)), *pts.values()]), radius_mm,
                              height_mm, z_step_mm=spacing_mm)
    lo, hi = sorted(band_mm)
    e = out.z_edges_mm
    mid = 0.5 * (e[1:] + e[:-1])
    rows = (mid >= lo) & (mid <= hi)
    if not rows.any():
        rows[int(np.argmin(np.abs(mid - 0.5 * (lo + hi))))] = True
    r = out.filled_r_mm()
    closed = np.isfinite(r[:, rows])
    cells = closed.size
    # each band cell's radius: its own, else the nearest closed cell's of its column
    jj = np.arange(r.shape[1])
    dist = np.where(np.isfinite(r)[:, None, :],  # (nphi, band rows, nz): the band's alone
                    np.abs(jj[rows][None, :, None] - jj[None, None, :]), np.inf)
    rr = np.take_along_axis(r, np.argmin(dist, axis=2), axis=1)  # NaN: a column with none
    i, j = np.nonzero(np.isfinite(rr))
    phi = np.radians((i + 0.5) * out.phi_step_deg)
    ref = np.column_stack([rr[i, j] * np.cos(phi), rr[i, j] * np.sin(phi), mid[rows][j]])
    res = {m: round(float(covered_mask(ref, p, spacing_mm).sum()) / cells, 4)
           for m, p in pts.items()}
    res["directions"] = round(float(closed.any(axis=1).mean()), 4)
    return res
