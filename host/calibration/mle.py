"""The calibration's joint maximum-likelihood refinement (eq. 8) and the covariance of its result.

Plain functions on numpy arrays (`solver.solve` strings them together). The parameter vector p
is, in order: v and n as tangent steps from their SVD estimates (2 + 2), X_R's x and y (z = 0:
the gauge of Table I), the filament line at theta = 0 (a tangent step of its direction and a
step of its point across it, 2 + 2), the tip point (3) and the table angle of each edge frame.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import NamedTuple

import numpy as np
from scipy.optimize import least_squares

from .geometry import retract, rodrigues, tangent_basis, unit

SCALE_PRIOR_DOF = 4.0  # the declared lateral covariances (scale 1) count as this many
# residuals (a conjugate inverse-gamma prior), so a scale from the tips' 4 residual degrees
# of freedom cannot collapse, and the reported stds with it
MAX_FITS = 8  # fits repeated with the depth scatters and lateral scales of the one before


class Problem(NamedTuple):
    """The center points as the MLE sees them (mm, deg) with their covariances (§IV-C)."""

    tip_S: np.ndarray       # (k, 3)
    tip_d: np.ndarray       # (k,)
    tip_cov_S: np.ndarray   # (k, 3, 3)
    tip_var_d: np.ndarray   # (k,)
    edge_S: np.ndarray      # (m, 3)
    edge_d: np.ndarray      # (m,)
    edge_cov_S: np.ndarray  # (m, 3, 3)
    edge_var_d: np.ndarray  # (m,)
    edge_frame: np.ndarray  # (m,) frame index of each edge center point
    frames: np.ndarray      # (F,) the edge frames, sorted
    thetas: list[float]     # (F,) table angle read per edge frame (deg)
    radius_mm: float        # filament radius: edge depths moved onto its axis
    sigma_theta_deg: float  # table angle reading noise
    edge_front: np.ndarray  # (m,) the front depth in edge_d for a square beam (mm)
    tip_grad: np.ndarray    # (k, 3) a tip depth's change per mm of its stage reading's error


class Params(NamedTuple):
    """The parameters p stands for."""

    v: np.ndarray
    n: np.ndarray
    X_R: np.ndarray
    q: np.ndarray          # filament direction at theta = 0
    point: np.ndarray      # a point of the filament at theta = 0
    tip: np.ndarray
    theta_deg: np.ndarray  # fitted table angle per edge frame


class Gauge(NamedTuple):
    """Where p = 0 is (the SVD estimates) and the tangent bases its steps are taken in."""

    v0: np.ndarray
    n0: np.ndarray
    l0: np.ndarray  # unit filament direction at theta = 0
    p0: np.ndarray  # filament point at theta = 0
    Bv: np.ndarray
    Bn: np.ndarray
    Bl: np.ndarray

    def unpack(self, p: np.ndarray, n_frames: int) -> Params:
        """The parameters of the vector p."""
        return Params(retract(self.v0, self.Bv, p[0:2]), retract(self.n0, self.Bn, p[2:4]),
                      np.array([p[4], p[5], 0.0]), retract(self.l0, self.Bl, p[6:8]),
                      self.p0 + self.Bl @ p[8:10],  # the line's point moves across it only
                      p[10:13], p[13:13 + n_frames])


class DepthResiduals(NamedTuple):
    """Residuals along the beam (mm, unwhitened) with the variances their covariances give
    them (without the extra depth variance), and the lateral chi-squares (scale included)."""

    tip: np.ndarray
    tip_var: np.ndarray
    edge: np.ndarray
    edge_var: np.ndarray
    tip_lateral_chi2: float   # across the beam: the raster's plane
    edge_lateral_chi2: float  # across the line and the beam, over all edge frames


class Fit(NamedTuple):
    """The MLE's solution with the depth scatters and lateral scales from its residuals
    (those it was whitened with, once they settled)."""

    x: np.ndarray
    jac: np.ndarray
    fun: np.ndarray
    depth_var: tuple[float, float]      # extra variance (mm^2) of each tip and edge depth
    lateral_scale: tuple[float, float]  # factor on the tips' and the edges' lateral covs


def gauge_fix(v0: np.ndarray, n0: np.ndarray, xr0: np.ndarray, tip0: np.ndarray,
              lines: list[tuple[np.ndarray, np.ndarray]], thetas: list[float]
              ) -> tuple[Gauge, np.ndarray]:
    """The MLE's gauge (X_R on z = 0, Table I; the filament line carried back to theta = 0
    about n) and its starting vector p from the SVD estimates (eqs. 2-7)."""
    R0 = rodrigues(n0, -np.radians(thetas[0]))
    l0 = unit(R0 @ lines[0][0])
    p0 = xr0 + R0 @ (lines[0][1] - xr0)
    gauge = Gauge(v0, n0, l0, p0, tangent_basis(v0), tangent_basis(n0), tangent_basis(l0))
    return gauge, np.concatenate([np.zeros(4), xr0[:2], np.zeros(4), tip0, thetas])


def _tip(pb: Problem, P: Params, scale: float, extra: float = 0.0
         ) -> tuple[np.ndarray, np.ndarray]:
    """Each tip center point's offset from the tip (k, 3) and its covariance: the stage
    reading's (scaled), carried with the depth error it brings (g . dS along v: the
    point stays on the tip's face), plus its depth variance (with the extra) along v."""
    X = pb.tip_S + pb.tip_d[:, None] * P.v - P.tip
    vd = pb.tip_var_d + extra
    M = np.eye(3)[None] + P.v[None, :, None] * pb.tip_grad[:, None, :]  # dX = M dS
    cov_S = np.einsum("kij,kjl,kml->kim", M, pb.tip_cov_S, M)
    return X, scale * cov_S + vd[:, None, None] * np.outer(P.v, P.v)


