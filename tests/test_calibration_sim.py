"""Calibration against the emulator's physics over repeated seeds: the host's rig procedure,
center points and solver recover Table I within the reported uncertainties, those
uncertainties match the spread over seeds, and the filament-radius bias is gone."""

import numpy as np
import pytest

from dmdsm.host.calibration.center_points import center_points
from dmdsm.host.calibration.rig_file import COLUMNS
from dmdsm.host.calibration.solver import solve, tangent_errors
from dmdsm.sim.data.rig_data import record

SEEDS = range(12)
COORDS = ("v t1", "v t2", "n t1", "n t2", "X_R x", "X_R y")


def as_raw(rows):
    """Rows as read_raw returns them."""
    return {c: np.array([r[c] for r in rows], dtype=str if c in ("step", "modality")
                        else float) for c in COLUMNS}


def errors(result, truth):
    """(errors, reported std) over COORDS: unit vectors in their tangent planes, X_R in x, y."""
    e, s = [], []
    for name in ("v", "n"):
        err, sd = tangent_errors(result, name, np.array(truth[name]))
        e += list(err)
        s += list(sd)
    e += list((result.X_R - np.array(truth["X_R"]))[:2])
    s += list(result.std["X_R"][:2])
    return np.array(e), np.array(s)


@pytest.fixture(scope="module")
def recordings():
    return [record(seed) for seed in SEEDS]


def test_truth_within_reported_uncertainty_and_spread_matches_it(recordings):
    errs, sds = [], []
    for rows, truth in recordings:
        e, s = errors(solve(center_points(as_raw(rows))), truth)
        errs.append(e)
        sds.append(s)
        z = e / s
        assert (np.abs(z) <= 4).all(), f"seed {truth['seed']}: error/std {np.round(z, 1)}"
    errs, sds = np.array(errs), np.array(sds)
    # RMS of error / std per coordinate: 1 when the reported stds hold (12 seeds give it to
    # about +-20 %); a covariance that ignored the surface's share of the edge depths was
    # ~6x too small in n and X_R y, and the raster's Sigma_P / n (before its scale was
    # estimated) made v and X_R x ~1.4x too large
    rms_z = np.sqrt(np.mean((errs / sds) ** 2, axis=0))
    assert ((rms_z > 0.6) & (rms_z < 1.5)).all(), dict(zip(COORDS, np.round(rms_z, 2)))


def test_filament_radius_bias_is_gone(recordings):
    """X_R along the beam: on the axis with the spot model; behind the front surface by
    about the radius without correction, ~0.05 mm off with a constant radius."""
    along = {"model": [], "none": [], "constant": []}
    for rows, truth in recordings:
        v = np.array(truth["v"])
        raw = as_raw(rows)
        along["model"].append((solve(center_points(raw)).X_R - truth["X_R"]) @ v)
        plain = center_points(raw, radius_mm=0.0)
        along["none"].append((solve(plain).X_R - truth["X_R"]) @ v)
        plain.filament_radius_mm = 0.25  # every hit moved by the radius, whatever its offset
        along["constant"].append((solve(plain).X_R - truth["X_R"]) @ v)
    m = {k: float(np.mean(a)) for k, a in along.items()}
    se = float(np.std(along["model"]) / np.sqrt(len(SEEDS)))
    assert abs(m["model"]) < max(3 * se, 0.01), m
    assert m["none"] < -0.15, m  # X_R pulled toward the sensor by ~0.2 mm
    assert m["constant"] > m["model"] + 0.02, m


def test_center_points_lateral_covariance_matches_their_true_scatter(recordings):
    """The raster model of a thresholded centroid (raster_centroid_cov) against the truth: the
    tip centers' scatter across the beam and the edge centers' across the filament agree with
    the declared std within 1.6x (Sigma_P / n, the points' spread / n, claimed ~3x)."""
    from dmdsm.sim.physics.objects import rig_horizontal, rig_vertical
    from dmdsm.sim.physics.scene import rodrigues, table_frame

    horizontal, vertical = rig_horizontal()[0].shape, rig_vertical()[0].shape
    tip_local = horizontal.center - horizontal.half_length * horizontal.R[:, 2]  # toward -y
    tip_err, tip_sd, edge_err, edge_sd = [], [], [], []
    for rows, truth in recordings:
        data = center_points(as_raw(rows))
        v, n, X_R = (np.array(truth[k]) for k in ("v", "n", "X_R"))
        B = table_frame(n)
        rel = data.tip_S - (X_R + B @ tip_local)
        tip_err += list((rel - np.outer(rel @ v, v))[:, [0, 2]].ravel())
        tip_sd += list(np.sqrt(data.tip_cov_S[:, [0, 2], [0, 2]]).ravel())
        w = np.cross(n, v) / np.linalg.norm(np.cross(n, v))  # across the filament and beam
        for f in np.unique(data.edge_frame):
            sel = data.edge_frame == f
            axis = X_R + rodrigues(n, np.radians(data.theta_deg[int(f)])) @ B @ vertical.center
            edge_err += list((data.edge_S[sel] + data.edge_d[sel, None] * v - axis) @ w)
            edge_sd += list(np.sqrt(data.edge_cov_S[sel, 0, 0]))
    for err, sd in ((tip_err, tip_sd), (edge_err, edge_sd)):
        ratio = np.sqrt(np.mean(np.square(err))) / np.median(sd)
        assert 1 / 1.6 < ratio < 1.6, ratio
