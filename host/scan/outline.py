"""The outline a first look measured, and its keep-out checked on moves of X, Y, Z and A."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dmdsm.marlin_patch import MachineLimits

from ..links.safety import KeepOut, UnsafeMove, check_target
from .reconstruct import table_frame

OUTLIER_MM = 1.0       # a cell's point with no other within this radial distance is isolated
STEP_MM = 0.25         # samples of a move: at most this much stage travel apart, at most
STEP_DEG = 0.5         # this much table turn, and at most STEP_MM of an outline's rim turned
CHUNK = 65_536         # samples checked at once (bounds the memory of a long path)
MAX_SAMPLES = 10_000_000  # a move needing more samples than this is refused, not checked


@dataclass(eq=False)
class Outline:
    """The object's outline measured by a first look: per azimuth bin (object frame) and height
    bin, the radius (mm) of the outermost surface seen."""

    phi_step_deg: float          # azimuth bin width; bins start at 0 deg
    z_edges_mm: np.ndarray       # (nz+1,) height bin edges (object frame, 0 = table)
    r_mm: np.ndarray             # (nphi, nz) outermost measured radius, NaN where none seen
    radius_mm: float             # the bounding cylinder's radius: the keep-out where not closed
    height_mm: float             # the bounding cylinder's height
    max_gap: int = 2             # azimuth bins a row may miss between measured cells

    def _filled(self) -> np.ndarray:
        """(nphi, nz) radius (mm) of the closed cells, NaN elsewhere: measured cells, and runs
        of at most max_gap unmeasured cells along phi between two measured cells of the same
        row, which take the larger radius of those two."""
        r = np.asarray(self.r_mm, float)
        meas = np.isfinite(r)
        out = r.copy()
        g = max(int(self.max_gap), 0)
        back = np.full(r.shape, g + 1)   # bins back to the nearest measured cell (>g: none)
        fwd = np.full(r.shape, g + 1)
        r_back = np.full(r.shape, np.nan)
        r_fwd = np.full(r.shape, np.nan)
        for k in range(g, 0, -1):       # nearest last, so it wins
            mb, mf = np.roll(meas, k, axis=0), np.roll(meas, -k, axis=0)
            back = np.where(mb, k, back)
            r_back = np.where(mb, np.roll(r, k, axis=0), r_back)
            fwd = np.where(mf, k, fwd)
            r_fwd = np.where(mf, np.roll(r, -k, axis=0), r_fwd)
        fill = ~meas & (back <= g) & (fwd <= g) & (back + fwd - 1 <= g)
        out[fill] = np.fmax(r_back, r_fwd)[fill]
        return out

    def filled_r_mm(self) -> np.ndarray:
        """(nphi, nz) radius (mm) of every closed cell (measured or filled), NaN elsewhere."""
        return self._filled()

    def closed(self) -> np.ndarray:
        """(nphi, nz) bool: cells whose radius is known (measured, or filled between measured
        neighbours at most max_gap bins apart along phi in the same z row)."""
        return np.isfinite(self._filled())

    def _keep_grid(self) -> np.ndarray:
        """(nphi, nz) keep-out radius (mm): in closed cells the max over the cell and its 8
        neighbours (phi wraps round, z does not), at most radius_mm; radius_mm elsewhere."""
        f = self._filled()
        m = f.copy()
        padded = np.pad(f, ((0, 0), (1, 1)), constant_values=np.nan)
        for dz in (0, 1, 2):
            row = padded[:, dz:dz + f.shape[1]]
            for dphi in (-1, 0, 1):
                m = np.fmax(m, np.roll(row, dphi, axis=0))
        return np.where(np.isfinite(f), np.minimum(m, self.radius_mm), self.radius_mm)

    def _cells(self, phi_deg: np.ndarray, z_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Grid indices (i along phi, j along z, clipped into the grid) of object-frame
        azimuths (deg) and heights (mm)."""
        nphi, nz = np.shape(self.r_mm)
        i = np.floor(np.mod(phi_deg, 360.0) / self.phi_step_deg).astype(np.int64) % nphi
        j = np.clip(np.searchsorted(self.z_edges_mm, z_mm, side="right") - 1, 0, nz - 1)
        return i, j

    def rows_at(self, z_mm: np.ndarray) -> np.ndarray:
        """The outline's row index of each object-frame height (mm), clipped to its rows."""
        return self._cells(np.zeros_like(np.asarray(z_mm, float)), z_mm)[1]

    def keep_radius_mm(self, phi_deg: np.ndarray, z_mm: np.ndarray) -> np.ndarray:
        """The keep-out radius (mm) at object-frame azimuths (deg) and heights (mm): in closed
        cells the max of r over the cell and its 8 neighbours (so a surface between samples is
        not cut), never more than radius_mm; radius_mm in open cells; 0 above height_mm."""
        phi, z = np.broadcast_arrays(np.asarray(phi_deg, float), np.asarray(z_mm, float))
        i, j = self._cells(phi, z)
        return np.where(z > self.height_mm, 0.0, self._keep_grid()[i, j])

    def surface_points(self) -> np.ndarray:
        """(m, 3) object-frame points (mm) on the closed outline, one per closed cell at the
        cell centre's phi and z and the cell's radius: what coverage is measured against when
        no truth is known."""
        f = self._filled()
        i, j = np.nonzero(np.isfinite(f))
        phi = np.radians((i + 0.5) * self.phi_step_deg)
        z = 0.5 * (self.z_edges_mm[j] + self.z_edges_mm[j + 1])
        r = f[i, j]
        return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def outline_from_points(P: np.ndarray, radius_mm: float, height_mm: float,
                        phi_step_deg: float = 5.0, z_step_mm: float = 2.0,
                        max_gap: int = 2) -> Outline:
    """The outline of a first look's object-frame points P (k, 3) in mm, in cells of
    phi_step_deg (which must divide 360) by z_step_mm from z = 0 up to height_mm.

    Rule: a cell's radius is the largest radial distance sqrt(x^2 + y^2) of its points that has
    another point of the cell within OUTLIER_MM (1 mm) of it; a point with none is an isolated
    outlier and is dropped, unless every point of the cell is isolated (then the largest
    counts). Points that are not finite or lie outside the bounding cylinder (r > radius_mm + 1
    or z outside -1 .. height_mm + 1) are ignored (not the object); those within 1 mm below 0 or
    above the top edge count in the nearest row."""
    if not (radius_mm > 0 and height_mm > 0 and phi_step_deg > 0 and z_step_mm > 0):
        raise ValueError("radius_mm, height_mm, phi_step_deg and z_step_mm must be positive")
    nphi = round(360.0 / phi_step_deg)
    if nphi < 1 or abs(nphi * phi_step_deg - 360.0) > 1e-6:
        raise ValueError(f"phi_step_deg = {phi_step_deg:g} does not divide 360")
    nz = max(1, math.ceil(height_mm / z_step_mm - 1e-9))
    edges = np.arange(nz + 1) * float(z_step_mm)
    out = Outline(float(phi_step_deg), edges, np.full((nphi, nz), np.nan), float(radius_mm),
                  float(height_mm), int(max_gap))
    P = np.asarray(P, float).reshape(-1, 3)
    P = P[np.all(np.isfinite(P), axis=1)]
    r = np.hypot(P[:, 0], P[:, 1])
    ok = (r <= radius_mm + 1.0) & (P[:, 2] >= -1.0) & (P[:, 2] <= height_mm + 1.0)
    P, r = P[ok], r[ok]
    if not len(P):
        return out
    i, j = out._cells(np.degrees(np.arctan2(P[:, 1], P[:, 0])), P[:, 2])
    cell = i * nz + j
    order = np.lexsort((r, cell))
    cell, r = cell[order], r[order]
    same_prev = np.r_[False, cell[1:] == cell[:-1]]
    same_next = np.r_[same_prev[1:], False]
    gap_prev = np.where(same_prev, np.r_[np.inf, np.diff(r)], np.inf)
    gap_next = np.where(same_next, np.r_[np.diff(r), np.inf], np.inf)
    supported = np.minimum(gap_prev, gap_next) <= OUTLIER_MM
    last = ~same_next                                     # each cell's largest radius
    flat = np.full(nphi * nz, np.nan)
    flat[cell[last]] = r[last]
    cs, rs = cell[supported], r[supported]                 # still sorted by cell, then r
    last_s = np.r_[cs[1:] != cs[:-1], True] if len(cs) else np.zeros(0, bool)
    flat[cs[last_s]] = rs[last_s]
    out.r_mm = flat.reshape(nphi, nz)
    return out