def _edges(pb: Problem, P: Params, scale: float, extra: float = 0.0
           ) -> Iterator[tuple[np.ndarray, ...]]:
    """Per edge frame: the center points' offsets across the turned filament line (2-D, in
    the basis B of the plane across it), B, their stage covariances there and their full
    covariances (stage scaled plus depth)."""
    for i, f in enumerate(pb.frames):
        sel = pb.edge_frame == f
        R = rodrigues(P.n, np.radians(P.theta_deg[i]))
        li = R @ P.q
        # a beam at angle beta to the filament meets its front 1 / sin(beta) times as far
        # before the axis as a square one (the radius, and center_points' front depths)
        k = 1.0 / max(float(np.linalg.norm(np.cross(li, P.v))), 1e-3)
        d = pb.edge_d[sel] + k * pb.radius_mm + (k - 1.0) * pb.edge_front[sel]
        X = pb.edge_S[sel] + d[:, None] * P.v
        rel = X - (P.X_R + R @ (P.point - P.X_R))
        B = tangent_basis(li)
        perp = (rel - np.outer(rel @ li, li)) @ B
        cS = np.einsum("ai,kab,bj->kij", B, pb.edge_cov_S[sel], B)
        vd = pb.edge_var_d[sel] + extra
        yield perp, B, cS, scale * cS + vd[:, None, None] * np.outer(B.T @ P.v, B.T @ P.v)


def whitened_residuals(p: np.ndarray, pb: Problem, gauge: Gauge, depth_var: tuple,
                       lateral_scale: tuple) -> np.ndarray:
    """The residuals eq. 8 sums the squares of: each center point's, whitened by its
    covariance (with the extra depth variances), then the table angles' against their
    readings."""
    P = gauge.unpack(p, len(pb.frames))
    X, cov = _tip(pb, P, lateral_scale[0], depth_var[0])
    W = np.linalg.cholesky(np.linalg.inv(cov))
    r = [np.einsum("ki,kij->kj", X, W).ravel()]
    for perp, _, _, cov in _edges(pb, P, lateral_scale[1], depth_var[1]):
        W = np.linalg.cholesky(np.linalg.inv(cov))
        r.append(np.einsum("ki,kij->kj", perp, W).ravel())
    r.append((P.theta_deg - np.asarray(pb.thetas)) / pb.sigma_theta_deg)
    return np.concatenate(r)


def depth_residuals(p: np.ndarray, pb: Problem, gauge: Gauge, lateral_scale: tuple
                    ) -> DepthResiduals:
    """The residuals along the beam and the lateral chi-squares at p."""
    P = gauge.unpack(p, len(pb.frames))
    X, cov = _tip(pb, P, lateral_scale[0])
    Bt = tangent_basis(P.v)  # across the beam: the raster's lateral plane
    lat = X @ Bt
    cl = np.einsum("ai,kab,bj->kij", Bt, pb.tip_cov_S, Bt)
    tip_chi2 = float(np.einsum("ki,kij,kj->", lat, np.linalg.inv(cl), lat))
    r, var, chi2 = [], [], []
    for perp, B, cS, cov_e in _edges(pb, P, lateral_scale[1]):
        e = unit(B.T @ P.v)
        r.append(perp @ e)
        var.append(np.einsum("i,kij,j->k", e, cov_e, e))
        w = np.array([-e[1], e[0]])  # across the line, across the beam
        chi2.append(float(np.sum((perp @ w) ** 2 / np.einsum("i,kij,j->k", w, cS, w))))
    return DepthResiduals(X @ P.v, np.einsum("i,kij,j->k", P.v, cov, P.v), np.concatenate(r),
                          np.concatenate(var), tip_chi2, sum(chi2))


def raw_residuals(p: np.ndarray, pb: Problem, gauge: Gauge) -> np.ndarray:
    """Unwhitened residuals (mm): tip (k, 3) flattened, then 2 across the line per edge
    point, frame by frame."""
    P = gauge.unpack(p, len(pb.frames))
    X, _ = _tip(pb, P, 1.0)
    return np.concatenate([X.ravel()] + [perp.ravel() for perp, *_ in _edges(pb, P, 1.0)])


