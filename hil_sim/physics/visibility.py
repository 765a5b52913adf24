"""The part of an object's true surface the sensor can reach from some table angle (ray casts).

The truth a scan's coverage is judged against (host/scan/coverage.py): not the whole surface
(a bowl's inside, an object's floor, a top the beam only grazes can never give a point) but the
samples, evenly spaced over the surface, that some table angle shows to the sensor: the ray from
the sample toward the sensor (-v, turned into the table's frame at that angle) leaves the object
without meeting it again (an Embree ray cast through trimesh, as hil_sim/physics/mesh.py casts),
and the beam meets the surface at most `max_incidence_deg` from its normal.

Points and normals come in the turntable frame at theta = 0: origin X_R, z along n, x along
unit(y0 x n), the frame of `Scene` (scene.py's `table_frame`, `Scene._frames`) and the object
frame of the host's host/scan/reconstruct.py (`object_points`). All lengths in mm, angles in
degrees. The sensor is taken as far away (the beam's direction alone decides) and the table
itself as no obstacle (the beam looks down onto it, so the ray toward the sensor rises); other
objects on the table are not obstacles either (one object at a time).
"""

from __future__ import annotations

import numpy as np
import trimesh

from .mesh import ObjectTruth
from .scene import rodrigues, table_frame, unit

LIFT_MM = 1e-3           # the ray toward the sensor starts this far off the surface (mm)
RAYS_PER_CAST = 200_000  # rays per Embree call (bounded memory)
FLOOR_TOL_MM = 0.5       # a downward face within this of the object's lowest point is its floor
ANGLES_DEG = np.arange(0.0, 360.0, 5.0)  # table angles looked from by default (deg)
ANGLES_DEG.setflags(write=False)


def toward_sensor(v: np.ndarray, n: np.ndarray, theta_deg: float) -> np.ndarray:
    """Unit direction from the object toward the sensor (-v) in the turntable frame at
    theta = 0, with the table turned to `theta_deg` (deg): the world direction -v taken back
    through the table's rotation R_n(theta) and its frame (scene.py's Scene._frames)."""
    rot = rodrigues(n, np.radians(theta_deg)) @ table_frame(n)
    return rot.T @ -unit(v)


def surface_samples(truth: ObjectTruth, spacing_mm: float = 1.0, seed: int = 0
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Samples about `spacing_mm` (mm) apart over the whole true surface (trimesh's
    sample_surface_even, area / spacing^2 of them): points (m, 3, mm) and outward unit
    normals (m, 3), in the turntable frame at theta = 0."""
    if not spacing_mm > 0:
        raise ValueError(f"spacing_mm must be > 0 (got {spacing_mm})")
    mesh = truth.mesh
    count = max(int(np.ceil(mesh.area / spacing_mm ** 2)), 1)
    logger = trimesh.util.log
    level = logger.level
    logger.setLevel(max(level, 40))  # a few samples short of the count is expected
    try:
        p, face = trimesh.sample.sample_surface_even(mesh, count, seed=seed)
    finally:
        logger.setLevel(level)
    normals = np.asarray(mesh.face_normals, float)[face]
    R = np.asarray(truth.R, float)
    return np.asarray(p, float) @ R.T + truth.center, normals @ R.T


def visible_mask(truth: ObjectTruth, points: np.ndarray, normals: np.ndarray, v: np.ndarray,
                 n: np.ndarray, angles_deg: np.ndarray = ANGLES_DEG,
                 max_incidence_deg: float = 60.0) -> np.ndarray:
    """Per surface sample (points, normals: (m, 3), turntable frame at theta = 0, mm): True
    where at some table angle of `angles_deg` (deg) the beam (unit v, world) meets it at most
    `max_incidence_deg` (deg) from its normal and the ray from it toward the sensor leaves the
    object unobstructed. The object's floor (faces facing down at its lowest point, on the
    table) is never visible."""
    pts = np.asarray(points, float).reshape(-1, 3)
    nrm = np.asarray(normals, float).reshape(-1, 3)
    R = np.asarray(truth.R, float)
    own_p = (pts - truth.center) @ R  # the mesh's own frame, where the rays are cast
    own_n = nrm @ R
    origins = own_p + LIFT_MM * own_n
    lowest = float((np.asarray(truth.mesh.vertices, float) @ R.T + truth.center)[:, 2].min())
    floor = (nrm[:, 2] < -0.5) & (pts[:, 2] <= lowest + FLOOR_TOL_MM)
    seen = np.zeros(len(pts), bool)
    cos_max = np.cos(np.radians(max_incidence_deg))
    ray = truth.mesh.ray  # Embree when embreex is installed (as mesh.py), numpy otherwise
    for theta in np.asarray(angles_deg, float).ravel():
        d = R.T @ toward_sensor(v, n, float(theta))  # toward the sensor, mesh's own frame
        todo = np.flatnonzero(~seen & ~floor & (own_n @ d >= cos_max))
        for lo in range(0, len(todo), RAYS_PER_CAST):
            idx = todo[lo:lo + RAYS_PER_CAST]
            blocked = np.asarray(ray.intersects_any(origins[idx], np.tile(d, (len(idx), 1))),
                                 bool)
            seen[idx[~blocked]] = True
    return seen


def reachable_surface(truth: ObjectTruth, v: np.ndarray, n: np.ndarray, spacing_mm: float = 1.0,
                      angles_deg: np.ndarray = ANGLES_DEG,
                      max_incidence_deg: float = 60.0,
                      z_range_mm: tuple[float, float] | None = None, seed: int = 0
                      ) -> tuple[np.ndarray, np.ndarray]:
    """The surface samples (about `spacing_mm` mm apart) the sensor can see from some table
    angle of `angles_deg` (deg) at an incidence of at most `max_incidence_deg` (deg), within
    the heights `z_range_mm` (mm, turntable frame z: the scanner's reachable levels) if
    given: points (m, 3, mm) and outward unit normals (m, 3) in the turntable frame at
    theta = 0 (the host's object frame). v: the beam's unit direction, n: the table's axis
    (world frame). The share of the surface reachable is m over len(surface_samples(...)[0])
    with the same spacing and seed."""
    points, normals = surface_samples(truth, spacing_mm, seed)
    if z_range_mm is not None:
        keep = (points[:, 2] >= z_range_mm[0]) & (points[:, 2] <= z_range_mm[1])
        points, normals = points[keep], normals[keep]
    seen = visible_mask(truth, points, normals, v, n, angles_deg, max_incidence_deg)
    return points[seen], normals[seen]
