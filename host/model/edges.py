"""Sharp edges: a vertex whose points come from two faces, fitted as two planes, not rounded.

A local quadratic (fuse.local_fit) cannot follow a crease: where a vertex's neighbours lie on
two faces meeting at an angle, the fit rounds the edge off by a few tenths of a mm (the block's
vertical edges: 0.35 mm inside within 1 mm of them). There, and only where the quadratic
demonstrably misfits the points nearest the vertex, the neighbours are split in two by their
own normals (two-means on the unit sphere), each group is fitted as a plane (the same robust
weighted fit, curvature held at zero), and the vertex is moved along its direction onto the
pair: onto the nearer plane's crossing for a convex edge (the object is inside both planes),
the farther for a concave one (inside either). The split is kept only if both faces have
enough points, meet at least MIN_ANGLE_DEG, the move direction crosses both, and the planes
fit their own points where the one quadratic did not; otherwise the vertex keeps the quadratic.
"""

from __future__ import annotations

import numpy as np

from .fuse import local_fit

MIN_ANGLE_DEG = 25.0   # two faces closer than this are one smooth surface to the fit
MIN_FACE_POINTS = 4  # effective points each face needs (the plane's 3 parameters and a margin)
MIN_CROSSING = 0.3     # the move direction's cosine with each face's normal (edge-on: skip)
PLANE_PRIOR = 1e6      # local_fit's curvature prior that makes its quadratic a plane


def split_by_normal(normals: np.ndarray, w: np.ndarray, iters: int = 4) -> np.ndarray:
    """Two-means of unit normals (m, K, 3) with weights w (m, K) (0: not a point): a (m, K)
    bool, True for the second group. Seeded by the normal farthest from the weighted mean and
    the one farthest from that."""
    mean = np.einsum("mk,mki->mi", w, normals)
    rows = np.arange(len(w))
    far = np.where(w > 0, np.einsum("mki,mi->mk", normals, mean), np.inf).argmin(axis=1)
    a = normals[rows, far]
    b = normals[rows, np.where(w > 0, np.einsum("mki,mi->mk", normals, a), np.inf).argmin(1)]
    second = np.zeros(w.shape, bool)
    for _ in range(iters):
        second = np.einsum("mki,mi->mk", normals, b) > np.einsum("mki,mi->mk", normals, a)
        a = np.einsum("mk,mki->mi", w * ~second, normals)
        b = np.einsum("mk,mki->mi", w * second, normals)
        a /= np.maximum(np.linalg.norm(a, axis=1), 1e-12)[:, None]
        b /= np.maximum(np.linalg.norm(b, axis=1), 1e-12)[:, None]
    return second


def edge_fit(x: np.ndarray, Q: np.ndarray, valid: np.ndarray, cov: np.ndarray,
             normals: np.ndarray, point_var: np.ndarray, h_mm: float | np.ndarray,
             move: np.ndarray
             ) -> dict[str, np.ndarray]:
    """Two-plane fits of centres x (m, 3) mm whose neighbours Q (m, K, 3) (valid (m, K), cov
    (m, K, 3, 3) mm^2, own normals (m, K, 3), point_var (m, K) mm^2 along them) lie on two
    faces; move (m, 3) the unit direction the centre may move along (outward).
    Returns ok (m,) where the split holds; t (m,) mm, the move onto the edge's surface; normal
    (m, 3), the face it lands on; var (m,) mm^2, t's variance from that face's fit; chi2 (m,)
    the two fits' weighted reduced chi-square over their own points; n_eff (m,)."""
    h2 = np.broadcast_to(np.asarray(h_mm, float), (len(x),))[:, None] ** 2  # one or (m,)
    w0 = valid * np.exp(-0.5 * ((Q - x[:, None, :]) ** 2).sum(axis=2) / h2)
    second = split_by_normal(normals, w0)
    fits = []
    for grp in (~second & valid, second & valid):
        n_pts = grp.sum(axis=1)
        enough = n_pts >= 3
        r = local_fit(x, Q, grp | ~enough[:, None] & valid, cov, h_mm, ref_normal=move,
                      curvature_prior=PLANE_PRIOR, point_var=point_var)
        fits.append((r, grp, enough))
    (ra, ga, ea), (rb, gb, eb) = fits
    na, nb = ra["frame_normal"], rb["frame_normal"]
    ca, cb = np.einsum("mi,mi->m", move, na), np.einsum("mi,mi->m", move, nb)
    ok = (ea & eb & (ra["n_eff"] >= MIN_FACE_POINTS) & (rb["n_eff"] >= MIN_FACE_POINTS)
          & (np.einsum("mi,mi->m", na, nb) < np.cos(np.radians(MIN_ANGLE_DEG)))
          & (ca > MIN_CROSSING) & (cb > MIN_CROSSING) & np.isfinite(ra["var"] + rb["var"]))
    # heights of each face's points above the other face's plane: below it = a convex edge
    d = Q - x[:, None, :]
    hb = np.einsum("mki,mi->mk", d, na) - ra["offset"][:, None]
    ha = np.einsum("mki,mi->mk", d, nb) - rb["offset"][:, None]
    wb, wa = w0 * gb, w0 * ga
    below = ((wb * hb).sum(1) / np.maximum(wb.sum(1), 1e-300)
             + (wa * ha).sum(1) / np.maximum(wa.sum(1), 1e-300))
    convex = below < 0
    # signed distance outside of x to each plane is -offset; along move it grows by c per mm
    ca, cb = np.maximum(ca, MIN_CROSSING), np.maximum(cb, MIN_CROSSING)  # else not ok
    ta, tb = ra["offset"] / ca, rb["offset"] / cb
    pick_a = np.where(convex, ta <= tb, ta >= tb)
    t = np.where(pick_a, ta, tb)
    var = np.where(pick_a, ra["var"] / ca ** 2, rb["var"] / cb ** 2)
    normal = np.where(pick_a[:, None], ra["normal"], rb["normal"])
    sw = (ra["w"].sum(1) + rb["w"].sum(1))
    chi2 = ((ra["w"] * ra["r"] ** 2 / ra["s2"]).sum(1) + (rb["w"] * rb["r"] ** 2 / rb["s2"]).sum(1)
            ) / np.maximum(sw, 1e-300)
    n_eff = np.where(pick_a, ra["n_eff"], rb["n_eff"])
    return {"ok": ok & np.isfinite(t), "t": np.where(np.isfinite(t), t, 0.0), "normal": normal,
            "var": var, "chi2": chi2, "n_eff": n_eff}
