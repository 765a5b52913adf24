"""Scanner calibration (paper §IV): v from tip frames, edges as Plücker lines, n and X_R from a
turntable rotation, then the joint maximum-likelihood refinement with covariances.

Plain functions on numpy arrays. Points are X = S + d v (eq. 1) in the sensor frame {0} (mm).
X_R is fixed to the point of the turntable axis with z = 0 (the gauge of Table I).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares


class CalibrationError(ValueError):
    """The data cannot determine the parameters; the message names the problem and the fix."""


def unit(x: np.ndarray) -> np.ndarray:
    """x / |x|."""
    x = np.asarray(x, dtype=float)
    return x / np.linalg.norm(x)


def rodrigues(n: np.ndarray, theta_rad: float) -> np.ndarray:
    """R_n(theta) = I + sin(theta)[n]x + (1 - cos(theta))[n]x^2 (eq. 5)."""
    n = unit(n)
    k = np.array([[0, -n[2], n[1]], [n[2], 0, -n[0]], [-n[1], n[0], 0]])
    return np.eye(3) + np.sin(theta_rad) * k + (1 - np.cos(theta_rad)) * (k @ k)


def tangent_basis(u: np.ndarray) -> np.ndarray:
    """3x2 orthonormal basis of the plane perpendicular to the unit vector u."""
    a = np.array([1.0, 0, 0]) if abs(u[0]) < 0.9 else np.array([0, 1.0, 0])
    b1 = unit(np.cross(u, a))
    return np.column_stack([b1, np.cross(u, b1)])


def tangent_errors(result: CalibrationResult, name: str, true: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Error of unit vector `name` ('v' or 'n') in its tangent plane and the matching standard
    deviations: the two first-order coordinates a unit vector has."""
    i = {"v": 0, "n": 3}[name]
    est = getattr(result, name)
    B = tangent_basis(est)
    cov = B.T @ result.cov[i:i + 3, i:i + 3] @ B
    return B.T @ (est - true), np.sqrt(np.maximum(np.diag(cov), 0))


