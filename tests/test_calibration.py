"""Scanner calibration solvers: exact recovery without noise, honest covariances with noise."""

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from dmdsm.host.calibration.solver import (
    CalibrationData,
    CalibrationError,
    cramer_rao_bound,
    estimate_axis,
    estimate_v,
    rodrigues,
    solve,
    tangent_basis,
    tangent_errors,
    unit,
)

V = unit(np.array([0.0656, 0.9955, -0.0678]))
N = unit(np.array([-0.0007, 0.0022, 0.9999]))
XR = np.array([235.21, 288.17, 0.0])


def synth(v=V, n=N, xr=XR, thetas=(0.0, 180.0), noise=(0.0, 0.0, 0.0), seed=0, radius=0.0,
          tip_depths=(4.0, 6.0, 8.0, 10.0), heights=(10, 15, 20, 25, 30, 35, 40)):
    """Center points as the paper's procedure would record them, from true parameters."""
    rng = np.random.default_rng(seed)
    sS, sd, sth = noise
    tip = xr + np.array([0.0, -20.0, 20.0])
    d_tip = np.asarray(tip_depths, float)
    S_tip = tip - d_tip[:, None] * v
    # vertical filament (axis) 25 mm off the table centre, along n
    base = xr + np.array([25.0, 0.0, 0.0])
    S_e, d_e, fr = [], [], []
    for i, th in enumerate(thetas):
        R = rodrigues(n, np.radians(th))
        for h in heights:
            axis_pt = xr + R @ (base + h * n - xr)
            # the beam meets the front surface 1 / sin(beta) times the radius before the
            # axis, beta its angle to the filament (along n here)
            surf = axis_pt - radius / np.linalg.norm(np.cross(n, v)) * v
            d = 6.0 + 0.5 * (h % 3)
            S_e.append(surf - d * v)
            d_e.append(d)
            fr.append(i)
    S_e, d_e = np.array(S_e), np.array(d_e)
    data = CalibrationData(
        S_tip + rng.normal(0, sS, S_tip.shape), d_tip + rng.normal(0, sd, d_tip.shape),
        S_e + rng.normal(0, sS, S_e.shape), d_e + rng.normal(0, sd, d_e.shape),
        np.array(fr), np.array(thetas) + rng.normal(0, sth, len(thetas)),
        sigma_S_mm=max(sS, 1e-6), sigma_d_mm=max(sd, 1e-6), sigma_theta_deg=max(sth, 1e-6),
        filament_radius_mm=radius)
    return data


def test_noise_free_data_is_recovered_exactly():
    r = solve(synth(radius=0.25))
    assert np.allclose(r.v, V, rtol=0, atol=1e-9) and np.allclose(r.n, N, rtol=0, atol=1e-9)
    assert np.allclose(r.X_R, XR, rtol=0, atol=1e-7)
    assert np.allclose(r.svd["X_R"], XR, rtol=0, atol=1e-3)  # the SVD takes a square beam


@pytest.mark.parametrize("down_deg", [0.0, 10.0, 20.0])
def test_an_oblique_beam_meets_the_filament_further_before_its_axis(down_deg):
    """A beam at angle beta to the filament meets its front surface r / sin(beta) before the
    axis, not r: with v 20 deg off square (a sensor tilted down) that is 16 um of X_R along
    the beam, which the MLE took as the radius alone (4 um at 10 deg)."""
    tilt = np.radians(down_deg)
    v = unit(np.array([0.0656, np.cos(tilt), -np.sin(tilt)]))
    for radius, front in ((0.25, None), (0.0, 0.25)):
        data = synth(v=v, radius=0.25)
        if front is not None:  # center_points' way: the front depth inside each depth
            data.filament_radius_mm = 0.0
            data.edge_d = data.edge_d + front
            data.edge_front_mm = np.full(len(data.edge_d), front)
        r = solve(data)
        assert np.allclose(r.X_R, XR, rtol=0, atol=1e-7), (radius, r.X_R - XR)
        assert np.allclose(r.v, v, rtol=0, atol=1e-9)


@settings(max_examples=50, deadline=None)
@given(v=st.tuples(*[st.floats(-1, 1)] * 3).filter(lambda a: np.linalg.norm(a) > 0.1),
       depths=st.lists(st.floats(0.5, 30), min_size=2, max_size=8, unique=True).filter(
           lambda d: np.ptp(d) > 0.1))
def test_v_by_svd_points_from_sensor_to_target(v, depths):
    v, d = unit(np.array(v)), np.array(depths)
    tip = np.array([230.0, 280.0, 20.0])
    est, tip_est = estimate_v(tip - d[:, None] * v, d)
    assert np.allclose(est, v, atol=1e-9) and np.allclose(tip_est, tip, atol=1e-9)


