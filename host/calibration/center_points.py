"""Center points from raw calibration points (paper §IV-C): thresholding, averaging and their
covariances, edge depths moved onto the filament axis; bad data refused with what to do."""

from __future__ import annotations

import numpy as np

from .solver import CalibrationData, CalibrationError, same_angle

MIN_POINTS = 2  # raw points above threshold a center point needs (one gives no spread)


def front_depth_mm(offset_mm: np.ndarray, radius_mm: float, spot_radius_mm: float
                   ) -> np.ndarray:
    """How far in front of a filament's axis the ranged surface lies (mm), for a beam whose
    centre passes offset_mm beside the axis.

    Ranging reports the mean distance of the part of the spot (a uniform disk of
    spot_radius_mm) that lands on the filament (radius_mm); there the front surface is
    sqrt(r^2 - s^2) in front of the axis at lateral position s. Adding this to a raw depth
    puts the point on the axis: a constant `radius_mm` would leave it ~0.05 mm short."""
    u = np.atleast_1d(np.asarray(offset_mm, float))
    r, rho = float(radius_mm), float(spot_radius_mm)
    if r <= 0:
        return np.zeros_like(u)
    if rho <= 0:
        return np.sqrt(np.maximum(r * r - u * u, 0.0))
    t = (np.arange(512) + 0.5) / 256 - 1  # across the spot, in spot radii (midpoints)
    s = u[:, None] + rho * t[None, :]
    w = np.sqrt(1 - t * t)[None, :] * (np.abs(s) < r)  # chord length of the disk at s
    depth = np.sqrt(np.maximum(r * r - s * s, 0.0))
    total = w.sum(axis=1)
    return np.where(total > 0, (w * depth).sum(axis=1) / np.maximum(total, 1e-300), 0.0)


SPOT_SHAPES = ("disk", "gauss")  # the spot's intensity: uniform disk, or a Gaussian


def _spot_samples(spot_radius_mm: float, shape: str = "disk") -> np.ndarray:
    """Points (k, 2) spread over the laser spot (mm), each carrying an equal share of its
    power: for a uniform disk an 11 x 11 grid inside it; for a Gaussian of the same second
    moment (sigma = radius / 2) the 11 x 11 grid of its quantiles."""
    g = (np.arange(11) - 5) / 5.0
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    if shape == "gauss":
        from scipy.special import ndtri

        q = ndtri((np.arange(11) + 0.5) / 11)
        return spot_radius_mm / 2 * np.stack(np.meshgrid(q, q), -1).reshape(-1, 2)
    return spot_radius_mm * xy[(xy ** 2).sum(axis=1) <= 1.0]