def retract(u: np.ndarray, basis: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """u moved on the sphere by the tangent step basis @ delta (no pole singularity)."""
    return unit(u + basis @ delta)


def same_angle(a_deg: float, b_deg: float, tol_deg: float = 1.0) -> bool:
    """True if two turntable readings are the same angle modulo a turn (within tol_deg)."""
    return bool(abs((a_deg - b_deg + 180.0) % 360.0 - 180.0) < tol_deg)


# ---------------------------------------------------------------- closed-form estimates
def skew(a: np.ndarray) -> np.ndarray:
    """[a]_x: the matrix with [a]_x b = a x b."""
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


def estimate_v(S: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """v and the tip point from tip center points at >= 2 depths (eq. 2).

    All S_c + d_c v are the same tip point, so (S_c - S_mean) x v = 0: v is the null vector of
    the stacked [S_c - S_mean]_x, by SVD. Its sign makes v point from sensor to target: the
    depth shrinks as the sensor moves along v."""
    S, d = np.asarray(S, float), np.asarray(d, float)
    A = S - S.mean(axis=0) if len(S) else S
    if len(S) < 2 or np.ptp(d) < 1e-9 or np.linalg.norm(A, axis=1).max() < 1e-9:
        raise CalibrationError("need tip frames at two or more depths: step the sensor along "
                               "the beam between tip frames")
    v = np.linalg.svd(np.vstack([skew(a) for a in A]))[2][-1]
    if (A @ v) @ (d - d.mean()) > 0:
        v = -v
    tip = (S + d[:, None] * v).mean(axis=0)
    return v, tip


def fit_line(X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(direction q, moment m = centroid x q, centroid) of points by SVD (eqs. 3-4)."""
    X = np.asarray(X, float)
    if len(X) < 2:
        raise CalibrationError("an edge frame needs two or more center points")
    c = X.mean(axis=0)
    _, s, vt = np.linalg.svd(X - c)
    if s[0] < 1e-9:
        raise CalibrationError("the edge center points of a frame coincide: scan the edge "
                               "at two or more heights")
    q = vt[0]
    if q[2] < 0:
        q = -q
    return q, np.cross(c, q), c


def estimate_axis(lines: list[tuple[np.ndarray, np.ndarray]], thetas_deg: list[float]
                  ) -> tuple[np.ndarray, np.ndarray]:
    """n and X_R (z = 0) from edges (q, point) of frames at turntable angles theta (deg).

    n: the edges are the same filament turned about n, so n is the common direction the
    rotations preserve; for a filament standing along the axis it is the mean direction,
    otherwise the normal of the differences of the directions. X_R: where each edge crosses
    z = 0, the rotation maps one crossing onto the next; solved in the plane of the table."""
    th = np.radians(np.asarray(thetas_deg, float))
    if len(lines) < 2:
        raise CalibrationError("need edge frames at two or more turntable angles")
    for i in range(1, len(th)):
        if same_angle(thetas_deg[i], thetas_deg[0]):
            raise CalibrationError(f"edge frames 0 and {i} have the same turntable angle: "
                                   f"rotate the table between them")
    q = np.array([ln[0] for ln in lines])
    diffs = q[1:] - q[0]
    if np.linalg.norm(diffs, axis=1).max() < 1e-3:
        n = unit(q.mean(axis=0))
    else:
        _, _, vt = np.linalg.svd(diffs)
        n = vt[-1]
    if n[2] < 0:
        n = -n
    # crossings of each edge with z = 0
    P = []
    for qi, pi in lines:
        if abs(qi[2]) < 1e-6:
            raise CalibrationError("an edge is parallel to the table: hold the filament "
                                   "vertically for edge frames")
        P.append(pi - qi * pi[2] / qi[2])
    rows, rhs = [], []
    for i in range(1, len(lines)):
        R = rodrigues(n, th[i] - th[0])
        rows.append(np.eye(3) - R)
        rhs.append(P[i] - R @ P[0])
    A = np.vstack(rows)
    A = np.column_stack([A[:, 0], A[:, 1]])  # X_R = (x, y, 0)
    sol, *_ = np.linalg.lstsq(A, np.concatenate(rhs), rcond=None)
    return n, np.array([sol[0], sol[1], 0.0])


# ---------------------------------------------------------------- maximum likelihood
@dataclass
class CalibrationData:
    """Center points with their covariances (§IV-C) and turntable readings."""

    tip_S: np.ndarray          # (k, 3) stage readings of tip center points (mm)
    tip_d: np.ndarray          # (k,) depths (mm)
    edge_S: np.ndarray         # (m, 3)
    edge_d: np.ndarray         # (m,)
    edge_frame: np.ndarray     # (m,) frame index 0..F-1
    theta_deg: np.ndarray      # (F,) turntable reading per edge frame
    sigma_S_mm: float = 0.01   # stage reading noise of a center point (per axis)
    sigma_d_mm: float = 0.02   # depth noise of a center point
    sigma_theta_deg: float = 0.01
    filament_radius_mm: float = 0.0  # edge hits are on the front surface: moved onto the axis
    # per-point covariances (§IV-C: Sigma_ij = Sigma_P / n, sigma_ij = sigma_P / n); when
    # given they replace the scalar sigmas above
    tip_cov_S: np.ndarray | None = None   # (k, 3, 3) mm^2
    tip_var_d: np.ndarray | None = None   # (k,) mm^2
    edge_cov_S: np.ndarray | None = None  # (m, 3, 3)
    edge_var_d: np.ndarray | None = None  # (m,)

    def point_covs(self, which: str) -> tuple[np.ndarray, np.ndarray]:
        """(cov_S (k,3,3), var_d (k,)) of the tip or edge center points."""
        n = len(self.tip_d if which == "tip" else self.edge_d)
        cs = getattr(self, f"{which}_cov_S")
        vd = getattr(self, f"{which}_var_d")
        if cs is None:
            cs = np.broadcast_to(self.sigma_S_mm ** 2 * np.eye(3), (n, 3, 3))
        if vd is None:
            vd = np.full(n, self.sigma_d_mm ** 2)
        # a floor keeps single-point frames from claiming zero noise
        return cs + 1e-12 * np.eye(3), np.maximum(vd, 1e-12)


@dataclass
class CalibrationResult:
    """Estimates with standard deviations and the fit's residual."""

    v: np.ndarray
    n: np.ndarray
    X_R: np.ndarray
    std: dict[str, np.ndarray] = field(default_factory=dict)
    cov: np.ndarray | None = None
    rms_residual_mm: float = 0.0
    svd: dict[str, np.ndarray] = field(default_factory=dict)
    edge_depth_scatter_mm: float = 0.0  # the surface's share of an edge depth's std
    tip_depth_scatter_mm: float = 0.0   # the ranging's share of a tip depth's std
    # per center point at the solution: tip (k, 3) mm from the fitted tip; edge (m,) mm
    # from the fitted filament line; theta_deg (F,) fitted minus read table angle
    residuals: dict[str, np.ndarray] = field(default_factory=dict)
    # factor on the tips' center points' lateral covariances (the raster model, see
    # center_points.raster_centroid_cov), from the residuals
    lateral_scale: float = 1.0


SCALE_PRIOR_DOF = 4.0  # the declared lateral covariances (scale 1) count as this many
# residuals (a conjugate inverse-gamma prior), so a scale from the tips' 4 residual degrees
# of freedom cannot collapse, and the reported stds with it


def solve(data: CalibrationData, refine: bool = True, scatter_from_residuals: bool = True
          ) -> CalibrationResult:
    """SVD estimates (eqs. 2-7), then the joint MLE (eq. 8) by Levenberg-Marquardt; the
    depth scatters and the lateral scale are estimated from the residuals unless
    scatter_from_residuals is False (the covariances as given, as for the bound)."""
    v0, tip0 = estimate_v(data.tip_S, data.tip_d)
    frames = np.unique(data.edge_frame)
    if len(frames) < 2:
        raise CalibrationError("need edge frames at two or more turntable angles")
    lines, thetas = [], []
    for f in frames:
        sel = data.edge_frame == f
        X = data.edge_S[sel] + data.edge_d[sel, None] * v0 + data.filament_radius_mm * v0
        q, _, c = fit_line(X)
        lines.append((q, c))
        thetas.append(data.theta_deg[int(f)])
    n0, xr0 = estimate_axis(lines, thetas)
    svd = {"v": v0, "n": n0, "X_R": xr0}
    if not refine:
        return CalibrationResult(v0, n0, xr0, svd=svd)
    # filament line in the table frame at theta = 0: through point p0 with direction l0
    R0 = rodrigues(n0, -np.radians(thetas[0]))
    l0 = R0 @ lines[0][0]
    p0 = xr0 + R0 @ (lines[0][1] - xr0)
    Bv, Bn, Bl = tangent_basis(v0), tangent_basis(n0), tangent_basis(unit(l0))
    F = len(frames)
    tip_cS, tip_vd = data.point_covs("tip")
    edge_cS, edge_vd = data.point_covs("edge")

    def unpack(p: np.ndarray) -> tuple:
        v = retract(v0, Bv, p[0:2])
        n = retract(n0, Bn, p[2:4])
        xr = np.array([p[4], p[5], 0.0])
        q = retract(unit(l0), Bl, p[6:8])  # filament direction at theta = 0
        pt = p0 + Bl @ p[8:10]  # the line's point moves across the line only
        tip = p[10:13]
        th = p[13:13 + F]
        return v, n, xr, q, pt, tip, th

    extra = [0.0, 0.0]  # variances (mm^2) added to each tip and edge depth: see below
    scale = [1.0, 1.0]  # factors on the tips' and the edges' lateral covariances

    def residuals(p: np.ndarray, whiten: bool = True, depth: bool = False) -> np.ndarray:
        """Whitened residuals; depth=True: the tips' and the edges' unwhitened residuals
        along the beam with the variances their covariances give them (without `extra`)."""
        v, n, xr, q, pt, tip, th = unpack(p)
        # a tip point's noise: its stage reading covariance plus its depth variance along v
        X = data.tip_S + data.tip_d[:, None] * v - tip
        cov = scale[0] * tip_cS + tip_vd[:, None, None] * np.outer(v, v)
        if depth:
            out = [X @ v, np.einsum("i,kij,j->k", v, cov, v)]
            Bt = tangent_basis(v)  # across the beam: the raster's lateral plane
            lat = X @ Bt
            cl = np.einsum("ai,kab,bj->kij", Bt, tip_cS, Bt)
            lat_chi = [float(np.einsum("ki,kij,kj->", lat, np.linalg.inv(cl), lat))]
        elif whiten:
            cov = cov + extra[0] * np.outer(v, v)
            W = np.linalg.cholesky(np.linalg.inv(cov))  # (k, 3, 3)
            X = np.einsum("ki,kij->kj", X, W)
        r, dvar = [X.ravel()], []
        for i, f in enumerate(frames):
            sel = data.edge_frame == f
            X = data.edge_S[sel] + (data.edge_d[sel, None] + data.filament_radius_mm) * v
            R = rodrigues(n, np.radians(th[i]))
            li = R @ q
            pi = xr + R @ (pt - xr)
            rel = X - pi
            B = tangent_basis(li)
            perp = (rel - np.outer(rel @ li, li)) @ B  # across the line
            cS = np.einsum("ai,kab,bj->kij", B, edge_cS[sel], B)
            cov = scale[1] * cS + edge_vd[sel, None, None] * np.outer(B.T @ v, B.T @ v)
            if depth:
                e = unit(B.T @ v)
                r.append(perp @ e)
                dvar.append(np.einsum("i,kij,j->k", e, cov, e))
                w = np.array([-e[1], e[0]])  # across the line, across the beam
                lat_chi.append(float(np.sum((perp @ w) ** 2 /
                                            np.einsum("i,kij,j->k", w, cS, w))))
                continue
            if whiten:
                cov = cov + extra[1] * np.outer(B.T @ v, B.T @ v)
                W = np.linalg.cholesky(np.linalg.inv(cov))
                perp = np.einsum("ki,kij->kj", perp, W)
            r.append(perp.ravel())
        if depth:
            return out + [np.concatenate(r[1:]), np.concatenate(dvar), lat_chi]
        if whiten:
            r.append((th - np.asarray(thetas)) / data.sigma_theta_deg)
        return np.concatenate(r)

    p_init = np.concatenate([np.zeros(4), xr0[:2], np.zeros(4), tip0, thetas])
    # The points of one sweep share the patch of surface under the spot, so an edge center
    # point's depth scatters more than the sweep's spread / n says (rough graphite: ~0.05 mm);
    # a tip frame's depth carries the ranging's scale and offset errors at that distance.
    # Each is one variance for all depths of its kind, estimated from the residuals along the
    # beam (less the parameters acting there: the tip point's depth; the edge line's offset
    # and tilt, n, X_R) and the fit repeated with it: the covariances then match the scatter.
    for _ in range(8):
        sol = least_squares(residuals, p_init, method="lm", x_scale="jac")
        p_init = sol.x
        res = residuals(sol.x, depth=True)
        new = [max(0.0, float(np.sum(r ** 2) / (len(r) - k) - np.mean(var)))
               if len(r) > k else 0.0
               for r, var, k in ((res[0], res[1], 1), (res[2], res[3], 4))]
        # the lateral covariances (the raster model of a thresholded centroid, with the
        # amplitude noise the rasters show) are scaled to their residuals, tips and edges
        # each by its own factor: the model's profile is not the sensor's, and a tip's
        # centroid is a 2-D raster's, an edge's a 1-D sweep's; SCALE_PRIOR_DOF keeps the
        # tips' 4 degrees of freedom from collapsing the factor in an unlucky seed
        k, m = len(data.tip_d), len(data.edge_d)
        new_scale = [min(max((chi + SCALE_PRIOR_DOF) / (d + SCALE_PRIOR_DOF), 0.01), 100.0)
                     for chi, d in ((res[4][0], 2 * k - 4), (sum(res[4][1:]), m - 2 * F))]
        if not scatter_from_residuals:
            break
        if all(abs(a - b) <= 0.02 * max(a, b) + 1e-14 for a, b in zip(new, extra)) and \
                all(abs(a - b) <= 0.02 * max(a, b) for a, b in zip(new_scale, scale)):
            break
        extra[:] = new
        scale[:] = new_scale
    v, n, xr, *_ = unpack(sol.x)
    J = sol.jac
    cov_p = np.linalg.pinv(J.T @ J)  # residuals are whitened: no rescaling by s^2
    # heavy-tailed surface scatter on a few high-leverage points (both ends of an edge
    # frame) hides in the fit: where the residuals, leverage-corrected (the HC3 sandwich),
    # show more scatter than the model's covariance, that parameter's std is widened to it
    h = np.einsum("ij,jk,ik->i", J, cov_p, J)
    meat = (J * (sol.fun / np.maximum(1 - h, 1e-3))[:, None] ** 2).T @ J
    widen = np.sqrt(np.maximum(np.diag(cov_p @ meat @ cov_p) /
                               np.maximum(np.diag(cov_p), 1e-300), 1.0))
    cov_p = cov_p * np.outer(widen, widen)
    # to Cartesian: v, n via their tangent bases, X_R x y
    Jv = np.zeros((9, len(sol.x)))
    Jv[0:3, 0:2] = Bv
    Jv[3:6, 2:4] = Bn
    Jv[6, 4] = Jv[7, 5] = 1.0
    cov = Jv @ cov_p @ Jv.T
    sd = np.sqrt(np.maximum(np.diag(cov), 0))
    raw = residuals(sol.x, whiten=False)  # tip (k, 3), then 2 across-line mm per edge point
    rms_mm = float(np.sqrt(np.mean(raw ** 2)))
    k = len(data.tip_d)
    edge_res = np.empty(len(data.edge_d))
    order = np.concatenate([np.flatnonzero(data.edge_frame == f) for f in frames])
    edge_res[order] = np.linalg.norm(raw[3 * k:].reshape(-1, 2), axis=1)
    res = {"tip": raw[:3 * k].reshape(k, 3), "edge": edge_res,
           "theta_deg": unpack(sol.x)[6] - np.asarray(thetas)}
    return CalibrationResult(v, n, xr, {"v": sd[0:3], "n": sd[3:6], "X_R": sd[6:9]},
                             cov, rms_mm, svd, float(np.sqrt(extra[1])),
                             float(np.sqrt(extra[0])), res, float(scale[0]))


def cramer_rao_bound(design: CalibrationData) -> np.ndarray:
    """The Cramér-Rao bound (9x9 covariance of v, n, X_R in mm and unit-vector components)
    for a design: noise-free center points of the true parameters, with the noise levels in
    its sigmas / per-point covariances. It is the inverse Fisher information of the whitened
    model at the truth, where the MLE's covariance and the bound coincide."""
    r = solve(design, scatter_from_residuals=False)
    if r.rms_residual_mm > 1e-6:
        raise CalibrationError(f"a design must be noise-free center points of the true "
                               f"parameters (rms residual {r.rms_residual_mm:.2g} mm)")
    return r.cov
