"""An object's points fused into one set: each point's 3x3 covariance (mm^2) and the outlier rule.

Pure functions on numpy arrays. A point is P = B^T R_n(-theta) (S + d v - X_R) in the object
frame (host/scan/reconstruct.py). Its covariance is propagated to first order (analytic
Jacobians; central differences for the table frame's dependence on n) from the distance's std
along v, the stage's per-axis noise, the table angle's noise and the calibration's
per-component stds of v, n and X_R. The parts are returned separately by `covariance_parts`:
the point's own (distance, stage), which neighbouring points do not share, and the common part
(calibration, table angle), which they do and which no local fit averages down.

The outlier rule (`outliers`) and the surface's vertex fits (surface.py) share `local_fit`: a
weighted, robust (Tukey) quadratic height fit in a local frame, with its sandwich variance.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..scan.reconstruct import object_points, stage_points, table_frame

OK, OFF_SURFACE, ISOLATED, NOT_SMOOTH = 0, 1, 2, 3
REASONS = {OK: "ok", OFF_SURFACE: "off the surface", ISOLATED: "too few neighbours",
           NOT_SMOOTH: "neighbourhood not one smooth surface (kept, not tested)"}
_MAX_ANGLES = 512   # object_points loops over distinct angles; beyond this, the same formula
TUKEY_C = 4.685     # Tukey biweight's cut-off in robust scales
LONE = 0.6          # a point with no neighbour within this fraction of the radius is isolated,
LONE_CLUSTER = 3    # and so is a cluster of at most this many, each near only the others


def _rz(theta_deg: np.ndarray) -> np.ndarray:
    """(k, 3, 3) rotations about z by -theta (deg)."""
    t = -np.radians(np.asarray(theta_deg, float))
    c, s = np.cos(t), np.sin(t)
    R = np.zeros((len(t), 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1] = c, -s, s, c
    R[:, 2, 2] = 1.0
    return R


def covariance_parts(S_mm: np.ndarray, d_mm: np.ndarray, d_std_mm: np.ndarray,
                     theta_deg: np.ndarray, v: np.ndarray, n: np.ndarray, X_R: np.ndarray,
                     v_std: np.ndarray, n_std: np.ndarray, X_R_std: np.ndarray,
                     stage_std_mm: float = 0.01, table_std_deg: float = 0.01,
                     travel_mm: np.ndarray | None = None, cal_cov: np.ndarray | None = None,
                     offset_std_mm: float = 0.0
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Object-frame points P (k, 3) mm and their covariance (k, 3, 3) mm^2 in two parts:
    (P, own, common). own: the distance's std along v (d_std_mm, mm), the stage's noise
    (stage_std_mm per axis) and, with travel_mm (k, 3; stage frame, mm: the stage's travel
    while the shot was averaged), that travel's smear: where along it the echo came from is
    unknown, a uniform spread of variance travel^2 / 12 along it; common: the calibration
    (v_std, n_std per component, unitless; X_R_std mm; or with cal_cov, their joint 9 x 9
    covariance from `dmdsm calibrate`, v, n, X_R in that order: the rig fixes the table's
    axis at the heights it saw, so an error of n's tilt and one of X_R mostly cancel there,
    and the per-component stds alone overstate the points' error by up to 3x) and the table
    angle (table_std_deg, deg, shared by the points of one stop) and, offset_std_mm, an
    error of every distance alike (a ranging calibration's t0 the geometric one did not
    absorb, mm along v).
    Raises ValueError on a non-finite d_std (a distance without its std has no covariance)."""
    S = np.asarray(S_mm, float).reshape(-1, 3)
    d = np.asarray(d_mm, float).ravel()
    d_std = np.asarray(d_std_mm, float).ravel()
    theta = np.asarray(theta_deg, float).ravel()
    v, n, X_R = (np.asarray(a, float) for a in (v, n, X_R))
    if not (len(S) == len(d) == len(d_std) == len(theta)):
        raise ValueError("S, d, d_std and theta must have one row per point")
    if not np.isfinite(d_std).all():
        raise ValueError(f"{int((~np.isfinite(d_std)).sum())} distances have no std: "
                         "give d_std for every point")
    vn = np.linalg.norm(v)
    vu = v / vn
    B = table_frame(n)
    rel = S + d[:, None] * vu - X_R
    Rz = _rz(theta)
    if len(np.unique(theta)) <= _MAX_ANGLES:
        P = object_points(stage_points(S, d, v), theta, n, X_R)
    else:   # the same map, B^T R_n(-theta) = R_z(-theta) B^T, without a loop per angle
        P = np.einsum("kij,kj->ki", Rz, rel @ B)
    M = Rz @ B.T                                      # dP/dX, (k, 3, 3)
    own = (d_std ** 2)[:, None, None] * np.einsum("ki,kj->kij", M @ vu, M @ vu)
    own += stage_std_mm ** 2 * np.eye(3)              # M M^T = I
    if travel_mm is not None:
        own += _travel_cov(M, travel_mm)
    Jv = d[:, None, None] * (M @ ((np.eye(3) - np.outer(vu, vu)) / vn))
    h = 1e-6
    Jn = np.empty((len(S), 3, 3))
    for j in range(3):
        e = np.zeros(3)
        e[j] = h
        dBt = (table_frame(n + e) - table_frame(n - e)).T / (2 * h)
        Jn[:, :, j] = np.einsum("kij,kj->ki", Rz, rel @ dBt.T)
    if cal_cov is not None:   # v, n and X_R together: the rig pins the axis where it saw it
        J = np.concatenate([Jv, Jn, -M], axis=2)      # (k, 3, 9)
        common = np.einsum("kia,ab,kjb->kij", J, np.asarray(cal_cov, float), J)
    else:
        common = np.einsum("kij,j,klj->kil", Jv, np.asarray(v_std, float) ** 2, Jv)
        common += np.einsum("kij,j,klj->kil", M, np.asarray(X_R_std, float) ** 2, M)
        common += np.einsum("kij,j,klj->kil", Jn, np.asarray(n_std, float) ** 2, Jn)
    if offset_std_mm:
        common += offset_std_mm ** 2 * np.einsum("ki,kj->kij", M @ vu, M @ vu)
    Jt = np.radians(1.0) * np.column_stack([P[:, 1], -P[:, 0], np.zeros(len(P))])
    common += table_std_deg ** 2 * np.einsum("ki,kj->kij", Jt, Jt)
    return P, own, common


