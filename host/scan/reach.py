"""What the sensor reaches from a sweep's path: its limits per modality and the passes and
standoff a box's sweep needs for both (docs/scanning.md, "A box's passes")."""

from __future__ import annotations

import math

import numpy as np

US_MAX_INCIDENCE_DEG = 15.0  # US echoes come back within this of head on (bench/sensor_limits.py)
# the farthest (mm) a sweep's shots find each: US echoes at 12 averaged shots to ~46 mm (the
# tissue box's sweep: 41-79 % of shots at 38-46 mm, none beyond 48; the record ends at
# ~52), OA pulses to 80-100 mm (bench/sensor_limits.py); a margin below each
REACH_MM = {"us": 44.0, "oa": 80.0}
MAX_INCIDENCE_DEG = {"us": US_MAX_INCIDENCE_DEG, "oa": 30.0}  # OA: 30 on paper, 60 on metal
MIN_STANDOFF_MM = 3.0  # a sweep's sensor outside the bounding cylinder at least (the
# keep-out margin is 2 mm; the cylinder is 1 mm outside the object)
FACE_STEP_MM = 0.5     # the faces' sampling in the model


def face_hit(half_mm: float, offset_mm: float, phi_rad: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
    """(along the face from its middle, out from the table axis along the beam; mm) where a
    beam offset_mm across from the axis meets a flat face half_mm from it, turned phi_rad
    from facing the beam head on: (o - a sin phi) / cos phi and (a - o sin phi) / cos phi."""
    s, c = np.sin(phi_rad), np.cos(phi_rad)
    return (offset_mm - half_mm * s) / c, (half_mm - offset_mm * s) / c


def face_share(half_mm: float, face_mm: float, path_mm: float, offsets_mm: list[float],
               modality: str, spacing_mm: float) -> float:
    """The share of a flat face (face_mm wide, half_mm from the table axis) that one turn of
    passes at offsets_mm (mm across the beam) from path_mm out (the sensor's distance from
    the axis along the beam) sees in one modality: a point of it within spacing_mm of where
    a beam meets it within the modality's incidence and reach (face_hit)."""
    phi = np.radians(np.linspace(-MAX_INCIDENCE_DEG[modality], MAX_INCIDENCE_DEG[modality],
                                 241))
    hits = []
    for o in offsets_mm:
        t, out = face_hit(half_mm, o, phi)
        ok = (path_mm - out <= REACH_MM[modality]) & (np.abs(t) <= face_mm / 2)
        hits.append(t[ok])
    met = np.sort(np.concatenate(hits))
    face = np.arange(-face_mm / 2, face_mm / 2 + 1e-9, FACE_STEP_MM)
    if not len(met):
        return 0.0
    k = np.clip(np.searchsorted(met, face), 1, len(met) - 1)
    gap = np.minimum(np.abs(face - met[k - 1]), np.abs(face - met[k]))
    return float(np.mean(gap <= spacing_mm))


def box_share(width_mm: float, depth_mm: float, path_mm: float, offsets_mm: list[float],
              modality: str, spacing_mm: float) -> float:
    """face_share over a box's four faces centred on the axis, by their widths."""
    w, d = width_mm, depth_mm
    return (w * face_share(d / 2, w, path_mm, offsets_mm, modality, spacing_mm)
            + d * face_share(w / 2, d, path_mm, offsets_mm, modality, spacing_mm)) / (w + d)


def strips(side_mm: float, n: int, limit_mm: float) -> list[float]:
    """The middles (mm) of n equal strips of a side centred on the axis, within +-limit_mm."""
    return [round(math.copysign(min(abs(k), limit_mm), k), 1)
            for k in ((j + 0.5) * side_mm / n - side_mm / 2 for j in range(n))]


def box_passes(width_mm: float, depth_mm: float, radius_mm: float, standoff_mm: float,
               modalities: tuple[str, ...], spacing_mm: float, max_passes: int
               ) -> tuple[list[float], float, dict[str, float]]:
    """(offsets_mm, standoff_mm, the share of the faces the model sees per modality) of a
    box's sweep: the standoff brought in (to MIN_STANDOFF_MM at least) until the faces
    nearest the axis are within a modality's reach head on, then the fewest equal strips of
    the widest side (at most max_passes) that see within half a per cent of what the most
    would, in every modality."""
    near = min(width_mm, depth_mm) / 2
    for m in modalities:  # within reach head on, with 4 mm to spare for the faces' tilt
        standoff_mm = min(standoff_mm, near + REACH_MM[m] - 4.0 - radius_mm)
    standoff_mm = round(max(standoff_mm, MIN_STANDOFF_MM), 1)
    path = radius_mm + standoff_mm
    side = max(width_mm, depth_mm)
    shares = {n: {m: box_share(width_mm, depth_mm, path, strips(side, n, 0.9 * radius_mm), m,
                               spacing_mm) for m in modalities}
              for n in range(1, max_passes + 1)}
    best = {m: max(s[m] for s in shares.values()) for m in modalities}
    n = min(k for k, s in shares.items() if all(s[m] >= best[m] - 0.005 for m in modalities))
    return strips(side, n, 0.9 * radius_mm), standoff_mm, shares[n]
