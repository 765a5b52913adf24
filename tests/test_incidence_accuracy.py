"""bench/incidence_accuracy.py: a scan's error by the incidence at which its beam met the true
surface, the figure issue 32 holds against the paper's head-on accuracies. Points placed off a
turned box's face by known distances land in the bin of the face's turn, with those
distances' mean and std."""

import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh
from hypothesis import assume, given, settings
from hypothesis import strategies as st

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from incidence_accuracy import BINS_DEG, by_incidence, pooled  # noqa: E402
from scan_coverage import object_frame  # noqa: E402

from dmdsm.sim.physics.mesh import ObjectTruth  # noqa: E402

V = np.array([0.0, 1.0, 0.0])  # the beam, along +y (the stage's and object's frames agree)
N = np.array([0.0, 0.0, 1.0])
X_R = np.zeros(3)


def turned_box(alpha_deg: float) -> ObjectTruth:
    """A 40 x 20 x 40 mm box 50 mm along the beam, turned alpha about the vertical."""
    a = np.radians(alpha_deg)
    R = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0, 0, 1.0]])
    mesh = trimesh.creation.box(extents=(40.0, 20.0, 40.0))
    return ObjectTruth("box", "plastic", mesh, np.array([0.0, 50.0, 0.0]), R,
                       np.full(len(mesh.faces), "plastic", dtype=object))


@settings(max_examples=25, deadline=None)
@given(st.floats(1.0, 60.0), st.floats(0.0, 0.3), st.integers(0, 2**31 - 1))
def test_points_off_a_turned_face_land_in_its_bin_with_their_error(alpha, spread, seed):
    assume(min(abs(alpha - b) for b in BINS_DEG) > 0.01)  # not on a bin's edge
    box = turned_box(alpha)
    rng = np.random.default_rng(seed)
    k = 200
    local = np.column_stack([rng.uniform(-15, 15, k), np.full(k, -10.0), rng.uniform(-15, 15, k)])
    e = rng.uniform(0.0, spread, k)
    normal = box.R @ np.array([0.0, -1.0, 0.0])  # the face toward the sensor, outward
    P = local @ box.R.T + box.center + e[:, None] * normal
    S = P - 30.0 * V
    bins = by_incidence(P, S, np.zeros(k), V, N, X_R, [box], object_frame)
    want = int(np.searchsorted(BINS_DEG, alpha, side="right") - 1)
    assert [b["n"] for b in bins] == [k if i == want else 0 for i in range(len(bins))]
    assert bins[want]["mean_mm"] == pytest.approx(e.mean(), abs=1e-6)
    assert bins[want]["std_mm"] == pytest.approx(e.std(), abs=1e-6)


def test_pooled_bins_are_the_bins_of_all_the_points():
    rng = np.random.default_rng(1)
    box = turned_box(5.0)
    runs, every = [], []
    for k in (50, 120):
        local = np.column_stack([rng.uniform(-15, 15, k), np.full(k, -10.0),
                                 rng.uniform(-15, 15, k)])
        e = rng.uniform(0.0, 0.4, k)
        P = local @ box.R.T + box.center + e[:, None] * (box.R @ np.array([0.0, -1.0, 0.0]))
        runs.append(by_incidence(P, P - 30.0 * V, np.zeros(k), V, N, X_R, [box], object_frame))
        every.append(e)
    both = pooled(runs)[0]
    e = np.concatenate(every)
    assert both["n"] == len(e) and both["mean_mm"] == pytest.approx(e.mean(), abs=1e-9)
    assert both["std_mm"] == pytest.approx(e.std(), abs=1e-9)
