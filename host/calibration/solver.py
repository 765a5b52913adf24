"""Scanner calibration (paper §IV): v from tip frames, edges as Plücker lines, n and X_R from a
turntable rotation, then the joint maximum-likelihood refinement with covariances.

Plain functions on numpy arrays. Points are X = S + d v (eq. 1) in the sensor frame {0} (mm).
X_R is fixed to the point of the turntable axis with z = 0 (the gauge of Table I). `solve`
runs the steps in order: `svd_estimate` (`estimate_v`: eq. 2; `edge_lines`: eqs. 3-4;
`estimate_axis`: eqs. 5-7), then in mle.py `gauge_fix`, `fit` (eq. 8), `covariance` and
`point_residuals`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from . import mle
from .geometry import retract, rodrigues, same_angle, skew, tangent_basis, unit

__all__ = [  # the geometry is imported from here too
    "CalibrationData", "CalibrationError", "CalibrationResult", "SvdEstimate", "angle_std_deg",
    "cramer_rao_bound",
    "edge_lines", "edge_points", "estimate_axis", "estimate_v", "fit_line", "mle_problem",
    "retract", "rodrigues", "same_angle", "skew", "solve", "svd_estimate", "tangent_basis",
    "tangent_errors", "unit",
]


class CalibrationError(ValueError):
    """The data cannot determine the parameters; the message names the problem and the fix."""


# ---------------------------------------------------------------- closed-form estimates
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


# ---------------------------------------------------------------- data and result
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
    # (k, 3) mm/mm: how a tip center point's depth follows its stage reading's error (the
    # face's slope across the raster: center_points.depth_gradient); None: not at all
    tip_grad: np.ndarray | None = None
    # (m,) mm: the part of each edge depth that moved it from the front surface onto the
    # axis for a beam square to the filament (center_points: front_depth_mm); the MLE
    # divides it by the sine of the beam's angle to the filament
    edge_front_mm: np.ndarray | None = None

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
    # unit vectors v, n: the std (deg) of the angle between estimate and truth, the root of
    # the trace of the covariance in the tangent plane (a unit vector's error is an angle:
    # its largest component's std is second order and says nothing)
    angle_std_deg: dict[str, float] = field(default_factory=dict)


def angle_std_deg(cov: np.ndarray, u: np.ndarray, i: int) -> float:
    """RMS angle (deg) between the unit vector u and its truth, from the 3 x 3 block at
    (i, i) of the 9 x 9 covariance: sqrt of the trace of the tangent-plane covariance."""
    B = tangent_basis(u)
    return float(np.degrees(np.sqrt(max(np.trace(B.T @ cov[i:i + 3, i:i + 3] @ B), 0.0))))


def tangent_errors(result: CalibrationResult, name: str, true: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Error of unit vector `name` ('v' or 'n') in its tangent plane and the matching standard
    deviations: the two first-order coordinates a unit vector has."""
    i = {"v": 0, "n": 3}[name]
    est = getattr(result, name)
    B = tangent_basis(est)
    cov = B.T @ result.cov[i:i + 3, i:i + 3] @ B
    return B.T @ (est - true), np.sqrt(np.maximum(np.diag(cov), 0))


# ---------------------------------------------------------------- the steps of solve
class SvdEstimate(NamedTuple):
    """The closed-form estimates (eqs. 2-7) and the edges they came from."""

    v: np.ndarray
    tip: np.ndarray                              # the tip point (mm)
    n: np.ndarray
    X_R: np.ndarray                              # on z = 0 (mm)
    frames: np.ndarray                           # the edge frames' indices, sorted
    lines: list[tuple[np.ndarray, np.ndarray]]   # per edge frame: direction q, centroid
    thetas: list[float]                          # per edge frame: table angle read (deg)


def edge_points(S: np.ndarray, d: np.ndarray, v: np.ndarray, radius_mm: float) -> np.ndarray:
    """Edge center points in {0}, X = S + d v (eq. 1), moved by the filament radius along the
    beam onto its axis."""
    return S + d[:, None] * v + radius_mm * v