def _profile(P: np.ndarray, c: np.ndarray, spot: np.ndarray, target: str, r: float
             ) -> np.ndarray:
    """Model amplitude (draws, n) at raster positions P (n, k) for target centres c
    (draws, k): the share of the spot on the target, a cylinder's side weighted by
    sqrt(cos) of the incidence (the OA signal falls as the light arrives obliquely).
    Evaluated PROFILE_ELEMENTS (draw, point, spot sample) triples at a time: bounded memory
    whatever the raster's size."""
    chunk = max(1, int(PROFILE_ELEMENTS // max(len(P) * len(spot), 1)))
    if len(c) > chunk:
        return np.concatenate([_profile(P, c[i:i + chunk], spot, target, r)
                               for i in range(0, len(c), chunk)])

    def rel(j: int) -> np.ndarray:  # (draws, n, spot samples) offsets along raster axis j
        return P[None, :, None, j] - c[:, None, None, j] + spot[None, None, :, j]

    if target == "strip":  # only the axis across the strip matters
        on = np.sqrt(np.sqrt(np.clip(1 - (rel(0) / r) ** 2, 0, None)))
    else:
        on = (sum(rel(j) ** 2 for j in range(P.shape[1])) < r * r).astype(float)
    return on.mean(axis=2)


PROFILE_ELEMENTS = 2e6  # model amplitudes evaluated at once (x 8 bytes, a few times over)
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


def _model_counts(P: np.ndarray, c: np.ndarray, spot: np.ndarray, target: str, r: float,
                  threshold: float) -> np.ndarray:
    """Raster points above threshold x max of the noise-free model profile, per centre c."""
    a = _profile(P, c, spot, target, r)
    return (a >= threshold * a.max(axis=1, keepdims=True)).sum(axis=1)


def match_count(P: np.ndarray, spot: np.ndarray, target: str, r: float, threshold: float,
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
        if _model_counts(P, c, spot * np.exp(mid), target, r * np.exp(mid),
                         threshold).mean() < count:
            lo = mid
        else:
            hi = mid
    return float(np.exp(0.5 * (lo + hi)))


def _amp_noise(P: np.ndarray, amp: np.ndarray, c0: np.ndarray, steps: np.ndarray,
               spot_radius_mm: float, target: str, r: float) -> tuple[float, str]:
    """(relative amplitude noise, spot shape): the robust (median) scale of the measured
    amplitudes' relative residuals about the model profile that fits them best - the spot a
    uniform disk or a Gaussian (SPOT_SHAPES), spot and target scaled together by 0.7-1.4,
    the centre within about a raster step of c0 (the thresholded centroid). About one fixed
    profile (the nominal uniform disk, centred on c0) the profile's own misfit passed for
    amplitude noise: 3-18 % on data with 0.01 % (docs/calibration.md)."""
    k = P.shape[1]
    g = np.linspace(-0.6, 0.6, 5)
    shifts = np.stack(np.meshgrid(*[g * max(s, 1e-3) for s in steps]), -1).reshape(-1, k)
    best = (np.inf, "disk")
    for shape in SPOT_SHAPES:
        spot = _spot_samples(spot_radius_mm, shape)[:, :k]
        for stretch in np.geomspace(0.7, 1.4, 7):
            prof = _profile(P, c0 + shifts, spot * stretch, target, r * stretch)
            gain = (prof @ amp) / np.maximum((prof * prof).sum(axis=1), 1e-12)
            near = prof > 0.25 * prof.max(axis=1, keepdims=True)
            with np.errstate(invalid="ignore"):
                rel = np.where(near, (amp[None] / np.maximum(gain[:, None], 1e-12) - prof)
                               / np.maximum(prof, 1e-12), np.nan)
                scale = 1.4826 * np.nanmedian(np.abs(rel), axis=1)
            if np.isfinite(scale).any() and np.nanmin(scale) < best[0]:
                best = (float(np.nanmin(scale)), shape)
    return float(np.clip(best[0] if np.isfinite(best[0]) else 0.0, 0, 0.5)), best[1]


def raster_centroid_cov(P: np.ndarray, amp: np.ndarray, threshold: float, target: str,
                        radius_mm: float, spot_radius_mm: float, draws: int = 400,
                        count: float | None = None) -> np.ndarray:
    """Covariance (k, k) mm^2 of the center point of raster positions P (n, k; the raster's
    own plane, k = 1 or 2 axes) above threshold x max amplitude, over the raster's unknown
    phase: the amplitude is the share of the spot (uniform disk) on the target, a disk of
    radius_mm seen end on ("disk": the tip) or a strip of half-width radius_mm ("strip": a
    filament swept across), with the relative amplitude noise the measured amplitudes `amp`
    (n,) show about that profile, which moves points across the threshold. The raster and
    the noise, not the points' spread / n, set how far a thresholded centroid moves.
    `count`: the mean number of raster points above threshold in the frames (or sweeps) of
    this target, to which the profile's width is matched (match_count)."""
    P = np.asarray(P, float)
    k = P.shape[1]
    steps = _steps(P)
    rho, r = max(spot_radius_mm, 1e-3), max(radius_mm, 0.05)
    amp = np.asarray(amp, float)
    kept = amp >= threshold * amp.max()
    rel_noise, shape = _amp_noise(P, amp, P[kept].mean(axis=0), steps, rho, target, r)
    spot = _spot_samples(rho, shape)[:, :k]
    if count is not None:
        stretch = match_count(P, spot, target, r, threshold, count)
        spot, r = spot * stretch, r * stretch
    rng = np.random.default_rng(0)  # a fixed design sum: the same data give the same result
    c = P.mean(axis=0) + (rng.random((draws, k)) - 0.5) * steps
    noise = rng.standard_normal((draws, len(P)))
    err = np.empty((draws, k))
    chunk = max(1, int(PROFILE_ELEMENTS // max(len(P) * len(spot), 1)))  # bounded memory
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


def _center(S: np.ndarray, d: np.ndarray, amp: np.ndarray, threshold: float,
            radius_mm: float = 0.0, spot_radius_mm: float = 0.0, target: str = "strip",
            count: float | None = None
            ) -> tuple[np.ndarray, float, np.ndarray, tuple[np.ndarray, np.ndarray]] | None:
    """(stage reading S (mm), depth (mm), stage covariance (3, 3 mm^2), (kept points'
    lateral offsets, their depths) for depth_noise_var) of the center point of the ranged
    raw points above threshold x max amplitude (§IV-C), or None with fewer than
    MIN_POINTS. With a filament radius and target "strip" the points
    are a sweep across a filament: each depth is moved from the ranged front surface onto
    the axis (front_depth_mm of its offset from the sweep's centre). The lateral covariance
    is the raster's (raster_centroid_cov) in the raster's plane and the points' spread / n
    out of it (stage noise)."""
    ok, keep = _above(S, d, amp, threshold)
    n = int(keep.sum())
    if n < MIN_POINTS:
        return None
    Sk, dk = S[keep], d[keep]
    if radius_mm > 0 and target == "strip":
        _, _, vt = np.linalg.svd(S[ok] - S[ok].mean(axis=0))  # the sweep direction
        dk = dk + front_depth_mm((Sk - Sk.mean(axis=0)) @ vt[0], radius_mm, spot_radius_mm)
    spread = np.cov(Sk.T) / n
    # the raster's plane: the stage axes it steps along (a square raster has no SVD axes)
    span = np.ptp(S[ok], axis=0)
    U = np.eye(3)[:, span > max(0.2 * span.max(), 1e-3)]  # (3, k)
    if U.shape[1] in (1, 2) and spot_radius_mm > 0:
        out = np.eye(3) - U @ U.T
        Q = raster_centroid_cov((S[ok] - S[ok].mean(axis=0)) @ U, amp[ok], threshold, target,
                                radius_mm, spot_radius_mm, count=count)
        cov = U @ Q @ U.T + out @ spread @ out
    else:
        cov = spread
    return Sk.mean(axis=0), float(dk.mean()), cov, ((Sk - Sk.mean(axis=0)) @ U, dk)


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
    if dof < 1:
        return 0.0
    res = d - A @ np.linalg.lstsq(A, d, rcond=None)[0]
    return float(res @ res / dof)


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
    for f in np.unique(raw["frame"][is_tip]):
        m = is_tip & (raw["frame"] == f)
        c = _center(S[m], raw["d_mm"][m], raw["amplitude"][m], threshold, radius_mm,
                    spot_radius_mm, target="disk", count=tip_count)
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
                        spot_radius_mm, count=edge_count)
            if c is not None:
                got.append(c)
        if len(got) < 2:
            raise CalibrationError(
                f"edge frame {f:g}: {len(got)} of {len(lines)} scan lines have {MIN_POINTS} or "
                f"more ranged points above threshold (no echo or too weak): sweep across the "
                f"filament at two or more heights (--at, --edge-half)")
        heights = np.array([c[0] for c in got])
        span = np.ptp(heights - heights.mean(axis=0), axis=0).max()
        if span < 1.0:
            raise CalibrationError(f"edge frame {f:g}: its center points span {span:.2f} mm: "
                                   f"scan the filament at heights 1 mm or more apart "
                                   f"(--edge-levels)")
        edges += [(len(frames), *c) for c in got]
        frames.append(float(f))
        th = raw["theta_deg"][fm]
        thetas.append(float(np.median(th[np.isfinite(th)])) if np.isfinite(th).any()
                      else np.nan)
    if len(frames) < 2:
        raise CalibrationError(f"{len(frames)} edge frame(s): need edge frames at two or more "
                               f"turntable angles")
    _edge_angles(frames, thetas)
    return CalibrationData(
        np.array([t[0] for t in tips]), np.array([t[1] for t in tips]),
        np.array([e[1] for e in edges]), np.array([e[2] for e in edges]),
        np.array([e[0] for e in edges]), np.array(thetas), sigma_theta_deg=sigma_theta_deg,
        tip_cov_S=np.array([t[2] for t in tips]),
        tip_var_d=depth_noise_var([t[3] for t in tips]) / np.array([len(t[3][1]) for t in tips]),
        edge_cov_S=np.array([e[3] for e in edges]),
        edge_var_d=depth_noise_var([e[4] for e in edges]) / np.array([len(e[4][1])
                                                                      for e in edges]))
