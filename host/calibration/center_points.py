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


def _spot_samples(spot_radius_mm: float) -> np.ndarray:
    """Points (k, 2) spread evenly over the laser spot's disk (mm): an 11 x 11 grid inside it."""
    g = (np.arange(11) - 5) / 5.0
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    return spot_radius_mm * xy[(xy ** 2).sum(axis=1) <= 1.0]


def _profile(P: np.ndarray, c: np.ndarray, spot: np.ndarray, target: str, r: float
             ) -> np.ndarray:
    """Model amplitude (draws, n) at raster positions P (n, k) for target centres c
    (draws, k): the share of the spot on the target, a cylinder's side weighted by
    sqrt(cos) of the incidence (the OA signal falls as the light arrives obliquely)."""
    def rel(j: int) -> np.ndarray:  # (draws, n, spot samples) offsets along raster axis j
        return P[None, :, None, j] - c[:, None, None, j] + spot[None, None, :, j]

    if target == "strip":  # only the axis across the strip matters
        on = np.sqrt(np.sqrt(np.clip(1 - (rel(0) / r) ** 2, 0, None)))
    else:
        on = (sum(rel(j) ** 2 for j in range(P.shape[1])) < r * r).astype(float)
    return on.mean(axis=2)


def raster_centroid_cov(P: np.ndarray, amp: np.ndarray, threshold: float, target: str,
                        radius_mm: float, spot_radius_mm: float, draws: int = 400
                        ) -> np.ndarray:
    """Covariance (k, k) mm^2 of the center point of raster positions P (n, k; the raster's
    own plane, k = 1 or 2 axes) above threshold x max amplitude, over the raster's unknown
    phase: the amplitude is the share of the spot (uniform disk) on the target, a disk of
    radius_mm seen end on ("disk": the tip) or a strip of half-width radius_mm ("strip": a
    filament swept across), with the relative amplitude noise the measured amplitudes `amp`
    (n,) show about that profile, which moves points across the threshold. The raster and
    the noise, not the points' spread / n, set how far a thresholded centroid moves."""
    P = np.asarray(P, float)
    k = P.shape[1]
    steps = []
    for j in range(k):
        u = np.unique(np.round(P[:, j], 4))
        dif = np.diff(u)
        steps.append(float(np.median(dif[dif > 1e-4])) if (dif > 1e-4).any() else 0.0)
    spot = _spot_samples(max(spot_radius_mm, 1e-3))[:, :k]
    r = max(radius_mm, 0.05)
    rng = np.random.default_rng(0)  # a fixed design sum: the same data give the same result
    c = P.mean(axis=0) + (rng.random((draws, k)) - 0.5) * np.asarray(steps)
    amp = np.asarray(amp, float)
    kept = amp >= threshold * amp.max()
    prof = _profile(P, P[kept].mean(axis=0)[None], spot, target, r)[0]
    gain = float(prof @ amp / max(prof @ prof, 1e-12))
    near = prof > 0.25 * prof.max()
    # robust (median) scale: the profile is a model, and its misfit at the target's rim
    # would pass for noise
    rel = (amp[near] / gain - prof[near]) / prof[near]
    rel_noise = float(np.clip(1.4826 * np.median(np.abs(rel)) if near.any() else 0.0, 0, 0.5))
    amp = _profile(P, c, spot, target, r) * (1 + rel_noise * rng.standard_normal((draws, len(P))))
    keep = amp >= threshold * amp.max(axis=1, keepdims=True)
    cnt = np.maximum(keep.sum(axis=1), 1)
    err = (keep[..., None] * P[None]).sum(axis=1) / cnt[:, None] - c
    return err.T @ err / draws


def _center(S: np.ndarray, d: np.ndarray, amp: np.ndarray, threshold: float,
            radius_mm: float = 0.0, spot_radius_mm: float = 0.0, target: str = "strip"
            ) -> tuple[np.ndarray, float, np.ndarray, float] | None:
    """Center point of the ranged raw points above threshold x max amplitude (§IV-C), or
    None with fewer than MIN_POINTS. With a filament radius and target "strip" the points
    are a sweep across a filament: each depth is moved from the ranged front surface onto
    the axis (front_depth_mm of its offset from the sweep's centre). The lateral covariance
    is the raster's (raster_centroid_cov) in the raster's plane and the points' spread / n
    out of it (stage noise)."""
    ok = np.isfinite(d) & np.isfinite(amp) & np.isfinite(S).all(axis=1)
    if not ok.any():
        return None
    keep = ok & (amp >= threshold * np.max(amp[ok]))
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
                                radius_mm, spot_radius_mm)
        cov = U @ Q @ U.T + out @ spread @ out
    else:
        cov = spread
    return Sk.mean(axis=0), float(dk.mean()), cov, float(np.var(dk, ddof=1) / n)


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
    for f in np.unique(raw["frame"][is_tip]):
        m = is_tip & (raw["frame"] == f)
        c = _center(S[m], raw["d_mm"][m], raw["amplitude"][m], threshold, radius_mm,
                    spot_radius_mm, target="disk")
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
                        spot_radius_mm)
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
        tip_cov_S=np.array([t[2] for t in tips]), tip_var_d=np.array([t[3] for t in tips]),
        edge_cov_S=np.array([e[3] for e in edges]), edge_var_d=np.array([e[4] for e in edges]))
