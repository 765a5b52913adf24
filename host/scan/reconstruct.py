"""Reconstruction (paper §V): points X = S + d v in the stage frame, then in the object frame by
undoing the turntable rotation; contours per level; the block validation metric e = d(X_ij, E_i).

Pure functions on numpy arrays. The object frame is the turntable frame at theta = 0: origin
X_R, z along n, x = unit(y0 x n) (roughly the stage X), all in mm.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from ..calibration.solver import rodrigues


def table_frame(n: np.ndarray) -> np.ndarray:
    """Columns: the object frame's x, y, z axes in the stage frame {0} (z = n)."""
    z = np.asarray(n, float) / np.linalg.norm(n)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])


def stage_points(S: np.ndarray, d: np.ndarray, v: np.ndarray) -> np.ndarray:
    """X = S + d v (eq. 1) for sensor positions S (k, 3) and distances d (k,) in mm."""
    v = np.asarray(v, float) / np.linalg.norm(v)
    return np.asarray(S, float) + np.asarray(d, float)[:, None] * v


def object_points(X: np.ndarray, theta_deg: np.ndarray, n: np.ndarray, X_R: np.ndarray
                  ) -> np.ndarray:
    """Stage-frame points taken with the table at theta, in the object frame (mm):
    B^T R_n(-theta) (X - X_R)."""
    B = table_frame(n)
    out = np.empty_like(np.asarray(X, float))
    rel = np.asarray(X, float) - np.asarray(X_R, float)
    for th in np.unique(theta_deg):
        sel = theta_deg == th
        out[sel] = rel[sel] @ (rodrigues(np.asarray(n, float), np.radians(-th)).T @ B)
    return out


def contour_order(P: np.ndarray) -> np.ndarray:
    """Indices ordering the points of one level around their centroid (for drawing lines
    between adjacent points, as in the paper's Fig. 4)."""
    c = P[:, :2].mean(axis=0)
    return np.argsort(np.arctan2(P[:, 1] - c[1], P[:, 0] - c[0]))


def box_distance(P: np.ndarray, size_xy: tuple[float, float], pose: np.ndarray) -> np.ndarray:
    """Signed distance (mm) in the xy plane from points to the outline of a w x h rectangle
    at pose (tx, ty, yaw in rad): negative inside."""
    tx, ty, yaw = pose
    c, s = np.cos(yaw), np.sin(yaw)
    q = P[:, :2] - [tx, ty]
    q = np.column_stack([c * q[:, 0] + s * q[:, 1], -s * q[:, 0] + c * q[:, 1]])
    h = np.asarray(size_xy, float) / 2
    a = np.abs(q) - h
    outside = np.linalg.norm(np.maximum(a, 0), axis=1)
    inside = np.minimum(a.max(axis=1), 0)
    return outside + inside


@dataclass
class BoxFit:
    """A rectangle of known size fitted to a modality's points, and the error metric."""

    pose: np.ndarray         # tx, ty (mm), yaw (deg) in the object frame
    e_mm: np.ndarray         # |distance| of every point to the fitted outline
    n: int

    @property
    def mean_mm(self) -> float:
        """Mean point-to-contour error (mm)."""
        return float(self.e_mm.mean())

    @property
    def std_mm(self) -> float:
        """Standard deviation of the point-to-contour error (mm)."""
        return float(self.e_mm.std(ddof=1)) if self.n > 1 else 0.0


def fit_box(P: np.ndarray, size_xy: tuple[float, float]) -> BoxFit:
    """Fit the block's outline (known size, unknown placement and yaw on the table) to
    object-frame points, as the paper's fitted contours; raises ValueError if < 4 points."""
    P = np.asarray(P, float)
    P = P[np.all(np.isfinite(P), axis=1)]
    if len(P) < 4:
        raise ValueError(f"{len(P)} points: too few to fit the block outline (need 4)")
    c = P[:, :2].mean(axis=0)
    best = None
    for yaw0 in np.radians([0.0, 30.0, 60.0, 90.0, 120.0, 150.0]):
        r = least_squares(lambda p: box_distance(P, size_xy, p), [c[0], c[1], yaw0],
                          loss="soft_l1", f_scale=0.3, x_scale=[1.0, 1.0, 0.01])
        if best is None or r.cost < best.cost:
            best = r
    tx, ty, yaw = best.x
    yaw = (yaw + np.pi / 2) % np.pi - np.pi / 2  # a rectangle repeats every 180 deg
    e = np.abs(box_distance(P, size_xy, best.x))
    return BoxFit(np.array([tx, ty, np.degrees(yaw)]), e, len(P))


def ply_text(P: np.ndarray, modality: np.ndarray, level: np.ndarray) -> str:
    """ASCII PLY of points (mm) with per-vertex modality (0 OA, 1 US) and level index."""
    head = ["ply", "format ascii 1.0", "comment dmdsm reconstruction, object frame, mm",
            f"element vertex {len(P)}", "property float x", "property float y",
            "property float z", "property uchar modality", "property int level",
            "end_header"]
    body = [f"{p[0]:.4f} {p[1]:.4f} {p[2]:.4f} {int(m)} {int(k)}"
            for p, m, k in zip(P, modality, level)]
    return "\n".join(head + body) + "\n"
