"""Placing shots by one input's counted steps across the bursts one slow-starting move may be
reported as (host/scan/sweep.py), against a model of the board's counting."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from dmdsm.host.scan.sweep import counted_steps, place_on_move

QUIET = 20_000  # ticks (sync_quiet_ms at 1 MHz ticks, for the model)
PERIOD = 1_000  # ticks between laser shots


def board_counts(edges: np.ndarray, shots: np.ndarray) -> tuple[np.ndarray, list]:
    """What the board reports: per shot, the edges of the burst open then made up to the
    shot (0 with none open); and the bursts (first, last, edges), a gap >= QUIET ending one."""
    cut = np.nonzero(np.diff(edges) >= QUIET)[0] + 1
    groups = np.split(edges, cut) if len(edges) else []
    bursts = [(int(g[0]), int(g[-1]), len(g)) for g in groups]
    counts = np.zeros(len(shots), int)
    for i, t in enumerate(shots):
        for g in groups:
            if g[0] <= t < g[-1] + QUIET:
                counts[i] = int(np.sum(g <= t))
    return counts, bursts


@st.composite
def edge_trains(draw):
    """A few runs of steps, some apart by more than QUIET (a slow start splits a move)."""
    t, edges = 5_000, []
    for _ in range(draw(st.integers(1, 4))):
        n = draw(st.integers(1, 60))
        gap = draw(st.integers(300, 3_000))
        edges += [t + gap * i for i in range(n)]
        t = edges[-1] + draw(st.sampled_from([2_000, 15_000, 21_000, 60_000]))
    return np.array(edges, np.int64)


@settings(max_examples=200, deadline=None)
@given(edges=edge_trains(), n_avg=st.sampled_from([1, 4, 12]))
def test_counted_steps_are_the_steps_made_whatever_the_bursts(edges, n_avg):
    shots = np.arange(0, int(edges[-1]) + 3 * QUIET, PERIOD)
    counts, bursts = board_counts(edges, shots)
    n = len(shots) // n_avg
    ts = shots[:n * n_avg:n_avg]
    sums = counts[:n * n_avg].reshape(n, n_avg).sum(axis=1)
    got = counted_steps(ts, sums, n_avg, PERIOD, bursts, QUIET)
    made = np.array([np.sum(edges <= t) for t in shots[:n * n_avg]]).reshape(n, n_avg)
    want = made.mean(axis=1)
    ok = np.isfinite(got)
    assert np.allclose(got[ok], want[ok])
    # every waveform whose shots lie inside one burst, or all between two (the axis at
    # rest), is placed
    starts = [f for f, _, _ in bursts] + [np.inf]
    for i in range(n):
        lo, hi = ts[i], ts[i] + (n_avg - 1) * PERIOD
        if any(f <= lo and hi <= la for f, la, _ in bursts) or \
                any(la <= lo and hi < nxt for (_, la, _), nxt in zip(bursts, starts[1:])):
            assert ok[i], (i, lo, hi, bursts)


def test_place_on_move_puts_every_axis_at_its_share():
    start, delta = np.array([200.0, 300.0, 20.0, 10.0]), np.array([2.0, 0.0, 1.5, 300.0])
    p = place_on_move(start, delta, np.array([0.0, 1333.5, 2667.0]), 2667)
    assert np.allclose(p[0], start) and np.allclose(p[2], start + delta)
    assert np.allclose(p[1], start + delta / 2)


def test_a_waveform_with_steps_but_no_burst_reported_is_not_placed():
    got = counted_steps(np.array([0, 100_000]), np.array([0, 5]), 1, PERIOD, [], QUIET)
    assert got[0] == 0 and np.isnan(got[1])
