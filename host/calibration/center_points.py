"""Center points from raw calibration points (paper §IV-C): thresholding, averaging and their
covariances, edge depths moved onto the filament axis; bad data refused with what to do."""

from __future__ import annotations

import functools
from typing import NamedTuple

import numpy as np

from .solver import CalibrationData, CalibrationError, same_angle

MIN_POINTS = 2  # raw points above threshold a center point needs (one gives no spread)


def front_depth_mm(offset_mm: np.ndarray, radius_mm: float, spot_radius_mm: float,
                   shape: str = "disk") -> np.ndarray:
    """How far in front of a filament's axis the ranged surface lies (mm), for a beam whose
    centre passes offset_mm beside the axis, square to it (an oblique beam: solve's MLE
    divides by the sine of its angle to the filament).

    Ranging reports the mean distance of the part of the spot (`shape` as in Spot: a
    uniform disk of spot_radius_mm, or a Gaussian of sigma spot_radius_mm / 2) that lands
    on the filament (radius_mm); there the front surface is sqrt(r^2 - s^2) in front of
    the axis at lateral position s. Adding this to a raw depth puts the point on the axis:
    a constant `radius_mm` would leave it ~0.05 mm short."""
    u = np.atleast_1d(np.asarray(offset_mm, float))
    r, rho = float(radius_mm), float(spot_radius_mm)
    if r <= 0:
        return np.zeros_like(u)
    if rho <= 0:
        return np.sqrt(np.maximum(r * r - u * u, 0.0))
    if shape == "gauss":  # over the filament at s = r sin(phi): smooth at its sides
        phi = ((np.arange(512) + 0.5) / 512 - 0.5) * np.pi
        s, c = r * np.sin(phi), r * np.cos(phi)  # c: the front's depth there
        w = np.exp(-0.5 * ((s[None, :] - u[:, None]) / (0.5 * rho)) ** 2) * c  # ds = c dphi
        total = w.sum(axis=1)
        return np.where(total > 0, (w * c).sum(axis=1) / np.maximum(total, 1e-300), 0.0)
    t = (np.arange(512) + 0.5) / 256 - 1  # across the spot, in spot radii (midpoints)
    s = u[:, None] + rho * t[None, :]
    w = np.sqrt(1 - t * t)[None, :] * (np.abs(s) < r)  # chord length of the disk at s
    depth = np.sqrt(np.maximum(r * r - s * s, 0.0))
    total = w.sum(axis=1)
    return np.where(total > 0, (w * depth).sum(axis=1) / np.maximum(total, 1e-300), 0.0)


SPOT_SHAPES = ("disk", "gauss")  # the spot's intensity: uniform disk, or a Gaussian


class Spot(NamedTuple):
    """The laser spot of the raster model: its intensity's shape (SPOT_SHAPES) and radius."""

    shape: str        # "disk": uniform; "gauss": a Gaussian of sigma = radius / 2 (the
    radius_mm: float  # disk's second moment), cut at 5 sigma

    def scaled(self, factor: float) -> Spot:
        """The spot stretched by factor."""
        return Spot(self.shape, self.radius_mm * factor)


PROFILE_TABLE = 2048  # offsets at which a profile is tabulated (then interpolated)


