"""A closed surface from an object's fused points, with sigma and support per vertex.

Method, and why. (1) Each point gets an oriented normal: the PCA normal of its neighbours,
signed against the beam (toward `view_dir`, the unit vector from the point toward the sensor),
which is the one thing the scan knows for sure about outside and inside. (2) A Hoppe-style
signed distance on a voxel grid: at each node the mean of (x - p_j) . n_j over its 8 nearest
points, weighted toward the nearest (beyond 2.5 voxels from any point, the nearest occupied
voxel's point's plane, by a distance transform); far from the data this extends the planes, so a
hole the scans did not see is closed by the grid (its faces lie at most a margin beyond the
points) instead of leaving the surface open. The grid's outer layer is forced outside, so
marching cubes (skimage) always yields closed surfaces; the largest component is kept. (3) The
grid only gives topology and a first position (about a voxel): each vertex is then moved along
its local normal onto a robust weighted quadratic fit of the points near it (MLS, fuse.local_fit)
- a quadratic, not a plane, so a radius of 15 mm is followed to a few um over the support;
each point weighted by the inverse of its own variance along its own normal, so a smeared or
weak point beside precise ones counts as little as it deserves - and
its sigma is that fit's height std propagated from the points' covariances (n^T Sigma n per
point, sandwich over the fit's weights), inflated by the fit's robust reduced chi-square
(from the residuals' MAD, so a face the robust fit rightly ignored at an edge does not count)
where the residuals significantly exceed the covariances (the model or the noise is worse
than stated), else scaled down by the reduced chi-square of the fits around it where the
points scatter less than stated (the ranging's floor is its calibration target's scatter,
and a waveform averaged over a moving spot averages the surface's own scatter down), plus
the common (calibration) part, which a local fit cannot average down, plus
the laser spot's footprint on a surface tilted across the travel (footprint_var: every shot
of a waveform sees the same footprint, so neither the shots nor the fit average it), plus
the travel smear once however many scans repeat it, plus a bias term where the points nearest
the vertex misfit the fit (a sharp edge it rounds). Where the points near a vertex come from
two faces (their normals spread by half of edges.MIN_ANGLE_DEG, or that misfit) and the
quadratic misfits them all (EDGE_MISFIT), two planes replace the quadratic if they fit their
points far better (EDGE_BETTER) and move the vertex less than a quarter of the radius from it:
edges.py; the block's vertical edges then stay sharp instead of rounded by 0.2-0.4 mm.
Vertices with too few points near them, with all their points on one side (a hole's rim),
or whose fitted plane does not face the beams that measured its points (a lone row: its
points lie in the plane of their beams, which PCA takes for the surface, edge-on to it, with
a sigma of um for errors of tenths) are unsupported: not moved, sigma NaN. The support
radius comes from the points' density (fuse.neighbourhood_radius), so rows of dense points
a level apart get a radius spanning levels, and the points' normals use all points within
it. Poisson reconstruction would smooth more but moves every vertex by a global solve whose
error is hard to state per vertex; the local fit's error is explicit, which is the point
here.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import trimesh
from scipy.ndimage import distance_transform_edt
from scipy.spatial import cKDTree
from skimage.measure import marching_cubes

from .edges import MIN_ANGLE_DEG, edge_fit
from .fuse import local_fit, neighbourhood_radius

_CHUNK = 20000
CURVATURE_PRIOR = 1e-3  # local_fit's prior on the quadratic terms: a vertex whose points span
# two rows (a scan's levels) in one direction gets a plane there, not a singular fit
CHI2_SIGNIFICANT = 2.0   # inflate sigma by chi^2 where it exceeds 1 by this many of its stds
LOCAL_SIGNIFICANT = 3.0  # the nearest points' misfit (an edge the fit rounds): a bias term
MAD_EFFICIENCY = 0.37    # the MAD's efficiency: its chi^2 has the std of 0.37 n points' one
MIN_FACING = 0.25        # a vertex's fitted plane must face the beams that measured it: mean
# |cos| of the angle between them at least this (75 deg); a lone row's plane is edge-on to them
EDGE_MISFIT = 3.0       # two planes are tried where the quadratic's chi^2 exceeds 1 by this many
# of its stds (it demonstrably misfits: on a noisy smooth surface a split can fit noise)...
EDGE_BETTER = 0.5       # ... and replace it where their chi^2 is below this share of its, and
# they move the vertex less than a quarter of the radius from where the quadratic put it
FOOTPRINT_K = 0.5        # the footprint's error along the normal, in spot radii x sin(tilt)
MIN_TRAVEL_MM = 0.05     # a waveform whose shots moved less than this stood still
SCATTER_VERTICES = 64    # the scatter factor's neighbourhood: this many supported vertices...
SCATTER_RADIUS = 2.0     # ... within this many support radii
WIDER = (1.0, 1.3, 1.7)  # the support radii a vertex's fit may take, in R's: the widest whose
WIDER_GAMMA = 2.0        # height stays within this many stds of every narrower one's (the
# intersection of confidence intervals): wider where the surface is smooth (less noise), not
# across an edge or a turn (more bias)


@dataclass
class SurfaceModel:
    """A closed triangle mesh in the object frame (mm) with per-vertex quality."""

    vertices_mm: np.ndarray        # (V, 3) f8
    faces: np.ndarray              # (F, 3) i4, counter-clockwise seen from outside
    normals: np.ndarray            # (V, 3) f8, unit, outward
    sigma_mm: np.ndarray           # (V,) f8, std of the vertex along its normal; NaN unsupported
    support: np.ndarray            # (V,) i4, points within the support radius
    supported: np.ndarray          # (V,) bool
    params: dict = field(default_factory=dict)


def point_normals(P_mm: np.ndarray, view_dir: np.ndarray, k: int = 16,
                  radius_mm: float = 0.0, max_k: int = 64) -> np.ndarray:
    """Unit normals (k, 3) of points (mm): the PCA normal of each point's neighbours - its k
    nearest, or with radius_mm all within it (at most max_k, at least k) - signed to point
    toward view_dir (unit vectors from each point toward the sensor). With a radius the
    points are first thinned to cells of radius / 4 (their centroids; each point takes its
    cell's normal): on turntable data many lines cross one level, so a point's nearest
    neighbours, however many, can all lie on its own row (collinear: no normal); thinned,
    those within the radius span the levels."""
    P = np.asarray(P_mm, float)
    if radius_mm > 0 and len(P):
        cell = radius_mm / 4
        _, first, inv = np.unique(np.floor(P / cell).astype(np.int64), axis=0,
                                  return_index=True, return_inverse=True)
        inv = inv.ravel()
        C = np.zeros((len(first), 3))
        np.add.at(C, inv, P)
        C /= np.bincount(inv, minlength=len(first))[:, None]
        out = _pca_normals(C, k, radius_mm, max_k)[inv]
    else:
        out = _pca_normals(P, k, 0.0, k)
    flip = np.einsum("ki,ki->k", out, np.asarray(view_dir, float)) < 0
    out[flip] *= -1
    return out


def _pca_normals(P: np.ndarray, k: int, radius_mm: float, max_k: int) -> np.ndarray:
    """Unsigned PCA normals of points: of their k nearest, or all within radius_mm (at most
    max_k, at least the k nearest)."""
    n = len(P)
    kk = min(max(k, max_k if radius_mm > 0 else k), n)
    dist, idx = cKDTree(P).query(P, k=kk, workers=-1)
    dist, idx = dist.reshape(n, kk), idx.reshape(n, kk)
    use = np.ones((n, kk), bool)
    if radius_mm > 0:
        use = dist <= radius_mm
        use[:, :min(k, n)] = True  # at least the k nearest
    out = np.empty_like(P)
    for lo in range(0, n, _CHUNK):
        w = use[lo:lo + _CHUNK].astype(float)[:, :, None]
        Q = P[idx[lo:lo + _CHUNK]]
        Q = Q - (Q * w).sum(axis=1, keepdims=True) / w.sum(axis=1, keepdims=True)
        Q = Q * w
        _, vec = np.linalg.eigh(np.matmul(Q.transpose(0, 2, 1), Q))
        out[lo:lo + _CHUNK] = vec[:, :, 0]
    return out


def footprint_var(spot_mm: np.ndarray, normals: np.ndarray, view: np.ndarray,
                  travel_cov: np.ndarray | None) -> np.ndarray:
    """(k,) mm^2 the variance along its normal that the laser spot's footprint adds to a
    point (spot radius spot_mm; unit normals and view directions (k, 3); the travel's
    covariance (k, 3, 3) mm^2 or None): on a surface tilted across the travel, where the
    shots of one fly waveform see the same footprint, (FOOTPRINT_K * spot * sin(tilt))^2,
    the same for the points of one place; a tilt along the travel is averaged over the
    shots and is the travel smear's. Measured on fly and auto scans (bench/model.py, the
    pear); a point that stood still (step and shoot, or no travel given) gets none: its
    neighbours, a step apart, see other footprints, and the fit's scatter shows them."""
    n = np.asarray(normals, float)
    b = np.asarray(view, float)
    if travel_cov is None:
        return np.zeros(len(n))
    nb = np.einsum("ki,ki->k", n, b)
    w, vec = np.linalg.eigh(np.asarray(travel_cov, float))
    t = vec[:, :, -1]                                     # the travel's direction
    moved = 12.0 * w[:, -1] > MIN_TRAVEL_MM ** 2
    c = np.cross(b, t)
    c /= np.maximum(np.linalg.norm(c, axis=1, keepdims=True), 1e-12)
    nc = np.einsum("ki,ki->k", n, c)
    across2 = np.where(moved, nc ** 2 / np.maximum(nb ** 2 + nc ** 2, 1e-12), 0.0)
    return (FOOTPRINT_K * np.asarray(spot_mm, float)) ** 2 * across2