def depth_scatters(dr: DepthResiduals) -> tuple[float, float]:
    """The extra variance (mm^2) of a tip and of an edge depth that makes the residuals along
    the beam as large as their covariances say, less the parameters acting there (the tip
    point's depth; the edge line's offset and tilt, n, X_R)."""
    return tuple(max(0.0, float(np.sum(r ** 2) / (len(r) - k) - np.mean(var)))
                 if len(r) > k else 0.0
                 for r, var, k in ((dr.tip, dr.tip_var, 1), (dr.edge, dr.edge_var, 4)))


def lateral_scales(dr: DepthResiduals, n_tip: int, n_edge: int, n_frames: int
                   ) -> tuple[float, float]:
    """Factors on the tips' and the edges' lateral covariances from their chi-squares, over
    their degrees of freedom (2 per tip less v and the tip across the beam; 1 per edge point
    less 2 per frame), each with SCALE_PRIOR_DOF prior residuals at scale 1."""
    return tuple(min(max((chi + SCALE_PRIOR_DOF) / (max(dof, 0) + SCALE_PRIOR_DOF), 0.01),
                     100.0)
                 for chi, dof in ((dr.tip_lateral_chi2, 2 * n_tip - 4),
                                  (dr.edge_lateral_chi2, n_edge - 2 * n_frames)))


def fit(pb: Problem, gauge: Gauge, p_init: np.ndarray, scatter_from_residuals: bool = True
        ) -> Fit:
    """Eq. 8 by Levenberg-Marquardt, repeated (at most MAX_FITS times) with the depth scatters
    and lateral scales of the previous fit's residuals until they settle (within 2 %);
    scatter_from_residuals False: one fit with the covariances as given."""
    depth_var, scale = (0.0, 0.0), (1.0, 1.0)
    n_tip, n_edge, n_frames = len(pb.tip_d), len(pb.edge_d), len(pb.frames)
    for _ in range(MAX_FITS):
        sol = least_squares(whitened_residuals, p_init, method="lm", x_scale="jac",
                            args=(pb, gauge, depth_var, scale))
        p_init = sol.x
        if not scatter_from_residuals:
            break
        dr = depth_residuals(sol.x, pb, gauge, scale)
        new, new_scale = depth_scatters(dr), lateral_scales(dr, n_tip, n_edge, n_frames)
        if all(abs(a - b) <= 0.02 * max(a, b) + 1e-14 for a, b in zip(new, depth_var)) and \
                all(abs(a - b) <= 0.02 * max(a, b) for a, b in zip(new_scale, scale)):
            break
        depth_var, scale = new, new_scale
    return Fit(sol.x, sol.jac, sol.fun, depth_var, scale)


def covariance(f: Fit, gauge: Gauge) -> np.ndarray:
    """9x9 covariance of v, n (unit-vector components) and X_R (mm) at the solution: (J^T J)^-1
    of the whitened residuals, each parameter's std widened where the leverage-corrected
    residuals (the HC2 sandwich, r^2 / (1 - h): unbiased when the model holds) show more
    scatter than the model's covariance (heavy-tailed surface scatter on a few
    high-leverage points hides in the fit), then mapped to Cartesian through the tangent
    bases. HC3's r^2 / (1 - h)^2 is a jackknife's bound, biased wide: with 4 tip frames
    against 5 parameters of v and the tip its leverages are high and it widened v's std
    1.3x on data where the model held (docs/calibration.md)."""
    J = f.jac
    cov_p = np.linalg.pinv(J.T @ J)  # residuals are whitened: no rescaling by s^2
    h = np.einsum("ij,jk,ik->i", J, cov_p, J)
    meat = (J * (f.fun ** 2 / np.maximum(1 - h, 1e-3))[:, None]).T @ J
    widen = np.sqrt(np.maximum(np.diag(cov_p @ meat @ cov_p) /
                               np.maximum(np.diag(cov_p), 1e-300), 1.0))
    cov_p = cov_p * np.outer(widen, widen)
    Jv = np.zeros((9, len(f.x)))
    Jv[0:3, 0:2] = gauge.Bv
    Jv[3:6, 2:4] = gauge.Bn
    Jv[6, 4] = Jv[7, 5] = 1.0
    return Jv @ cov_p @ Jv.T


def point_residuals(raw: np.ndarray, pb: Problem, theta_deg: np.ndarray
                    ) -> dict[str, np.ndarray]:
    """Per center point at the solution: tip (k, 3) mm from the fitted tip; edge (m,) mm
    from the fitted filament line, in the data's order; theta_deg (F,) fitted minus read."""
    k = len(pb.tip_d)
    edge = np.empty(len(pb.edge_d))
    order = np.concatenate([np.flatnonzero(pb.edge_frame == f) for f in pb.frames])
    edge[order] = np.linalg.norm(raw[3 * k:].reshape(-1, 2), axis=1)
    return {"tip": raw[:3 * k].reshape(k, 3), "edge": edge,
            "theta_deg": theta_deg - np.asarray(pb.thetas)}