def edge_lines(data: CalibrationData, v: np.ndarray
               ) -> tuple[np.ndarray, list[tuple[np.ndarray, np.ndarray]], list[float]]:
    """(frames, lines, thetas): each edge frame's points (eq. 1 with v) as a line by SVD,
    direction q and centroid (the Plücker line q, m = centroid x q: eqs. 3-4), and its table
    angle."""
    frames = np.unique(data.edge_frame)
    if len(frames) < 2:
        raise CalibrationError("need edge frames at two or more turntable angles")
    lines, thetas = [], []
    for f in frames:
        sel = data.edge_frame == f
        q, _, c = fit_line(edge_points(data.edge_S[sel], data.edge_d[sel], v,
                                       data.filament_radius_mm))
        lines.append((q, c))
        thetas.append(data.theta_deg[int(f)])
    return frames, lines, thetas


def svd_estimate(data: CalibrationData) -> SvdEstimate:
    """v by SVD of the tip frames (eq. 2), the edges as lines (eqs. 3-4), then n and X_R from
    the turn between them (eqs. 5-7)."""
    v, tip = estimate_v(data.tip_S, data.tip_d)
    frames, lines, thetas = edge_lines(data, v)
    n, xr = estimate_axis(lines, thetas)
    return SvdEstimate(v, tip, n, xr, frames, lines, thetas)


def mle_problem(data: CalibrationData, frames: np.ndarray, thetas: list[float]) -> mle.Problem:
    """The center points with their per-point covariances (§IV-C), as the MLE (eq. 8) takes
    them."""
    tip_cS, tip_vd = data.point_covs("tip")
    edge_cS, edge_vd = data.point_covs("edge")
    front = np.zeros(len(data.edge_d)) if data.edge_front_mm is None else \
        np.asarray(data.edge_front_mm, float)
    grad = np.zeros((len(data.tip_d), 3)) if data.tip_grad is None else \
        np.asarray(data.tip_grad, float)
    return mle.Problem(data.tip_S, data.tip_d, tip_cS, tip_vd, data.edge_S, data.edge_d,
                       edge_cS, edge_vd, data.edge_frame, frames, thetas,
                       data.filament_radius_mm, data.sigma_theta_deg, front, grad)


def solve(data: CalibrationData, refine: bool = True, scatter_from_residuals: bool = True
          ) -> CalibrationResult:
    """SVD estimates (eqs. 2-7), then the joint MLE (eq. 8) by Levenberg-Marquardt; the
    depth scatters and the lateral scale are estimated from the residuals unless
    scatter_from_residuals is False (the covariances as given, as for the bound)."""
    est = svd_estimate(data)
    svd = {"v": est.v, "n": est.n, "X_R": est.X_R}
    if not refine:
        return CalibrationResult(est.v, est.n, est.X_R, svd=svd)
    problem = mle_problem(data, est.frames, est.thetas)
    gauge, p_init = mle.gauge_fix(est.v, est.n, est.X_R, est.tip, est.lines, est.thetas)
    fit = mle.fit(problem, gauge, p_init, scatter_from_residuals)
    p = gauge.unpack(fit.x, len(est.frames))
    cov = mle.covariance(fit, gauge)
    sd = np.sqrt(np.maximum(np.diag(cov), 0))
    raw = mle.raw_residuals(fit.x, problem, gauge)
    return CalibrationResult(
        p.v, p.n, p.X_R, std={"v": sd[0:3], "n": sd[3:6], "X_R": sd[6:9]}, cov=cov,
        rms_residual_mm=float(np.sqrt(np.mean(raw ** 2))), svd=svd,
        edge_depth_scatter_mm=float(np.sqrt(max(fit.depth_var[1], 0.0))),
        tip_depth_scatter_mm=float(np.sqrt(max(fit.depth_var[0], 0.0))),
        residuals=mle.point_residuals(raw, problem, p.theta_deg),
        lateral_scale=float(fit.lateral_scale[0]),
        angle_std_deg={"v": angle_std_deg(cov, p.v, 0), "n": angle_std_deg(cov, p.n, 3)})


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
