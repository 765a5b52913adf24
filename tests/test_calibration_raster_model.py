"""The raster model of a thresholded centroid (host/calibration/center_points.py) against known
truth (issue 30, item 3): the spot's exact profile, the amplitude noise without the profile's
own misfit, one spot shape for all frames of a target, and the declared lateral std of the
tip center points against their true scatter on the independent generator's data (a lumpy
256-ray Gaussian spot the model does not know)."""

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from independent_rig import Rig, generate, random_truth

from dmdsm.host.calibration.center_points import (
    SPOT_SHAPES,
    Spot,
    _profile,
    _profile_fits,
    _steps,
    amp_noise,
    center_points,
)

_MC = np.random.default_rng(7).standard_normal((200_000, 2))  # unit Gaussian draws


def _brute_force(shape: str, target: str, ratio: float, offset: float) -> float:
    """The share of a spot of radius `ratio` on the unit target at `offset` (target radii),
    by Monte Carlo over the spot's intensity."""
    if shape == "gauss":
        pts = _MC * ratio / 2
    else:
        u = np.random.default_rng(8).uniform(-1, 1, (400_000, 2))
        pts = u[(u ** 2).sum(axis=1) < 1] * ratio
    x = pts[:, 0] + offset
    if target == "strip":
        return float(np.sqrt(np.sqrt(np.clip(1 - x * x, 0, None))).mean())
    return float((x * x + pts[:, 1] ** 2 < 1).mean())


@settings(max_examples=25, deadline=None)
@given(shape=st.sampled_from(SPOT_SHAPES), target=st.sampled_from(["disk", "strip"]),
       ratio=st.floats(0.3, 3.0), offset=st.floats(0.0, 3.0))
def test_the_profile_is_the_spots_exact_share_on_the_target(shape, target, ratio, offset):
    """_profile interpolates the exact share (no spot sampling: 121 samples made the model's
    own profile lumpy) for any spot / target ratio and offset."""
    r = 0.25
    got = _profile(np.array([[offset * r, 0.0]]), np.zeros((1, 2)),
                      Spot(shape, ratio * r), target, r)[0, 0]
    assert got == pytest.approx(_brute_force(shape, target, ratio, offset), abs=0.006)


def _smooth_frames(rel_noise: float, seed: int, n_frames: int = 4, gain: float = 1.0,
                   stretch: float = 1.0) -> tuple[list, np.ndarray]:
    """Tip frames (9 x 9 raster, 0.1 mm) of a smooth Gaussian spot (sigma 0.125 mm) on a
    0.25 mm disk, both stretched by `stretch`, at random phases, with relative amplitude
    noise; their profile fits (for the nominal spot and disk)."""
    from scipy.stats import ncx2

    rng = np.random.default_rng(seed)
    g = np.arange(-0.4, 0.4001, 0.1)
    P = np.column_stack([a.ravel() for a in np.meshgrid(g, g)])
    steps = _steps(P)
    fits = []
    for _ in range(n_frames):
        c = rng.uniform(-0.05, 0.05, 2)
        sigma, radius = 0.125 * stretch, 0.25 * stretch
        a = gain * ncx2.cdf(radius ** 2 / sigma ** 2, 2,
                            ((P - c) ** 2).sum(axis=1) / sigma ** 2)
        a = a * (1 + rel_noise * rng.standard_normal(len(a)))
        fits.append(_profile_fits(P, a, P[a >= 0.5 * a.max()].mean(axis=0), steps, 0.25,
                                     "disk", 0.25))
    return fits, steps


@pytest.mark.parametrize("rel_noise", [0.0, 0.02, 0.05, 0.10, 0.15])
def test_amplitude_noise_is_recovered(rel_noise):
    """Monte Carlo against the known noise: the mean estimate over 12 data sets of 4 frames
    within 20 % (or 0.01) of the truth."""
    est = [amp_noise(*_smooth_frames(rel_noise, seed))[0] for seed in range(12)]
    assert np.mean(est) == pytest.approx(rel_noise, rel=0.2, abs=0.01), est


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 10_000), gain=st.floats(0.01, 100.0),
       stretch=st.floats(0.75, 1.35))
@example(seed=246, gain=1.0, stretch=1.2890625)  # a grid start in the wrong basin (make test)
@example(seed=1191, gain=0.01, stretch=0.75)  # least squares stopped on a small gradient
def test_a_smooth_profile_without_noise_shows_none(seed, gain, stretch):
    """Whatever the gain, the phases and the width of spot and target together, a noise-free
    profile the model follows shows under 2 % noise (the misfit of the fitted width and
    centre is not noise) and is taken for a Gaussian spot. (A spot narrower or wider than
    the nominal one against the target is a shape the model does not follow: its misfit
    changes within a raster step and counts in part as noise.)"""
    noise, shape = amp_noise(*_smooth_frames(0.0, seed, gain=gain, stretch=stretch))
    assert noise < 0.02 and shape == "gauss", (noise, shape)


def _tip_errors(noise: str, seeds: range) -> tuple[np.ndarray, np.ndarray]:
    """Per independent data set: the tip center points' lateral errors against the
    generator's hidden tip (frames, 2: x, z mm) and their declared stds."""
    errs, sds = [], []
    for seed in seeds:
        truth = random_truth(np.random.default_rng([seed, 1]))
        hidden: dict = {}
        rows = generate(truth, seed, noise, "default", Rig(), hidden=hidden)
        raw = {k: np.array([r[k] for r in rows]) for k in rows[0]}
        for k in ("frame", "line", "theta_deg", "sx_mm", "sy_mm", "sz_mm", "d_mm"):
            raw[k] = raw[k].astype(float)
        raw["amplitude"] = np.maximum(raw["amplitude"].astype(float), 0.0)
        data = center_points(raw)
        v, T = truth["v"], hidden["tip"]
        true_S = T + ((data.tip_S[:, 1] - T[1]) / v[1])[:, None] * v
        errs.append((data.tip_S - true_S)[:, [0, 2]])
        sds.append(np.sqrt(data.tip_cov_S[:, [0, 2], [0, 2]]))
    return np.array(errs), np.array(sds)


@pytest.mark.parametrize("noise", ["none", "large"])
def test_tip_center_stds_hold_on_a_lumpy_spot(noise):
    """The tip center points' declared lateral std against their true scatter from frame to
    frame (less each data set's common offset, which moves the tip point, not v) over 16
    independent data sets: within 0.8-1.3 (sampling: ~7 %). Before: 1.47 with almost no
    noise (the spot's lumps and the model's misfit taken for 5.5 % amplitude noise, a disk
    taken for the Gaussian spot, the model's own 121-sample lumps) and 0.90 with large
    noise (the robust scale of the residuals missed the additive noise near threshold)."""
    errs, sds = _tip_errors(noise, range(16))
    k = errs.shape[1]
    dev = errs - errs.mean(axis=1, keepdims=True)
    true_sd = np.sqrt((dev ** 2).sum(axis=(0, 1)) / (errs.shape[0] * (k - 1)))
    ratio = np.sqrt((sds ** 2).mean(axis=(0, 1))) / true_sd
    assert ((ratio > 0.8) & (ratio < 1.3)).all(), ratio