def test_residuals_point_at_the_bad_center_point():
    clean = solve(synth(noise=(0.01, 0.02, 0.01), seed=2))
    assert clean.residuals["tip"].shape == (4, 3) and clean.residuals["edge"].shape == (14,)
    assert np.abs(clean.residuals["edge"]).max() < 0.1
    bad = synth(noise=(0.01, 0.02, 0.01), seed=2)
    bad.edge_S[9] += 0.4 * unit(np.cross(V, N))  # one sweep found a dust grain, not the edge
    r = solve(bad)
    assert int(np.argmax(r.residuals["edge"])) == 9 and r.residuals["edge"][9] > 0.2
    assert r.rms_residual_mm > clean.rms_residual_mm
    assert np.allclose(solve(synth()).residuals["tip"], 0, atol=1e-9)


def test_filament_radius_is_corrected():
    svd = solve(synth(radius=0.25), refine=False)  # the SVD steps take a square beam
    d = synth(radius=0.25)
    d.filament_radius_mm = 0.0  # pretending the hits are on the axis biases X_R
    biased = solve(d, refine=False)
    assert np.linalg.norm(svd.X_R - XR) < 1e-3
    assert np.linalg.norm(biased.X_R - XR) > 0.2


# derandomized: the stds come from ~14 residuals, so z has heavier tails than a normal (a
# t distribution; bench/calibration.py measures them over 40 seeds), and a search over 2^31
# seeds finds a 4-sigma case in some runs; a fixed set of 25 cases fails only if the solver
# or its covariance changes
@settings(max_examples=25, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**31), tilt=st.floats(0.0, 0.05), turn=st.floats(60, 180),
       scale=st.floats(0.3, 3.0), x=st.floats(-50, 50), y=st.floats(-50, 50))
# a seed whose lateral scale, from its 14 residuals alone, fell to 0.20: v was 4.2 sigma off
@example(seed=128, tilt=0.0, turn=60.0, scale=1.0, x=0.0, y=0.0)
def test_errors_are_within_4_sigma_of_the_reported_covariance(seed, tilt, turn, scale, x, y):
    rng = np.random.default_rng(seed)
    n = unit(N + tilt * rng.normal(size=3))
    v = unit(V + 0.05 * rng.normal(size=3))
    xr = XR + np.array([x, y, 0.0])
    data = synth(v=v, n=n, xr=xr, thetas=(0.0, turn),
                 noise=(0.01 * scale, 0.02 * scale, 0.01 * scale), seed=seed)
    r = solve(data)
    for name, true in (("v", v), ("n", n)):  # unit vectors: their two tangent coordinates
        err, sd = tangent_errors(r, name, true)
        assert (np.abs(err) <= 4 * sd).all(), (name, err, sd)
    err = (r.X_R - xr)[:2]
    assert (np.abs(err) <= 4 * r.std["X_R"][:2]).all(), (err, r.std["X_R"])


def test_degenerate_data_gets_a_clear_error():
    d = synth()
    with pytest.raises(CalibrationError, match="tip frames at two or more depths"):
        solve(CalibrationData(d.tip_S[:1], d.tip_d[:1], d.edge_S, d.edge_d, d.edge_frame,
                              d.theta_deg))
    same = synth(thetas=(30.0, 30.0))
    with pytest.raises(CalibrationError, match="same turntable angle: rotate"):
        solve(same)
    with pytest.raises(CalibrationError, match="two or more turntable angles"):
        estimate_axis([(N, XR)], [0.0])


def test_mle_reaches_the_cramer_rao_bound_and_svd_does_not():
    """At the paper's data size and noise the MLE's rms error per first-order coordinate is
    the bound's (within the scatter of 120 trials); the SVD-only tilt of n is far above it."""
    noise, heights = (0.01, 0.03, 0.02), (8, 12, 16, 20, 24, 28, 32)
    design = synth(heights=heights)
    design.sigma_S_mm, design.sigma_d_mm, design.sigma_theta_deg = noise
    bound = cramer_rao_bound(design)
    proj = []  # (9,) projectors onto the first-order coordinates
    for i, u in ((0, V), (3, N)):
        for b in tangent_basis(u).T:
            p = np.zeros(9)
            p[i:i + 3] = b
            proj.append(p)
    proj += [np.eye(9)[6], np.eye(9)[7]]
    P = np.array(proj)
    crb = np.sqrt(np.diag(P @ bound @ P.T))
    truth = np.concatenate([V, N, XR])
    mle, svd = [], []
    for t in range(120):
        r = solve(synth(noise=noise, heights=heights, seed=t))
        mle.append(P @ (np.concatenate([r.v, r.n, r.X_R]) - truth))
        svd.append(P @ (np.concatenate([r.svd["v"], r.svd["n"], r.svd["X_R"]]) - truth))
    ratio = np.sqrt(np.mean(np.square(mle), axis=0)) / crb
    assert ((ratio > 0.75) & (ratio < 1.25)).all(), ratio
    assert (np.sqrt(np.mean(np.square(svd), axis=0)) / crb).max() > 3


def test_the_bound_needs_a_noise_free_design():
    with pytest.raises(CalibrationError, match="noise-free"):
        cramer_rao_bound(synth(noise=(0.01, 0.03, 0.02)))