def _travel_cov(M: np.ndarray, travel_mm: np.ndarray) -> np.ndarray:
    """(k, 3, 3) mm^2: a uniform spread along each shot's travel (stage frame, mm), mapped to
    the object frame by M (k, 3, 3)."""
    t = np.einsum("kij,kj->ki", M, np.asarray(travel_mm, float).reshape(-1, 3))
    return np.einsum("ki,kj->kij", t, t) / 12.0


def travel_covariance(theta_deg: np.ndarray, n: np.ndarray, travel_mm: np.ndarray
                      ) -> np.ndarray:
    """The travel smear's part (k, 3, 3) mm^2 of covariance_parts' own part, in the object
    frame: model building treats it apart (surface.build_surface's cov_repeat), since it is
    set by the surface's slope along the travel, which every scan of that place repeats."""
    return _travel_cov(_rz(np.asarray(theta_deg, float).ravel()) @ table_frame(
        np.asarray(n, float)).T, travel_mm)


def point_covariances(S_mm: np.ndarray, d_mm: np.ndarray, d_std_mm: np.ndarray,
                      theta_deg: np.ndarray, v: np.ndarray, n: np.ndarray, X_R: np.ndarray,
                      v_std: np.ndarray, n_std: np.ndarray, X_R_std: np.ndarray,
                      stage_std_mm: float = 0.01, table_std_deg: float = 0.01
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Object-frame points P (k, 3) mm and each point's full covariance (k, 3, 3) mm^2: the
    sum of covariance_parts' own and common parts (see there for the inputs and units)."""
    P, own, common = covariance_parts(S_mm, d_mm, d_std_mm, theta_deg, v, n, X_R, v_std,
                                      n_std, X_R_std, stage_std_mm, table_std_deg)
    return P, own + common


def _median(a: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Row-wise median of a over its valid entries (each row needs one)."""
    s = np.sort(np.where(valid, a, np.inf), axis=1)
    m = valid.sum(axis=1)
    r = np.arange(len(a))
    return 0.5 * (s[r, (m - 1) // 2] + s[r, m // 2])


def local_fit(x: np.ndarray, Q: np.ndarray, valid: np.ndarray, cov: np.ndarray,
              h_mm: float | np.ndarray, ref_normal: np.ndarray | None = None, iters: int = 4,
              curvature_prior: float = 1e-9, point_var: np.ndarray | None = None
              ) -> dict[str, np.ndarray]:
    """Robust weighted quadratic fit of each centre's neighbours, evaluated at the centre.

    x (m, 3) centres, Q (m, K, 3) neighbours (mm), valid (m, K) which of them are real (each row
    needs >= 6), cov (m, K, 3, 3) their covariances (mm^2), h_mm the Gaussian weight's scale
    (one, or (m,): each centre its own).
    The frame's normal is the weighted PCA normal (signed along ref_normal if given); the
    height z(u, v) = a0 + a1 u + a2 v + a3 u^2 + a4 uv + a5 v^2 is refitted `iters` times with
    Tukey weights on residuals over max(1.4826 MAD, the points' own std along the normal).
    point_var (m, K) mm^2, if given: each neighbour's variance along its own surface normal;
    the Gaussian weights are then times median(point_var) / point_var (inverse variance, so
    a smeared or weak point counts less than a precise one) and the Tukey scale grows with
    sqrt(point_var / median). Along its own normal, not the frame's: at an edge the other
    face's points have their noise across the frame's normal and would look precise.
    Returns: offset (m,) mm, the fitted surface's height above the centre along `normal`;
    normal (m, 3), the fitted surface's unit normal there; var (m,) mm^2, the offset's variance
    from the points' covariances (sandwich, weights fixed); chi2 (m,), the weighted residuals'
    reduced chi-square over their propagated variances, with n_eff (m,) the weights' effective
    number of points (sum w)^2 / sum w^2, and chi2_robust (m,) the same from the residuals'
    MAD over their stds (blind to the points the robust fit dropped); rejected (m,), the weight
    fraction the robust fit dropped; centred (m,), the weighted centroid's tangential offset
    over h_mm; and per neighbour s2 (m, K) its variance along the normal, w (m, K) its final
    weight, w0 (m, K) its Gaussian weight before the robust pass, r (m, K) its residual
    (mm), g0 (m, K) the offset's derivative by its height (var = sum g0^2 s2)."""
    m, K = valid.shape
    h_mm = np.broadcast_to(np.asarray(h_mm, float), (m,))[:, None]  # one scale per centre
    d = Q - x[:, None, :]
    w0 = valid * np.exp(-0.5 * ((d * d).sum(axis=2) / h_mm ** 2))
    sw = w0.sum(axis=1)
    c = np.matmul(w0[:, None, :], d)[:, 0, :] / sw[:, None]
    dc = d - c[:, None, :]
    C = np.matmul((dc * w0[:, :, None]).transpose(0, 2, 1), dc)
    _, vec = np.linalg.eigh(C)
    nrm, t1, t2 = vec[:, :, 0], vec[:, :, 2], vec[:, :, 1]
    if ref_normal is not None:
        flip = np.einsum("mi,mi->m", nrm, ref_normal) < 0
        nrm[flip] *= -1
        t1[flip] *= -1
    u, v, z = np.matmul(d, np.stack([t1 / h_mm, t2 / h_mm, nrm], axis=2)).transpose(2, 0, 1)
    A = np.stack([np.ones_like(u), u, v, u * u, u * v, v * v], axis=2)
    s2 = np.einsum("mkj,mj->mk", np.matmul(cov, nrm[:, None, :, None])[..., 0], nrm)
    s2 = np.where(valid, np.maximum(s2, 1e-12), 1.0)
    zs = np.ones_like(s2)
    wq = w0
    if point_var is not None:
        pv = np.where(valid, np.maximum(point_var, 1e-12), 1.0)
        ref = _median(pv, valid)[:, None]
        wq = w0 * ref / pv
        zs = np.sqrt(pv / ref)
    w = wq.copy()
    # curvature_prior: a ridge on the quadratic terms (u, v in weight scales), times sum w.
    # Where the neighbours span too few rows in one direction (a scan's levels near the
    # band's edge: two rows) that curvature is not determined, and without a prior the fit
    # is singular and its height wild; with one that direction is fitted as a plane.
    ridge = np.diag([1e-9, 1e-9, 1e-9] + [curvature_prior] * 3)
    for it in range(iters + 1):
        Aw = A * w[:, :, None]
        Ninv = np.linalg.inv(np.matmul(Aw.transpose(0, 2, 1), A) + ridge * sw[:, None, None])
        a = np.matmul(Ninv, np.matmul(Aw.transpose(0, 2, 1), z[:, :, None]))[:, :, 0]
        r = z - np.matmul(A, a[:, :, None])[:, :, 0]
        if it == iters:
            break
        mad = 1.4826 * _median(np.abs(r) / zs, valid)
        scale = np.maximum(mad, np.sqrt(_median(s2, valid)))
        t = r / (TUKEY_C * scale[:, None] * zs)
        w = wq * np.where(np.abs(t) < 1, (1 - t * t) ** 2, 0.0)
    g0 = np.matmul(Aw, Ninv[:, 0, :, None])[:, :, 0]       # d a0 / d z_k
    var = np.einsum("mk,mk->m", g0 ** 2, s2)
    sw_f = w.sum(axis=1)
    n_eff = sw_f ** 2 / np.maximum((w * w).sum(axis=1), 1e-300)
    chi2 = (np.einsum("mk,mk->m", w, r * r / s2) / np.maximum(sw_f, 1e-300)
            * n_eff / np.maximum(n_eff - 6, 1.0))
    chi2_robust = ((1.4826 * _median(np.abs(r) / np.sqrt(s2), valid)) ** 2
                   * n_eff / np.maximum(n_eff - 6, 1.0))
    g = np.column_stack([-a[:, 1], -a[:, 2], h_mm[:, 0]])
    g /= np.linalg.norm(g, axis=1)[:, None]
    normal = g[:, :1] * t1 + g[:, 1:2] * t2 + g[:, 2:] * nrm
    cen = np.hypot(np.einsum("mi,mi->m", c, t1), np.einsum("mi,mi->m", c, t2)) / h_mm[:, 0]
    return {"offset": a[:, 0], "normal": normal, "frame_normal": nrm, "var": var,
            "chi2": chi2, "chi2_robust": chi2_robust, "n_eff": n_eff,
            "rejected": 1 - sw_f / wq.sum(axis=1), "centred": cen, "s2": s2, "w": w, "w0": w0,
            "r": r, "g0": g0}


def neighbourhood_radius(P_mm: np.ndarray, target: int = 20, min_mm: float = 1.0,
                         max_mm: float = 8.0, sample: int = 400, rows: float = 2.2) -> float:
    """A local fit's radius (mm, within min_mm..max_mm) from the points' density: the smallest
    r (steps of 10 %) within which the median point (of a fixed subsample) has >= target other
    points spread over the surface (second PCA eigenvalue >= 0.25 of the first), and at least
    `rows` times the median largest gap between the neighbours' projections on either in-plane
    axis. Dense rows a level apart have that gap = the level spacing, so the radius spans about
    five levels (a quadratic needs several); on evenly spread points the gap is small."""
    P = np.asarray(P_mm, float)
    if len(P) < 3:
        return max_mm
    tree = cKDTree(P)
    sub = P[np.random.default_rng(0).choice(len(P), min(sample, len(P)), replace=False)]
    r = min_mm
    while r < max_mm:
        if np.median(tree.query_ball_point(sub, r, return_length=True)) - 1 >= target:
            ratio, gap = [], []
            for nb in tree.query_ball_point(sub, r):
                Q = P[nb] - P[nb].mean(axis=0)
                ev, vec = np.linalg.eigh(Q.T @ Q)
                ratio.append(ev[1] / max(ev[2], 1e-300))
                gap.append(max(np.diff(np.sort(Q @ vec[:, i])).max(initial=0.0)
                               for i in (1, 2)))
            if np.median(ratio) >= 0.25:
                return float(min(max(r, rows * np.median(gap)), max_mm))
        r *= 1.1
    return max_mm


def outliers(P_mm: np.ndarray, cov: np.ndarray, radius_mm: float | None = None,
             k_sigma: float = 5.0, min_neighbours: int = 8, max_neighbours: int = 32,
             max_rejected: float = 0.3, passes: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Which points to keep, and why: (keep (k,) bool, reason (k,) int8, codes in REASONS):
    _outlier_pass's rule, applied again to the points kept so far (at most `passes` times,
    the radius fixed by the first): two gross errors side by side each look like the other's
    rough surface (NOT_SMOOTH, kept) until one of them is gone."""
    P = np.asarray(P_mm, float)
    if radius_mm is None and len(P):
        radius_mm = neighbourhood_radius(P, target=60, min_mm=1.5)
    keep, reason = _outlier_pass(P, cov, radius_mm, k_sigma, min_neighbours, max_neighbours,
                                 max_rejected)
    for _ in range(passes - 1):
        kept = np.flatnonzero(keep)
        if len(kept) == len(P) or not len(kept):
            break
        k2, r2 = _outlier_pass(P[kept], np.asarray(cov, float)[kept], radius_mm, k_sigma,
                               min_neighbours, max_neighbours, max_rejected)
        if k2.all():
            break
        reason[kept] = r2
        keep[kept] = k2
    return keep, reason


def _small_clusters(idx: np.ndarray, close: np.ndarray, k: int) -> np.ndarray:
    """(k,) True for the points of the connected groups of at most LONE_CLUSTER points
    under "within LONE * radius" (idx: each point's neighbours, close: which of them are
    that near)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    rows = np.repeat(np.arange(k), close.shape[1])[close.ravel()]
    graph = coo_matrix((np.ones(len(rows), np.int8), (rows, idx[close])), shape=(k, k))
    _, label = connected_components(graph, directed=False)
    return np.bincount(label)[label] <= LONE_CLUSTER


def _outlier_pass(P_mm: np.ndarray, cov: np.ndarray, radius_mm: float | None = None,
                  k_sigma: float = 5.0, min_neighbours: int = 8, max_neighbours: int = 32,
                  max_rejected: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    """One pass of the outlier rule over all points: (keep, reason).

    The rule: a point's neighbours within radius_mm (the nearest max_neighbours, up to 1.2 times
    the median count within the radius and at most 2 max_neighbours, itself left out; radius_mm
    defaults to neighbourhood_radius for 60 points, so a scan's open rim still has ~30) get a
    robust quadratic fit (local_fit, Gaussian weight scale radius_mm). The point is OFF_SURFACE
    when its distance e along the fit's normal exceeds k_sigma * s, s^2 = n^T cov n + the fit's
    variance at it + the misfit: with chi2 the fit's reduced chi-square and s2 its points' mean
    variance along n, the fit's variance is scaled by max(1, chi2) and (chi2 - 1)+ * s2 added.
    On a smooth surface (chi2 ~ 1) that is its own and the fit's propagated std; where the
    neighbours do not fit one smooth surface at their noise (an edge, a corner), the bound
    widens with their misfit, so the edge's own points stay and only errors well beyond the
    misfit go. ISOLATED: fewer than min_neighbours neighbours, or none within LONE *
    radius_mm (a point that far off a surface sees it only as a ring, which fits poorly), or
    only the others of a cluster of at most LONE_CLUSTER points (two gross errors side by
    side: the fit bent to the pair and its misfit hid both). NOT_SMOOTH:
    kept, but the fit dropped more than max_rejected of its weight or its chi2 exceeds 1 by 4 of
    its stds (sqrt(2 / (n_eff - 6))), so it was tested at the wider bound.
    Kept: OK and NOT_SMOOTH. The quadratic follows a radius of 15 mm to a few um over the
    radius, so a curved surface's good points pass.
    """
    P = np.asarray(P_mm, float)
    cov = np.asarray(cov, float)
    k = len(P)
    reason = np.full(k, ISOLATED, np.int8)
    if k == 0:
        return np.zeros(0, bool), reason
    tree = cKDTree(P)
    if radius_mm is None:
        radius_mm = neighbourhood_radius(P, target=60, min_mm=1.5)
    counts = tree.query_ball_point(P, radius_mm, return_length=True, workers=-1)
    kq = int(min(max(max_neighbours, 1.2 * np.median(counts)), 2 * max_neighbours, k - 1)) + 1
    dist, idx = tree.query(P, k=kq, distance_upper_bound=radius_mm, workers=-1)
    dist, idx = dist.reshape(k, kq), idx.reshape(k, kq)
    valid = np.isfinite(dist) & (idx != np.arange(k)[:, None])
    close = valid & (dist <= LONE * radius_mm)
    has = (valid.sum(axis=1) >= max(min_neighbours, 6)) & close.any(axis=1) & \
        ~_small_clusters(idx, close, k)
    for lo in range(0, k, 20000):
        sel = np.flatnonzero(has[lo:lo + 20000]) + lo
        if len(sel) == 0:
            continue
        ii = np.where(valid[sel], idx[sel], 0)
        f = local_fit(P[sel], P[ii], valid[sel], cov[ii], radius_mm)
        n = f["frame_normal"]
        own = np.einsum("mi,mij,mj->m", n, cov[sel], n)
        w = f["w"]
        ms2 = (w * f["s2"]).sum(axis=1) / np.maximum(w.sum(axis=1), 1e-300)
        excess = np.maximum(f["chi2"] - 1.0, 0.0)
        s = np.sqrt(own + f["var"] * (1.0 + excess) + excess * ms2)
        off = np.abs(f["offset"]) > k_sigma * s
        rough = (f["rejected"] > max_rejected) | (
            f["chi2"] > 1 + 4 * np.sqrt(2 / np.maximum(f["n_eff"] - 6, 1)))
        reason[sel] = np.where(off, OFF_SURFACE, np.where(rough, NOT_SMOOTH, OK))
    return (reason == OK) | (reason == NOT_SMOOTH), reason
