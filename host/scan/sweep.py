"""Shots placed on moves of several axes by one axis's counted steps (the table's, for sweeps).

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

from collections.abc import Sequence

import numpy as np


def counted_steps(timestamps: np.ndarray, sync_steps: np.ndarray, n_average: int,
                  period_ticks: float, bursts: Sequence[tuple[int, int, int]],
                  quiet_ticks: float) -> np.ndarray:
    """Each waveform's mean count of one input's steps since the first of `bursts` began.

    timestamps: device ticks of each waveform's first shot; sync_steps: that input's count
    of each waveform (summed over its n_average shots, `waveform.sync_steps` or
    `sync_steps_a`); period_ticks: ticks between laser shots; bursts: (first_edge,
    last_edge, edges) of that input's bursts since the arm, in ticks; quiet_ticks: the
    board's sync_quiet_ms in ticks. Placed: a waveform whose shots all fall before the
    first burst, within one burst (from its first edge to half the quiet time after its
    last), or after one and before the next (the axis at rest); NaN otherwise (its shots
    straddle a burst's start, or its end and the board's closing of it)."""
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
    rest = ok & ~inside & (ts >= last[kk]) & (end < nxt)
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