@functools.lru_cache(maxsize=256)
def _profile_table(shape: str, target: str, ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """(offsets, amplitudes): the share of the spot on the target for the spot's centre
    `offsets` from the target's centre (disk) or axis (strip), in target radii, for a spot
    of radius `ratio` target radii; a strip's side weighted by sqrt(cos) of the incidence.
    Exact (no sampling of the spot): a disk on a disk is the circles' overlap, a Gaussian on
    a disk the noncentral chi-square's distribution function (2 degrees of freedom), a
    strip the integral of the spot's marginal across it (4001-point quadrature). The spot
    sampled by 121 points made the model's own profile lumpy by ~1 % of its top per raster
    step, which the raster model then added to the centroid's scatter (docs/calibration.md)."""
    from scipy.stats import ncx2

    a = max(ratio, 1e-6)
    reach = 1 + (2.5 * a if shape == "gauss" else a)  # beyond: no light on the target
    d = np.linspace(0.0, reach, PROFILE_TABLE)
    if target == "strip":
        x = np.linspace(-1, 1, 4001)
        w = np.sqrt(np.sqrt(np.clip(1 - x * x, 0, None)))
        t = x[None, :] - d[:, None]  # from the spot's centre across the strip
        if shape == "gauss":
            s = a / 2
            dens = np.exp(-0.5 * (t / s) ** 2) / (s * np.sqrt(2 * np.pi))
        else:
            dens = 2 * np.sqrt(np.clip(a * a - t * t, 0, None)) / (np.pi * a * a)
        y = (dens * w).sum(axis=1) * (x[1] - x[0])
    elif shape == "gauss":
        s = a / 2
        y = ncx2.cdf(1 / (s * s), 2, np.maximum(d / s, 1e-9) ** 2)
    else:  # overlap of the unit disk and the spot's, over the spot's area
        dd = np.maximum(d, 1e-12)
        c1 = np.clip((dd * dd + 1 - a * a) / (2 * dd), -1, 1)
        c2 = np.clip((dd * dd + a * a - 1) / (2 * dd * a), -1, 1)
        lens = (np.arccos(c1) + a * a * np.arccos(c2)
                - 0.5 * np.sqrt(np.clip((-dd + 1 + a) * (dd + 1 - a) * (dd - 1 + a)
                                        * (dd + 1 + a), 0, None)))
        full = np.pi * min(a, 1.0) ** 2
        y = np.where(d <= abs(1 - a), full, np.where(d >= 1 + a, 0.0, lens)) / (np.pi * a * a)
    return d, np.clip(y, 0, 1)


def _profile(P: np.ndarray, c: np.ndarray, spot: Spot, target: str, r: float
             ) -> np.ndarray:
    """Model amplitude (draws, n) at raster positions P (n, k mm) for target centres c
    (draws, k mm): the share of the spot on the target (a disk of radius r mm seen end on,
    or a strip of half-width r: only the raster's first axis crosses it), a cylinder's side
    weighted by sqrt(cos) of the incidence (the OA signal falls as the light arrives
    obliquely); interpolated in the spot's exact profile (_profile_table). Evaluated
    PROFILE_ELEMENTS (draw, point) pairs at a time: bounded memory whatever the raster's
    size."""
    chunk = max(1, int(PROFILE_ELEMENTS // max(len(P), 1)))
    if len(c) > chunk:
        return np.concatenate([_profile(P, c[i:i + chunk], spot, target, r)
                               for i in range(0, len(c), chunk)])
    d_tab, y_tab = _profile_table(spot.shape, target, round(spot.radius_mm / r, 4))
    if target == "strip":
        off = np.abs(P[None, :, 0] - c[:, None, 0])
    else:
        off = np.sqrt(((P[None, :, :] - c[:, None, :]) ** 2).sum(axis=2))
    return np.interp(off / r, d_tab, y_tab, right=0.0)


PROFILE_ELEMENTS = 2e5  # model amplitudes evaluated at once (x 8 bytes, a few times over)
MAX_GROUP_POINTS = 2500  # raw points of one tip frame or edge sweep (a 50 x 50 raster)
MAX_CENTERS = 1000       # tip frames plus edge sweeps (each ~30 ms of raster model)
MAX_EDGE_FRAMES = 72     # the MLE fits a table angle per edge frame (72: ~11 s)


def _steps(P: np.ndarray) -> np.ndarray:
    """The raster's step along each of its axes (mm; 0 for an axis it does not step)."""
    steps = []
    for j in range(P.shape[1]):
        dif = np.diff(np.unique(np.round(P[:, j], 4)))
        steps.append(float(np.median(dif[dif > 1e-4])) if (dif > 1e-4).any() else 0.0)
    return np.array(steps)


def _model_counts(P: np.ndarray, c: np.ndarray, spot: Spot, target: str, r: float,
                  threshold: float) -> np.ndarray:
    """Raster points above threshold x max of the noise-free model profile, per centre c."""
    a = _profile(P, c, spot, target, r)
    return (a >= threshold * a.max(axis=1, keepdims=True)).sum(axis=1)


def match_count(P: np.ndarray, spot: Spot, target: str, r: float, threshold: float,
                count: float) -> float:
    """The stretch (of the spot and the target together, 0.4-2.5) at which the model keeps
    `count` raster points above threshold on average over the raster's phase: the width of
    the thresholded patch, which sets the centroid's quantisation (a tenth of a step more or
    less changes its rms by up to 2x), taken from the data rather than from the nominal
    spot and filament."""
    steps = _steps(P)
    rng = np.random.default_rng(1)
    c = P.mean(axis=0) + (rng.random((48, P.shape[1])) - 0.5) * steps
    lo, hi = np.log(0.4), np.log(2.5)
    for _ in range(14):
        mid = 0.5 * (lo + hi)
        if _model_counts(P, c, spot.scaled(np.exp(mid)), target, r * np.exp(mid),
                         threshold).mean() < count:
            lo = mid
        else:
            hi = mid
    return float(np.exp(0.5 * (lo + hi)))


class ProfileFit(NamedTuple):
    """A frame's (or sweep's) measured amplitudes about the model profile of one spot shape
    that fits them best (spot and target stretched, centre shifted)."""

    scale: float     # robust (median-based) scale of the relative residuals
    u: np.ndarray    # (m, k) mm: the points near the profile's top, from the fitted centre
    rel: np.ndarray  # (m,) their relative residuals (measured / gain - model) / model
    level: np.ndarray  # (m,) their model amplitudes / the model's top


def _fit_at(P: np.ndarray, amp: np.ndarray, c: np.ndarray, spot: Spot, target: str,
            r: float) -> ProfileFit:
    """The profile fit with the spot and target (radius r mm) as given, centred at c (k,
    mm), its gain by least squares."""
    prof = _profile(P, c[None], spot, target, r)[0]
    gain = max(float(prof @ amp) / max(float(prof @ prof), 1e-12), 1e-12)
    top = max(float(prof.max()), 1e-12)
    near = prof > 0.25 * top
    rel = (amp[near] / gain - prof[near]) / np.maximum(prof[near], 1e-12)
    scale = float(1.4826 * np.median(np.abs(rel))) if near.any() else np.inf
    return ProfileFit(scale, P[near] - c, rel, prof[near] / top)


START_CANDIDATES = 3  # profile fits refined from at most this many grid stretches,
START_WITHIN = 1.5    # those whose grid scale is within this factor of the best


def _profile_fits(P: np.ndarray, amp: np.ndarray, c0: np.ndarray, steps: np.ndarray,
                  spot_radius_mm: float, target: str, r: float) -> dict[str, ProfileFit]:
    """Per spot shape (SPOT_SHAPES) the model profile that fits the amplitudes `amp` (n,) at
    raster positions P (n, k mm) best: spot and target scaled together by 0.6-1.6, the centre
    within about a raster step of c0 (the thresholded centroid, mm), the gain by least
    squares. A grid (the smallest robust scale of the relative residuals at the points above
    a quarter of the profile's top) and then least squares (soft L1, the stretch bounded)
    on the centre and the stretch, from each of the grid's best stretches (START_CANDIDATES
    within START_WITHIN of its best scale), the lowest cost kept: the misfit of a stretch
    between the grid's steps (12 % apart) changed within a raster step and passed for 4 %
    amplitude noise on a profile the model follows, and from the grid's best alone a fit
    could stay in another basin (a narrow spot a step off centre). The amplitudes are
    taken relative to their largest: least squares stops on the gradient's size, which
    scales with the gain squared (at 1/100 of the gain a fit stopped short of the
    profile, 10 % misfit taken for noise and the spot for a disk)."""
    from scipy.optimize import least_squares

    k = P.shape[1]
    amp = np.asarray(amp, float) / max(float(np.max(amp)), 1e-300)
    g = np.linspace(-0.6, 0.6, 5)
    shifts = np.stack(np.meshgrid(*[g * max(s, 1e-3) for s in steps]), -1).reshape(-1, k)
    out: dict[str, ProfileFit] = {}
    f_scale = 0.01
    lo = np.r_[np.full(k, -np.inf), np.log(0.6)]
    hi = np.r_[np.full(k, np.inf), np.log(1.6)]
    for shape in SPOT_SHAPES:
        spot = Spot(shape, spot_radius_mm)
        starts = []  # (grid scale, start) of each stretch's best shift
        for stretch in np.geomspace(0.7, 1.4, 7):
            prof = _profile(P, c0 + shifts, spot.scaled(stretch), target, r * stretch)
            gain = (prof @ amp) / np.maximum((prof * prof).sum(axis=1), 1e-12)
            near = prof > 0.25 * prof.max(axis=1, keepdims=True)
            with np.errstate(invalid="ignore"):
                rel = np.where(near, (amp[None] / np.maximum(gain[:, None], 1e-12) - prof)
                               / np.maximum(prof, 1e-12), np.nan)
                scale = 1.4826 * np.nanmedian(np.abs(rel), axis=1)
            if np.isfinite(scale).any():
                i = int(np.nanargmin(scale))
                starts.append((float(scale[i]), np.r_[c0 + shifts[i], np.log(stretch)]))
        starts.sort(key=lambda s: s[0])
        # the grid's best can lie in another basin than the profile's (a narrow spot a
        # step off centre against the true wide one, 0.065 against 0.066): refined from
        # every stretch whose grid scale is near the best, the lowest cost wins
        near_best = [st for sc, st in starts[:START_CANDIDATES]
                     if sc <= START_WITHIN * starts[0][0]] or [np.r_[c0, 0.0]]

        def resid(x: np.ndarray, spot: Spot = spot) -> np.ndarray:
            f = float(np.exp(np.clip(x[k], np.log(0.6), np.log(1.6))))
            prof = _profile(P, x[None, :k], spot.scaled(f), target, r * f)[0]
            gain = float(prof @ amp) / max(float(prof @ prof), 1e-12)
            return gain * prof - amp

        sols = [least_squares(resid, st, bounds=(lo, hi), loss="soft_l1",
                              f_scale=f_scale, diff_step=1e-3, max_nfev=60)
                for st in near_best]
        x = min(sols, key=lambda sol: sol.cost).x
        f = float(np.exp(np.clip(x[k], np.log(0.6), np.log(1.6))))
        out[shape] = _fit_at(P, amp, x[:k], spot.scaled(f), target, r * f)
    return out


NEAR_THRESHOLD = (0.3, 0.8)  # profile levels (x its top) whose noise moves the threshold


def white_noise(fits: list[ProfileFit], steps: np.ndarray) -> float:
    """Relative amplitude noise (its std) of the measured amplitudes, without the profile's
    own misfit: what is new at every raster point.

    About the model profile the residuals hold two parts: the noise, new at every raw point,
    and the misfit of the model to the real spot and target (a misplaced centre, a wrong
    width or shape, the smooth part of a lumpy spot), which changes little from one raster
    point to the next and does not average down. Each residual less the mean of its 2k
    raster neighbours (steps (k,) mm apart along the raster's axes) keeps the first with
    variance (1 + 1 / 2k) x the noise's and drops the second; the robust (median) scale of
    those differences at the points whose model amplitude lies within NEAR_THRESHOLD of the
    top (those whose noise moves them across the threshold), pooled over the frames of one
    target, is the noise. The scale of the residuals themselves took the misfit for noise:
    5-7.5 % on independent data with 0.01 % (docs/calibration.md)."""
    from scipy.spatial import cKDTree

    k = len(steps)
    steps = np.maximum(np.asarray(steps, float), 1e-3)
    diffs = []
    for f in fits:
        if len(f.rel) < 2 * k + 1:
            continue
        tree = cKDTree(f.u / steps)  # in raster steps: neighbours 1 apart
        nb = []
        for j in range(k):
            for sign in (-1, 1):
                e = np.zeros(k)
                e[j] = sign
                dist, idx = tree.query(f.u / steps + e, distance_upper_bound=0.25)
                nb.append(np.where(np.isfinite(dist), idx, -1))
        nb_idx = np.array(nb).T  # (m, 2k)
        lev = f.level
        use = (nb_idx >= 0).all(axis=1) & (lev >= NEAR_THRESHOLD[0]) & \
            (lev <= NEAR_THRESHOLD[1]) & np.isfinite(f.rel)
        if use.any():
            mean_nb = f.rel[nb_idx[use]].mean(axis=1)
            diffs.append((f.rel[use] - mean_nb) / np.sqrt(1 + 1 / (2 * k)))
    d = np.concatenate(diffs) if diffs else np.zeros(0)
    d = d[np.isfinite(d)]
    if len(d) < 3:  # too few interior points: the residuals' own scale (misfit included)
        rel = np.concatenate([f.rel for f in fits] or [np.zeros(0)])
        rel = rel[np.isfinite(rel)]
        return float(np.clip(1.4826 * np.median(np.abs(rel)) if len(rel) else 0.0, 0, 0.5))
    return float(np.clip(1.4826 * np.median(np.abs(d)), 0, 0.5))


def amp_noise(fits: list[dict[str, ProfileFit]], steps: np.ndarray) -> tuple[float, str]:
    """(relative amplitude noise, spot shape) of the frames (or sweeps) of one target from
    their profile fits (_profile_fits; steps (k,) mm: the raster's). The shape: the one whose
    residuals (in units of the profile's top), pooled over the frames, have the smallest rms
    - one laser spot for all of them; a frame's own choice by its relative residuals' scale
    followed its misfit and took a disk for the Gaussian spot in a third of the data sets,
    whose thresholded centroid it then declared 1.3x as uncertain. The noise: what is new at
    every raster point (white_noise), the smaller of its values about either shape (a
    shape's misfit can only add to it)."""
    def pooled(shape: str) -> float:
        res = [f[shape].rel * f[shape].level for f in fits if shape in f]
        res = np.concatenate(res) if res else np.zeros(0)
        res = res[np.isfinite(res)]
        return float(np.sqrt(np.mean(res ** 2))) if len(res) else np.inf

    noise = min(white_noise([f[sh] for f in fits if sh in f], steps) for sh in SPOT_SHAPES)
    return noise, min(SPOT_SHAPES, key=pooled)


def _amp_noise(P: np.ndarray, amp: np.ndarray, c0: np.ndarray, steps: np.ndarray,
               spot_radius_mm: float, target: str, r: float) -> tuple[float, str]:
    """(relative amplitude noise, spot shape) of one frame alone (amp_noise of its profile
    fits)."""
    fits = _profile_fits(P, amp, c0, steps, spot_radius_mm, target, r)
    return amp_noise([fits], steps)


def raster_centroid_cov(P: np.ndarray, amp: np.ndarray, threshold: float, target: str,
                        radius_mm: float, spot_radius_mm: float, draws: int = 400,
                        count: float | None = None, noise: tuple[float, str] | None = None
                        ) -> np.ndarray:
    """Covariance (k, k) mm^2 of the center point of raster positions P (n, k; the raster's
    own plane, k = 1 or 2 axes) above threshold x max amplitude, over the raster's unknown
    phase: the amplitude is the share of the spot (uniform disk) on the target, a disk of
    radius_mm seen end on ("disk": the tip) or a strip of half-width radius_mm ("strip": a
    filament swept across), with the relative amplitude noise the measured amplitudes `amp`
    (n,) show about that profile, which moves points across the threshold. The raster and
    the noise, not the points' spread / n, set how far a thresholded centroid moves.
    `count`: the mean number of raster points above threshold in the frames (or sweeps) of
    this target, to which the profile's width is matched (match_count). `noise`: (relative
    amplitude noise, spot shape) from all the frames of this target (amp_noise); without it
    they come from this frame's amplitudes alone."""
    P = np.asarray(P, float)
    k = P.shape[1]
    steps = _steps(P)
    rho, r = max(spot_radius_mm, 1e-3), max(radius_mm, 0.05)
    amp = np.asarray(amp, float)
    if noise is None:
        kept = amp >= threshold * amp.max()
        noise = _amp_noise(P, amp, P[kept].mean(axis=0), steps, rho, target, r)
    rel_noise, shape = noise
    spot = Spot(shape, rho)
    if count is not None:
        stretch = match_count(P, spot, target, r, threshold, count)
        spot, r = spot.scaled(stretch), r * stretch
    rng = np.random.default_rng(0)  # a fixed design sum: the same data give the same result
    c = P.mean(axis=0) + (rng.random((draws, k)) - 0.5) * steps
    noise = rng.standard_normal((draws, len(P)))
    err = np.empty((draws, k))
    chunk = max(1, int(PROFILE_ELEMENTS // max(len(P), 1)))  # bounded memory
    for i in range(0, draws, chunk):
        a = _profile(P, c[i:i + chunk], spot, target, r) * (1 + rel_noise * noise[i:i + chunk])
        keep = a >= threshold * a.max(axis=1, keepdims=True)
        cnt = np.maximum(keep.sum(axis=1), 1)
        err[i:i + chunk] = (keep[..., None] * P[None]).sum(axis=1) / cnt[:, None] - c[i:i + chunk]
    return err.T @ err / draws


def _above(S: np.ndarray, d: np.ndarray, amp: np.ndarray, threshold: float
           ) -> tuple[np.ndarray, np.ndarray]:
    """(ranged, kept): the raw points with a depth, and those of them at or above threshold x
    their maximum amplitude."""
    ok = np.isfinite(d) & np.isfinite(amp) & np.isfinite(S).all(axis=1)
    if not ok.any():
        return ok, ok
    return ok, ok & (amp >= threshold * np.max(amp[ok]))


def _mean_count(S: np.ndarray, raw: dict[str, np.ndarray], groups: list[np.ndarray],
                threshold: float) -> float | None:
    """Mean number of raw points kept per frame (or sweep) over the masks `groups`, among
    those keeping MIN_POINTS or more; None if there are none."""
    counts = [int(_above(S[m], raw["d_mm"][m], raw["amplitude"][m], threshold)[1].sum())
              for m in groups]
    counts = [c for c in counts if c >= MIN_POINTS]
    return float(np.mean(counts)) if counts else None


def _raster_plane(S: np.ndarray) -> np.ndarray:
    """(3, k) the stage axes a raster of stage readings S (n, 3 mm) steps along: its plane
    (a square raster has no SVD axes)."""
    span = np.ptp(S, axis=0)
    return np.eye(3)[:, span > max(0.2 * span.max(), 1e-3)]


def target_noise(S: np.ndarray, raw: dict[str, np.ndarray], groups: list[np.ndarray],
                 threshold: float, target: str, radius_mm: float, spot_radius_mm: float
                 ) -> tuple[float, str] | None:
    """(relative amplitude noise, spot shape) of one target from all its frames (or sweeps),
    the masks `groups` (amp_noise); None without a frame the raster model takes."""
    if spot_radius_mm <= 0:
        return None
    fits, steps = [], None
    rho, r = max(spot_radius_mm, 1e-3), max(radius_mm, 0.05)
    for m in groups:
        ok, keep = _above(S[m], raw["d_mm"][m], raw["amplitude"][m], threshold)
        if keep.sum() < MIN_POINTS:
            continue
        U = _raster_plane(S[m][ok])
        if U.shape[1] not in (1, 2):
            continue
        P = (S[m][ok] - S[m][ok].mean(axis=0)) @ U
        amp = raw["amplitude"][m][ok]
        st = _steps(P)
        if steps is not None and len(st) != len(steps):
            continue  # a frame stepped along other axes than the first
        steps = st if steps is None else np.maximum(steps, st)
        kept = amp >= threshold * amp.max()
        fits.append(_profile_fits(P, amp, P[kept].mean(axis=0), st, rho, target, r))
    return amp_noise(fits, steps) if fits else None


class Center(NamedTuple):
    """One center point (§IV-C) and what its covariance and the MLE need of its raw points."""

    S: np.ndarray        # (3,) stage reading (mm): the kept raw points' mean
    d: float             # depth (mm): their mean (an edge's moved onto the axis)
    cov_S: np.ndarray    # (3, 3) mm^2
    points: tuple[np.ndarray, np.ndarray]  # kept points' lateral offsets, depths
    front: float         # mean front depth added (mm; edges), for a beam square to it
    plane: np.ndarray    # (3, k) the stage axes of the raster's plane (points' offsets)


def _center(S: np.ndarray, d: np.ndarray, amp: np.ndarray, threshold: float,
            radius_mm: float = 0.0, spot_radius_mm: float = 0.0, target: str = "strip",
            count: float | None = None, noise: tuple[float, str] | None = None
            ) -> Center | None:
    """The center point of the ranged raw points above threshold x max amplitude (§IV-C),
    or None with fewer than MIN_POINTS. With a filament radius and target "strip" the
    points are a sweep across a filament: each depth is moved from the ranged front surface
    onto the axis (front_depth_mm of its offset from the sweep's centre, for the spot shape
    of `noise`, the one the amplitudes showed). The lateral covariance is the raster's
    (raster_centroid_cov, with the target's `noise` if given) in the raster's plane and the
    points' spread / n out of it (stage noise)."""
    ok, keep = _above(S, d, amp, threshold)
    n = int(keep.sum())
    if n < MIN_POINTS:
        return None
    Sk, dk = S[keep], d[keep]
    front = 0.0
    if radius_mm > 0 and target == "strip":
        _, _, vt = np.linalg.svd(S[ok] - S[ok].mean(axis=0))  # the sweep direction
        fd = front_depth_mm((Sk - Sk.mean(axis=0)) @ vt[0], radius_mm, spot_radius_mm,
                            noise[1] if noise is not None else "disk")
        dk, front = dk + fd, float(fd.mean())
    spread = np.cov(Sk.T) / n
    # the raster's plane: the stage axes it steps along (a square raster has no SVD axes)
    U = _raster_plane(S[ok])
    if U.shape[1] in (1, 2) and spot_radius_mm > 0:
        out = np.eye(3) - U @ U.T
        Q = raster_centroid_cov((S[ok] - S[ok].mean(axis=0)) @ U, amp[ok], threshold, target,
                                radius_mm, spot_radius_mm, count=count, noise=noise)
        cov = U @ Q @ U.T + out @ spread @ out
    else:
        cov = spread
    return Center(Sk.mean(axis=0), float(dk.mean()), cov, ((Sk - Sk.mean(axis=0)) @ U, dk),
                  front, U)


def _shared_trend(points: list[tuple[np.ndarray, np.ndarray]]
                  ) -> tuple[np.ndarray, np.ndarray, int, int]:
    """The least-squares fit of every kept raw depth to its center point's mean plus one
    smooth trend across the raster that all of them share (depth_noise_var): (residuals,
    coefficients: the means, then the trend's, degrees of freedom, k lateral axes). With too
    few points for a trend, the means alone."""
    k = points[0][0].shape[1] if points and points[0][0].ndim == 2 else 0
    L = np.vstack([p[0].reshape(len(p[1]), -1) for p in points]) if k else None
    d = np.concatenate([p[1] for p in points])
    group = np.repeat(np.arange(len(points)), [len(p[1]) for p in points])
    cols = [(group == g).astype(float) for g in range(len(points))]
    if k == 1:
        cols += [L[:, 0] ** e for e in (1, 2, 3, 4)]
    elif k == 2:
        x, z = L[:, 0], L[:, 1]
        cols += [x, z, x * x, x * z, z * z]
    A = np.column_stack(cols)
    dof = len(d) - np.linalg.matrix_rank(A)
    if dof < 2:  # too few points for a trend: the spread about each mean
        dof = len(d) - len(points)
        A = np.column_stack(cols[:len(points)])
    coef = np.linalg.lstsq(A, d, rcond=None)[0]
    return d - A @ coef, coef, dof, k


def depth_noise_var(points: list[tuple[np.ndarray, np.ndarray]]) -> float:
    """Variance (mm^2) of one raw depth's noise, pooled over center points: the kept raw
    points' depths about their center point's mean plus one smooth trend across the raster
    that all of them share (linear and quadratic in the two lateral axes of a tip raster;
    up to the 4th power of the offset along an edge sweep). `points`: per center point the
    kept raw points' lateral offsets from their centroid (n, k mm) and depths (n,).

    The target's own shape - a tip face a few degrees off the beam, a filament's front the
    spot model does not follow exactly - moves the raw depths across the raster the same way
    in every frame but does not move a center point's depth, which is their mean at the
    centroid; about their mean (sigma_P / n, §IV-C) it passed for noise: 0.003 mm claimed
    for tip depths good to 0.0001 mm (docs/calibration.md)."""
    res, _, dof, _ = _shared_trend(points)
    if dof < 1:
        return 0.0
    return float(res @ res / dof)


def depth_gradient(points: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """(k,) how much a center point's depth changes per mm its centroid moves in the
    raster's plane (mm/mm): the linear part, at the centroid, of the trend all the center
    points share (depth_noise_var); zeros without a trend.

    A center point's depth is the target's depth at its centroid, so where the raster
    misses the target's centre by e, the depth misses by this gradient . e: on a tip face
    3 deg off the beam, a lateral error of 8 um comes with 0.4 um along the beam, which
    the covariance must carry. Without it the point looked exact along the stage axis the
    raster does not step (nothing but the depth's noise there, 0.01 um with almost no
    noise), and that false precision tilted v's reported std: |z| up to 7.5
    (docs/calibration.md)."""
    _, coef, _, k = _shared_trend(points)
    return coef[len(points):len(points) + k] if len(coef) >= len(points) + k else \
        np.zeros(k)


def sweep_depth_var(points: list[tuple[np.ndarray, np.ndarray]]) -> float:
    """Variance (mm^2) of one raw depth's noise along edge sweeps: each depth less the line
    through its two neighbours along the sweep (interpolated at its offset), scaled by that
    difference's variance factor 1 + w^2 + (1 - w)^2, pooled as a mean square over the
    sweeps (`points`: per center point the kept raw points' offsets (n, 1 mm) and depths
    moved onto the axis (n,)); depth_noise_var where the sweeps have too few points.

    Moved onto the axis, a sweep's depths still carry what the front-depth model misses of
    the filament and the spot: smooth in the offset, different in every sweep (its phase),
    so a trend shared by all sweeps left it in and passed it for noise (2.7 um declared per
    edge center against 0.8 um true with almost no noise, docs/calibration.md). A locally
    linear part cancels in the differences; what is new at every raw point stays."""
    diffs = []
    for lat, d in points:
        if len(d) < 3 or lat.ndim != 2 or lat.shape[1] != 1:
            continue
        o = np.argsort(lat[:, 0], kind="stable")
        x, y = lat[o, 0], d[o]
        span = x[2:] - x[:-2]
        ok = span > 0  # two raw points at one offset give no line
        w = (x[2:] - x[1:-1])[ok] / span[ok]
        line = w * y[:-2][ok] + (1 - w) * y[2:][ok]
        diffs.append((y[1:-1][ok] - line) / np.sqrt(1 + w * w + (1 - w) ** 2))
    x = np.concatenate(diffs) if diffs else np.zeros(0)
    if len(x) < 3:
        return depth_noise_var(points)
    return float(np.mean(x ** 2))


def _check_size(tip_groups: list[np.ndarray], edge_groups: list[np.ndarray], n_frames: int
                ) -> None:
    """Refuse, before any heavy work, data whose solve would not finish in bounded memory
    and time (MAX_GROUP_POINTS, MAX_CENTERS, MAX_EDGE_FRAMES), in one line with the limit
    and what to do."""
    biggest = max((int(m.sum()) for m in tip_groups + edge_groups), default=0)
    if biggest > MAX_GROUP_POINTS:
        raise CalibrationError(
            f"a tip frame or edge sweep has {biggest} raw points, more than the "
            f"{MAX_GROUP_POINTS} the solve takes: scan a coarser raster (--tip-step, "
            f"--edge-step) or give each frame its own frame (and line) number")
    if len(tip_groups) + len(edge_groups) > MAX_CENTERS:
        raise CalibrationError(
            f"{len(tip_groups)} tip frames and {len(edge_groups)} edge sweeps, more than the "
            f"{MAX_CENTERS} center points the solve takes: give fewer frames (--tip-depths, "
            f"--edge-levels, --angles)")
    if n_frames > MAX_EDGE_FRAMES:
        raise CalibrationError(
            f"{n_frames} edge frames, more than the {MAX_EDGE_FRAMES} the solve takes: give "
            f"fewer --angles")


def _edge_angles(frames: list[float], thetas: list[float]) -> None:
    """Refuse edge frames that cannot give the axis: no angle, or all at one angle."""
    for f, th in zip(frames, thetas):
        if not np.isfinite(th):
            raise CalibrationError(f"edge frame {f:g} has no turntable angle (theta_deg): "
                                   f"record the table reading with each raw point")
    if len(frames) >= 2 and all(same_angle(th, thetas[0]) for th in thetas[1:]):
        raise CalibrationError(f"edge frames {frames[0]:g} and {frames[1]:g} have the same "
                               f"turntable angle ({thetas[0]:g} deg): rotate the table "
                               f"between them")


def center_points(raw: dict[str, np.ndarray], modality: str = "oa", threshold: float = 0.5,
                  radius_mm: float = 0.25, sigma_theta_deg: float = 0.01,
                  spot_radius_mm: float = 0.25) -> CalibrationData:
    """Tip center points per tip frame; edge center points per scan line of each edge frame,
    on the filament's axis (radius_mm: the filament's, spot_radius_mm: the laser spot's)."""
    sel = raw["modality"] == modality
    if not sel.any():
        have = ", ".join(sorted(set(raw["modality"].tolist()))) or "none"
        raise CalibrationError(f"no {modality.upper()} raw points (modality column has: "
                               f"{have}): pick that --modality")
    S = np.column_stack([raw["sx_mm"], raw["sy_mm"], raw["sz_mm"]])
    tips, edges = [], []
    is_tip, is_edge = sel & (raw["step"] == "tip"), sel & (raw["step"] == "edge")
    tip_groups = [is_tip & (raw["frame"] == f) for f in np.unique(raw["frame"][is_tip])]
    edge_groups = [is_edge & (raw["frame"] == f) & (raw["line"] == ln)
                   for f in np.unique(raw["frame"][is_edge])
                   for ln in np.unique(raw["line"][is_edge & (raw["frame"] == f)])]
    _check_size(tip_groups, edge_groups, len(np.unique(raw["frame"][is_edge])))
    tip_count = _mean_count(S, raw, tip_groups, threshold)
    edge_count = _mean_count(S, raw, edge_groups, threshold)
    tip_noise = target_noise(S, raw, tip_groups, threshold, "disk", radius_mm, spot_radius_mm)
    edge_noise = target_noise(S, raw, edge_groups, threshold, "strip", radius_mm,
                              spot_radius_mm)
    for f in np.unique(raw["frame"][is_tip]):
        m = is_tip & (raw["frame"] == f)
        c = _center(S[m], raw["d_mm"][m], raw["amplitude"][m], threshold, radius_mm,
                    spot_radius_mm, target="disk", count=tip_count, noise=tip_noise)
        if c is not None:
            tips.append(c)
    if len(tips) < 2:
        n_frames = len(np.unique(raw["frame"][is_tip]))
        raise CalibrationError(
            f"{len(tips)} of {n_frames} tip frame(s) have {MIN_POINTS} or more ranged "
            f"{modality.upper()} points above threshold: record tip frames at two or more "
            f"depths facing the tip (or lower --threshold)")
    frames, thetas = [], []
    for f in np.unique(raw["frame"][is_edge]):
        fm = is_edge & (raw["frame"] == f)
        lines = np.unique(raw["line"][fm])
        got = []
        for ln in lines:
            m = fm & (raw["line"] == ln)
            c = _center(S[m], raw["d_mm"][m], raw["amplitude"][m], threshold, radius_mm,
                        spot_radius_mm, count=edge_count, noise=edge_noise)
            if c is not None:
                got.append(c)
        if len(got) < 2:
            raise CalibrationError(
                f"edge frame {f:g}: {len(got)} of {len(lines)} scan lines have {MIN_POINTS} or "
                f"more ranged points above threshold (no echo or too weak): sweep across the "
                f"filament at two or more heights (--at, --edge-half)")
        heights = np.array([c.S for c in got])
        span = np.ptp(heights - heights.mean(axis=0), axis=0).max()
        if span < 1.0:
            raise CalibrationError(f"edge frame {f:g}: its center points span {span:.2f} mm: "
                                   f"scan the filament at heights 1 mm or more apart "
                                   f"(--edge-levels)")
        edges += [(len(frames), c) for c in got]
        frames.append(float(f))
        th = raw["theta_deg"][fm]
        thetas.append(float(np.median(th[np.isfinite(th)])) if np.isfinite(th).any()
                      else np.nan)
    if len(frames) < 2:
        raise CalibrationError(f"{len(frames)} edge frame(s): need edge frames at two or more "
                               f"turntable angles")
    _edge_angles(frames, thetas)
    ec = [e[1] for e in edges]
    tip_points = [t.points for t in tips]
    grad = depth_gradient(tip_points) if len({t.plane.shape for t in tips}) == 1 else None
    return CalibrationData(
        np.array([t.S for t in tips]), np.array([t.d for t in tips]),
        np.array([c.S for c in ec]), np.array([c.d for c in ec]),
        np.array([e[0] for e in edges]), np.array(thetas), sigma_theta_deg=sigma_theta_deg,
        tip_cov_S=np.array([t.cov_S for t in tips]),
        tip_var_d=depth_noise_var(tip_points) / np.array([len(t.points[1]) for t in tips]),
        tip_grad=None if grad is None else np.array([t.plane @ grad for t in tips]),
        edge_cov_S=np.array([c.cov_S for c in ec]),
        edge_var_d=sweep_depth_var([c.points for c in ec]) / np.array([len(c.points[1])
                                                                      for c in ec]),
        edge_front_mm=np.array([c.front for c in ec]))