def _facing(w0: np.ndarray, view: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """(m,) the mean |cos| between each centre's fitted plane normal (m, 3) and the beams
    (view (m, K, 3), unit, per neighbour) that measured its neighbours, weighted as the fit
    weighs them before its robust pass (w0 (m, K)). A surface the beams saw faces them
    (within the incidences the sensor ranges at); a lone row of points lies in the plane of
    its beams, so the plane fitted to it (whose tilt across the row nothing measured) has
    its normal across them: near 0."""
    c = np.abs(np.einsum("mki,mi->mk", view, normal))
    return (w0 * c).sum(axis=1) / np.maximum(w0.sum(axis=1), 1e-300)


def _scatter_factor(V: np.ndarray, supported: np.ndarray, chi2: np.ndarray, nu: np.ndarray,
                    radius_mm: float) -> np.ndarray:
    """Per vertex, how much less its points scatter about their fits than their stated
    variances say: the median over the supported vertices near it (SCATTER_VERTICES within
    radius_mm) of their fits' reduced chi-square (chi2 with nu degrees of freedom, divided by
    the chi-square's median over its mean, (1 - 2 / 9 nu)^3), at most 1 (a larger scatter is
    the per-vertex inflation's). 1 where there is no supported vertex."""
    lam = np.ones(len(V))
    idx = np.flatnonzero(supported)
    if len(idx) == 0:
        return lam
    c = chi2[idx] / (1 - 2 / (9 * nu[idx])) ** 3
    k = min(SCATTER_VERTICES, len(idx))
    dist, nb = cKDTree(V[idx]).query(V[idx], k=k, distance_upper_bound=radius_mm, workers=-1)
    near = np.where(np.isfinite(dist.reshape(len(idx), k)), c[np.minimum(
        nb.reshape(len(idx), k), len(idx) - 1)], np.nan)
    lam[idx] = np.nanmedian(near, axis=1)   # the vertex itself is always there
    return np.minimum(lam, 1.0)


def _repeated(g0: np.ndarray, valid: np.ndarray, s2: np.ndarray, group: np.ndarray
              ) -> np.ndarray:
    """(m,) mm^2 the excess variance of a fit's offset when the part s2 (m, K) of its
    neighbours' variance along the normal is the same error in every group (scan) at one
    place: (sum_g sqrt(V_g))^2 - sum_g V_g, V_g = sum over the group's neighbours of
    g0^2 s2 (g0 (m, K): the offset's derivative by each neighbour's height)."""
    part = np.where(valid, g0 ** 2 * np.maximum(s2, 0.0), 0.0)  # s2 of a rank-1 cov: >= -eps
    total, root = np.zeros(len(g0)), np.zeros(len(g0))
    for k in np.unique(group[valid]):
        vk = np.where(group == k, part, 0.0).sum(axis=1)
        total += vk
        root += np.sqrt(vk)
    return np.maximum(root ** 2 - total, 0.0)


def signed_distance(nodes: np.ndarray, tree: cKDTree, P: np.ndarray, normals: np.ndarray,
                    h_mm: float, k: int = 8) -> np.ndarray:
    """Hoppe signed distance (mm, negative inside) at nodes (m, 3): the mean of
    (x - p_j) . n_j over the k nearest oriented points, weighted exp(-(d_j^2 - d_0^2)/2h^2)."""
    k = min(k, len(P))
    out = np.empty(len(nodes))
    for lo in range(0, len(nodes), 200000):
        x = nodes[lo:lo + 200000]
        dist, idx = tree.query(x, k=k, workers=-1)
        dist, idx = dist.reshape(len(x), k), idx.reshape(len(x), k)
        w = np.exp(-(dist ** 2 - dist[:, :1] ** 2) / (2 * h_mm ** 2))
        f = np.einsum("mki,mki->mk", x[:, None, :] - P[idx], normals[idx])
        out[lo:lo + 200000] = (w * f).sum(axis=1) / w.sum(axis=1)
    return out


def _grid(P: np.ndarray, spacing: float, pad: float, max_voxels: int
          ) -> tuple[np.ndarray, tuple[int, int, int], float]:
    """Origin, shape and spacing (coarsened to stay within max_voxels) of the voxel grid."""
    lo, hi = P.min(axis=0) - pad, P.max(axis=0) + pad
    for _ in range(20):
        shape = tuple(int(np.ceil(e / spacing)) + 1 for e in hi - lo)
        if np.prod(shape, dtype=float) <= max_voxels:
            return lo, shape, spacing
        spacing *= 1.02 * (np.prod(shape, dtype=float) / max_voxels) ** (1 / 3)
    raise ValueError("the voxel grid does not fit the voxel budget")


def _hoppe_grid(P: np.ndarray, normals: np.ndarray, tree: cKDTree, origin: np.ndarray,
                shape: tuple[int, int, int], s: float, h: float) -> np.ndarray:
    """signed_distance on the grid: exact (8 nearest points) within 2.5 voxels of a point;
    farther, from the nearest occupied voxel's point (Euclidean distance transform), which is
    all the far field needs (its sign, and where a hole's closure falls)."""
    vox = np.clip(np.rint((P - origin) / s).astype(np.intp), 0, np.array(shape) - 1)
    rep = np.full(shape, -1, np.intp)
    rep[tuple(vox.T)] = np.arange(len(P))
    dist, ind = distance_transform_edt(rep < 0, return_indices=True)
    near = rep[tuple(ind)]
    axes = [origin[i] + s * np.arange(shape[i]) for i in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
    f = np.einsum("...i,...i->...", grid - P[near], normals[near])
    band = dist <= 2.5
    f[band] = signed_distance(grid[band], tree, P, normals, h)
    return f


def _mesh(f: np.ndarray, origin: np.ndarray, spacing: float) -> tuple[trimesh.Trimesh, int]:
    """The largest closed component of f's zero level, outward, and how many were dropped."""
    f[0], f[-1], f[:, 0], f[:, -1], f[:, :, 0], f[:, :, -1] = (spacing,) * 6
    verts, faces, _, _ = marching_cubes(f, 0.0, spacing=(spacing,) * 3, allow_degenerate=False)
    mesh = trimesh.Trimesh(verts + origin, faces, process=True)
    parts = mesh.split(only_watertight=False)
    if len(parts) == 0:
        raise ValueError("the points enclose no volume")
    mesh = max(parts, key=lambda m: abs(m.volume))
    if mesh.volume < 0:
        mesh.invert()
    return mesh, len(parts) - 1


_PER_POINT = {"s2": 1.0, "w": 0.0, "w0": 0.0, "r": 0.0, "g0": 0.0}  # local_fit's (m, K) parts


def _wider_radius(x: np.ndarray, Q: np.ndarray, dist: np.ndarray, cov: np.ndarray,
                  point_var: np.ndarray, ref: np.ndarray, R: float
                  ) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """Each centre's support radius (m,) mm among WIDER x R: the quadratic fitted at each
    (local_fit, weight scale half of it, neighbours Q (m, K, 3) at dist (m, K) mm, inf: none)
    gives a height along ref with a std (its points' noise propagated: a misfit widening it
    would hide the very shift the test looks for); a radius is taken while the heights'
    +-WIDER_GAMMA std intervals, its and every narrower one's, still overlap (the
    intersection of confidence intervals: the noise falls as the radius grows until the
    surface's turn shows as a shift) and its chi-square stays within EDGE_MISFIT of its stds
    of the narrowest one's (or of 1). Returns the radii, the squared shift (mm^2) of the
    taken height from the narrowest one beyond what their noise explains (the narrower's
    variance less the wider's: a bias the intervals let through, for the vertex's variance)
    and each centre's fit at its radius (local_fit's dict, per-neighbour parts over all K;
    dist is sorted along each row, as cKDTree gives it, so a radius's neighbours lead)."""
    lo, hi = np.full(len(x), -np.inf), np.full(len(x), np.inf)
    out, going = np.full(len(x), R), np.ones(len(x), bool)
    K = dist.shape[1]
    pick = np.zeros(len(x), np.int64)
    fits = []
    for j, f in enumerate(WIDER):
        valid = dist <= f * R
        k = max(int(valid.sum(axis=1).max(initial=0)), 1)  # the rows' leading neighbours
        fit = local_fit(x, Q[:, :k], valid[:, :k], cov[:, :k], f * R / 2, ref_normal=ref,
                        curvature_prior=CURVATURE_PRIOR, point_var=point_var[:, :k])
        fits.append(fit)
        z = fit["offset"] * np.einsum("mi,mi->m", fit["frame_normal"], ref)
        sd = np.sqrt(fit["var"])  # the points' noise only: a misfit is what it must show
        lo, hi = np.maximum(lo, z - WIDER_GAMMA * sd), np.minimum(hi, z + WIDER_GAMMA * sd)
        if j == 0:  # the narrowest: what the wider ones are held to
            z0, var0, z_at, var_at = z, sd ** 2, z.copy(), sd ** 2
            chi0 = np.maximum(fit["chi2"], 1.0)
        # and while the quadratic still fits its points as well as the narrowest did (two
        # faces at a corner can leave the heights alike and still not be one surface)
        alike = fit["chi2"] <= chi0 + EDGE_MISFIT * np.sqrt(2 / np.maximum(fit["n_eff"] - 6, 1))
        going &= (lo <= hi) & np.isfinite(sd) & alike
        out[going], z_at[going], var_at[going], pick[going] = f * R, z[going], sd[going] ** 2, j
    chosen = {}
    for key in fits[0]:
        parts = [ft[key] if key not in _PER_POINT else np.pad(
            ft[key], ((0, 0), (0, K - ft[key].shape[1])), constant_values=_PER_POINT[key])
            for ft in fits]
        chosen[key] = np.choose(pick.reshape((-1,) + (1,) * (parts[0].ndim - 1)), parts)
    shift2 = np.maximum((z_at - z0) ** 2 - np.maximum(var0 - var_at, 0.0), 0.0)
    return out, shift2, chosen


def _grouped_part(cov: np.ndarray | None, group: np.ndarray | None, ok: np.ndarray,
                  cov_name: str, group_name: str) -> tuple[np.ndarray | None, np.ndarray | None]:
    """A covariance part (k, 3, 3) with its group per point (k,), kept where ok; (None, None)
    unless both are given. Raises ValueError if their shapes do not match the points."""
    if cov is None or group is None:
        return None, None
    c, g = np.asarray(cov, float), np.asarray(group)
    if c.shape != (len(ok), 3, 3) or g.shape != (len(ok),):
        raise ValueError(f"{cov_name} (k, 3, 3) and {group_name} (k,) must match P")
    return c[ok], g[ok]


def build_surface(P_mm: np.ndarray, cov: np.ndarray, view_dir: np.ndarray,
                  spacing_mm: float = 1.0, support_radius_mm: float | None = None,
                  min_support: int = 10, *, cov_common: np.ndarray | None = None,
                  cov_repeat: np.ndarray | None = None, group: np.ndarray | None = None,
                  max_voxels: int = 3_000_000, max_neighbours: int = 48,
                  max_offcentre: float = 1.0, spot_mm: np.ndarray | None = None,
                  cov_offset: np.ndarray | None = None,
                  offset_group: np.ndarray | None = None) -> SurfaceModel:
    """The closed surface of points P_mm (k, 3) mm with covariances cov (k, 3, 3) mm^2 (all of
    it) and view_dir (k, 3) unit vectors toward the sensor, in the object frame.

    spacing_mm: the voxel grid's spacing (coarsened to keep within max_voxels nodes).
    support_radius_mm: the local fit's radius (Gaussian weight scale half of it); default
    fuse.neighbourhood_radius for 18 points (about 2.4 spacings on an even grid), 1.5..6 mm.
    A vertex is supported when it has >= min_support points within the radius, their weighted
    centroid lies within max_offcentre weight scales of it along the surface (not a one-sided
    rim) and the fit moves it less than half the radius; the others keep the grid's position
    and get sigma NaN.
    max_neighbours: the fit uses the nearest points within the radius, at least this many (if
    there), up to 1.2 times the median support (at most 4 times this), so dense rows do not
    crowd out the levels beside them.
    cov_common (k, 3, 3) mm^2: the part of cov shared by neighbouring points (fuse's
    covariance_parts' common part), added to sigma^2 as if fully correlated (not averaged).
    cov_repeat (k, 3, 3) mm^2 and group (k,) int: the part of cov every group (scan) repeats
    at the same place (fuse.travel_covariance: the smear set by the surface's slope along the
    travel), independent within a group but fully correlated across groups: its share of the
    fit variance, sum_g V_g, becomes (sum_g sqrt(V_g))^2, so fusing K scans of one place does
    not average it down by K.
    spot_mm (k,) mm: the laser spot's radius of each point (0 for a US point), for the
    footprint's variance (footprint_var), added like the common part.
    cov_offset (k, 3, 3) mm^2 and offset_group (k,) int: the part of cov_common that is one
    group's offset alone (a modality's ranging t0: every US distance alike, independent of
    the OA ones): fully correlated within a group, independent across groups, so the vertex
    takes (sum_g sum_{i in g} w_i s_i)^2 / (sum w)^2 of it (s_i: its std along the normal,
    w: the fit's weights), not the weighted mean of its variance (which overstated a fused
    OA + US vertex's sigma where the precise OA points carry most of the fit: the tissue
    box's RMS e/sigma 0.71).
    sigma_mm of a supported vertex: sqrt(fit variance * (robust chi2 if significant, else the
    scatter factor: _scatter_factor, <= 1) + common and footprint variance + bias^2 + the
    repeated part's excess), bias^2 = (chi2_near - 1) * s2 where the points nearest the
    vertex (weight scale h/2) misfit the fit by LOCAL_SIGNIFICANT of chi2's stds (an edge the
    quadratic rounds).
    params records the choices (spacing, radius, grid, watertight, time, edge_vertices: how
    many vertices two planes placed).
    Raises ValueError for fewer than 20 finite points or shapes that do not match."""
    t0 = time.perf_counter()
    P = np.asarray(P_mm, float)
    cov = np.asarray(cov, float)
    vd = np.asarray(view_dir, float)
    if P.ndim != 2 or P.shape[1] != 3 or cov.shape != (len(P), 3, 3) or vd.shape != P.shape:
        raise ValueError("P (k, 3), cov (k, 3, 3) and view_dir (k, 3) must match")
    ok = np.isfinite(P).all(axis=1) & np.isfinite(cov).all(axis=(1, 2)) & np.isfinite(vd).all(1)
    if ok.sum() < 20:
        raise ValueError(f"{int(ok.sum())} finite points: too few for a surface (need 20)")
    P, cov, vd = P[ok], cov[ok], vd[ok]
    common = np.zeros_like(cov) if cov_common is None else np.asarray(cov_common, float)[ok]
    repeat, grp = _grouped_part(cov_repeat, group, ok, "cov_repeat", "group")
    spot = np.zeros(len(ok)) if spot_mm is None else np.asarray(spot_mm, float)
    if spot.shape != (len(ok),):
        raise ValueError("spot_mm (k,) must match P")
    spot = spot[ok]
    repeat_all = None if cov_repeat is None else np.asarray(cov_repeat, float)[ok]
    own = cov - common
    off_cov, ogrp = _grouped_part(cov_offset, offset_group, ok, "cov_offset", "offset_group")
    if off_cov is not None:
        common = common - off_cov  # counted apart below
        offset_ids = np.unique(ogrp)
    tree = cKDTree(P)
    gap = float(np.median(tree.query(P, k=2, workers=-1)[0][:, 1]))
    R = (neighbourhood_radius(P, target=18, min_mm=1.5, max_mm=6.0)
         if support_radius_mm is None else support_radius_mm)
    h = R / 2
    normals_p = point_normals(P, vd, radius_mm=R)
    pvar = np.einsum("ki,kij,kj->k", normals_p, own, normals_p)
    fp_var = footprint_var(spot, normals_p, vd, repeat_all)
    origin, shape, s = _grid(P, spacing_mm, R + 2 * spacing_mm, max_voxels)
    f = _hoppe_grid(P, normals_p, tree, origin, shape, s, h)
    mesh, dropped = _mesh(f, origin, s)
    V = np.array(mesh.vertices, float)
    ref = np.array(mesh.vertex_normals, float)
    support = np.asarray(tree.query_ball_point(V, R, return_length=True, workers=-1), np.int32)
    Kq = int(min(max(max_neighbours, 1.2 * np.median(support)), 4 * max_neighbours, len(P)))
    Kq = int(min(np.ceil(Kq * WIDER[-1] ** 2), len(P)))  # as many more for the widest radius
    chunk = max(1000, 1_000_000 // Kq)
    radius = np.full(len(V), R)
    sigma = np.full(len(V), np.nan)
    normals = ref.copy()
    supported = np.zeros(len(V), bool)
    offset = np.zeros(len(V))
    var_fit, infl, chi2_w, nu, var_rest = (np.full(len(V), np.nan) for _ in range(5))
    n_edges = 0
    for lo in range(0, len(V), chunk):
        sl = slice(lo, lo + chunk)
        dist, idx = tree.query(V[sl], k=Kq, distance_upper_bound=R * WIDER[-1], workers=-1)
        dist, idx = dist.reshape(-1, Kq), idx.reshape(-1, Kq)
        fit_ok = (dist <= R).sum(axis=1) >= max(min_support, 6)
        sel = np.flatnonzero(fit_ok)
        if len(sel) == 0:
            continue
        ds, Vs = dist[sel], V[sl][sel]
        ii = np.where(np.isfinite(ds), idx[sel], 0)
        Rv, shift2, r = _wider_radius(Vs, P[ii], ds, own[ii], pvar[ii], ref[sl][sel], R)
        radius[sl][sel] = Rv
        hv = Rv / 2
        vs = ds <= Rv[:, None]  # each vertex's neighbours within its own radius
        w = r["w"]
        nn = r["frame_normal"]
        sc = np.einsum("mi,mkij,mj->mk", nn, common[ii], nn)
        var_c = (w * (sc + fp_var[ii])).sum(axis=1) / np.maximum(w.sum(axis=1), 1e-300)
        if off_cov is not None:
            so = np.sqrt(np.maximum(np.einsum("mi,mkij,mj->mk", nn, off_cov[ii], nn), 0.0))
            for gid in offset_ids:
                var_c += ((w * so * (ogrp[ii] == gid)).sum(axis=1)
                          / np.maximum(w.sum(axis=1), 1e-300)) ** 2
        good = ((r["centred"] <= max_offcentre) & (np.abs(r["offset"]) < Rv / 2)
                & np.isfinite(r["var"]) & (support[sl][sel] >= min_support)
                & (_facing(r["w0"], vd[ii], r["frame_normal"]) >= MIN_FACING))
        wl = vs * np.exp(-0.5 * (np.where(vs, ds, 0) / (hv[:, None] / 2)) ** 2)
        swl = wl.sum(axis=1)
        chi2_l = (wl * r["r"] ** 2 / r["s2"]).sum(axis=1) / swl
        ne_l = swl ** 2 / (wl * wl).sum(axis=1)
        ms2_l = (wl * r["s2"]).sum(axis=1) / swl
        bias2 = np.where(chi2_l > 1 + LOCAL_SIGNIFICANT * np.sqrt(2 / ne_l),
                         (chi2_l - 1) * ms2_l, 0.0)
        move, fit_var, n_eff = r["offset"].copy(), r["var"].copy(), r["n_eff"].copy()
        nrm_v, chi2, chi2_fit = r["normal"].copy(), r["chi2_robust"].copy(), r["chi2"].copy()
        spread = np.where(vs, np.einsum("mki,mi->mk", normals_p[ii], nn), 1.0).min(1)
        rounded = r["chi2"] > 1 + EDGE_MISFIT * np.sqrt(2 / np.maximum(r["n_eff"] - 6, 1))
        two_faces = (bias2 > 0) | (spread < np.cos(np.radians(MIN_ANGLE_DEG / 2)))
        e = np.flatnonzero(good & rounded & two_faces)  # only these get the two-plane fits
        if len(e):
            k = edge_fit(Vs[e], P[ii[e]], vs[e], own[ii[e]], normals_p[ii[e]],
                         pvar[ii[e]], hv[e], nn[e])
            take = (k["ok"] & (k["chi2"] < EDGE_BETTER * r["chi2"][e])
                    & (np.abs(k["t"]) < Rv[e] / 2) & (np.abs(k["t"] - r["offset"][e]) < Rv[e] / 4))
            e, n_edges = e[take], n_edges + int(take.sum())
            move[e], fit_var[e], nrm_v[e] = k["t"][take], k["var"][take], k["normal"][take]
            chi2[e], n_eff[e], bias2[e] = k["chi2"][take], k["n_eff"][take], 0.0
            shift2[e] = 0.0
            chi2_fit[e] = k["chi2"][take]
        g = sel[good] + lo
        offset[g] = move[good]
        V[g] += move[good, None] * nn[good]
        normals[g] = nrm_v[good]
        chi2, bias2 = chi2[good], bias2[good]
        misfit = chi2 > 1 + CHI2_SIGNIFICANT * np.sqrt(
            2 / (MAD_EFFICIENCY * np.maximum(n_eff[good] - 6, 1)))
        var_r = 0.0 if repeat is None else _repeated(
            r["g0"], vs, np.einsum("mi,mkij,mj->mk", nn, repeat[ii], nn), grp[ii])[good]
        var_fit[g] = fit_var[good]
        infl[g] = np.where(misfit, chi2, np.nan)
        chi2_w[g] = chi2_fit[good]
        nu[g] = np.maximum(n_eff[good] - 6, 1.0)
        var_rest[g] = var_c[good] + bias2 + shift2[good] + var_r
        supported[g] = True
    lam = _scatter_factor(V, supported, chi2_w, nu, SCATTER_RADIUS * R)
    sigma[supported] = np.sqrt(var_fit[supported] * np.where(
        np.isfinite(infl[supported]), infl[supported], lam[supported]) + var_rest[supported])
    mesh = trimesh.Trimesh(V, mesh.faces, process=False)
    normals[~supported] = np.array(mesh.vertex_normals, float)[~supported]
    params = {"spacing_mm": s, "support_radius_mm": R, "weight_scale_mm": h,
              "wider_radius_share": {f"{f:g}": float(np.mean(np.isclose(
                  radius[supported], f * R))) if supported.any() else 0.0 for f in WIDER},
              "min_support": min_support, "max_offcentre": max_offcentre,
              "point_spacing_mm": gap, "n_points": int(len(P)),
              "n_dropped_nonfinite": int((~ok).sum()), "grid_shape": list(shape),
              "components_dropped": dropped, "watertight": bool(mesh.is_watertight),
              "max_move_mm": float(np.abs(offset).max(initial=0.0)), "edge_vertices": n_edges,
              "build_s": time.perf_counter() - t0}
    return SurfaceModel(V, np.asarray(mesh.faces, np.int32), normals, sigma, support,
                        supported, params)