@dataclass(frozen=True, eq=False)
class OutlineKeepOut:
    """The outline grown by margin_mm, turning with the table: what the sensor (stage position
    S) must stay out of, checked in the object frame (X_R, n: the table axis, mm)."""

    outline: Outline
    X_R: np.ndarray
    n: np.ndarray
    margin_mm: float = 2.0

    def _table_coords(self, S: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """x, y, z (mm) of stage positions S (k, 3) in the table frame B not yet turned back:
        the object frame is B^T R_n(-theta) (S - X_R) (reconstruct.object_points), i.e. these
        with the azimuth less theta, as R_n(-theta) is a turn of -theta about B's z."""
        rel = np.atleast_2d(np.asarray(S, float)) - np.asarray(self.X_R, float)
        B = table_frame(np.asarray(self.n, float))
        return rel @ B[:, 0], rel @ B[:, 1], rel @ B[:, 2]  # (a (k,3)@(3,3) is slow in BLAS)

    def inside(self, S: np.ndarray, theta_deg: np.ndarray | float) -> np.ndarray:
        """(k,) bool: True where stage positions S (k, 3, mm) with the table at theta_deg
        (scalar or (k,), deg) are inside the keep-out: object-frame r < keep radius + margin
        and -margin < z < height + margin (the radius of the nearest height within the
        outline, so the margin also covers the top)."""
        S = np.atleast_2d(np.asarray(S, float))
        x, y, z = self._table_coords(S)
        o, m = self.outline, self.margin_mm
        out = (z > -m) & (z < o.height_mm + m) & (x * x + y * y < (o.radius_mm + m) ** 2)
        if out.any():  # the azimuth only where the bounding cylinder does not settle it
            k = np.flatnonzero(out)
            th = np.broadcast_to(np.asarray(theta_deg, float), (len(S),))[k]
            phi = np.degrees(np.arctan2(y[k], x[k])) - th
            keep = o.keep_radius_mm(phi, np.clip(z[k], 0.0, o.height_mm))
            out[k] = np.hypot(x[k], y[k]) < keep + m
        return out


def _describe(zone: object) -> str:
    """What a zone is, for the refusal."""
    if isinstance(zone, OutlineKeepOut):
        return f"the object's measured outline (+{zone.margin_mm:g} mm)"
    return (f"the object's keep-out cylinder (radius {zone.radius_mm:g} + {zone.margin_mm:g} "
            f"mm, height {zone.height_mm:g} mm)")


def check_moves(targets: list[tuple[float, float, float, float]], labels: list[str],
                start: tuple[float, float, float, float] | None, limits: MachineLimits,
                zones: list[OutlineKeepOut | KeepOut]) -> None:
    """Raise UnsafeMove naming the label if any straight move through the (X, Y, Z mm, A deg)
    targets, from start (None: from the first target), leaves the machine envelope (X, Y, Z)
    or passes through a zone. All axes move together and proportionally along a move (Marlin's
    linear moves), so the swept path is sampled, ends included, at most STEP_MM (0.25 mm) of
    stage travel and STEP_DEG (0.5 deg) of table turn apart, and with an outline zone at most
    0.25 mm of its circumference (at its radius + margin) apart. OutlineKeepOut zones are
    checked with the table angle at each sample, KeepOut cylinders (rotation-invariant) with
    their .inside; a KeepOut of radius 0 is no zone."""
    labels = [" ".join(str(x).split()) for x in labels]   # one line whatever the label holds
    T = np.asarray(targets, float).reshape(-1, 4)
    if len(labels) != len(T):
        raise ValueError(f"{len(T)} targets but {len(labels)} labels")
    if not len(T):
        return

    def prefix(k: int) -> str:
        t = T[k]
        return (f"scan plan refused before moving: {labels[k]} (X{t[0]:.6g} Y{t[1]:.6g} "
                f"Z{t[2]:.6g} A{t[3]:.6g})")

    lo, hi = np.asarray(limits.min_pos[:3], float), np.asarray(limits.max_pos[:3], float)
    bad = ~np.all(np.isfinite(T), axis=1) | np.any((T[:, :3] < lo) | (T[:, :3] > hi), axis=1)
    if bad.any():
        k = int(np.argmax(bad))
        try:
            check_target(dict(zip("XYZA", (float(x) for x in T[k]))), limits)
        except UnsafeMove as e:
            raise UnsafeMove(f"{prefix(k)}: {e}") from None
    if start is None:
        starts = np.vstack([T[:1], T[:-1]])
    else:
        s = np.asarray(start, float).reshape(4)
        if not np.all(np.isfinite(s)):
            raise UnsafeMove(f"{prefix(0)}: the stage's position {s.tolist()} is not known: "
                             f"home the stage first")
        starts = np.vstack([s[None], T[:-1]])
    zones = [z for z in zones if isinstance(z, OutlineKeepOut) or z.radius_mm > 0]
    if not zones:
        return
    d = T - starts
    r_cap = max([z.outline.radius_mm + z.margin_mm for z in zones
                 if isinstance(z, OutlineKeepOut)], default=0.0)
    step_deg = min(STEP_DEG, math.degrees(STEP_MM / r_cap)) if r_cap > 0 else STEP_DEG
    n_seg = np.maximum(np.ceil(np.linalg.norm(d[:, :3], axis=1) / STEP_MM),
                       np.ceil(np.abs(d[:, 3]) / step_deg))
    n_seg = np.maximum(n_seg, 1.0)
    if n_seg.max() > MAX_SAMPLES:
        k = int(np.argmax(n_seg > MAX_SAMPLES))
        raise UnsafeMove(f"{prefix(k)}: the move is too long to check ({n_seg[k]:.3g} samples): "
                         f"split it into shorter moves")
    n_seg = n_seg.astype(np.int64)
    offsets = np.r_[0, np.cumsum(n_seg + 1)]
    for g0 in range(0, int(offsets[-1]), CHUNK):
        g = np.arange(g0, min(g0 + CHUNK, int(offsets[-1])))
        m = np.searchsorted(offsets, g, side="right") - 1
        X = starts[m] + ((g - offsets[m]) / n_seg[m])[:, None] * d[m]
        which = np.full(len(g), -1)
        for zi, zone in enumerate(zones):
            if isinstance(zone, OutlineKeepOut):
                hit = zone.inside(X[:, :3], X[:, 3])
            else:
                hit = zone.inside(X[:, :3])
            which[hit & (which < 0)] = zi
        if (which >= 0).any():
            k = int(np.argmax(which >= 0))
            p = X[k]
            raise UnsafeMove(f"{prefix(int(m[k]))}: the move passes through "
                             f"{_describe(zones[which[k]])} near X{p[0]:.1f} Y{p[1]:.1f} "
                             f"Z{p[2]:.1f} at A{p[3]:.1f} deg; go around it, and turn the table "
                             f"only with the sensor clear of the object")
