"""How much of a surface a scan covered, and how much of the laser's firing ended in points.

Pure functions on numpy arrays (mm, s, Hz). `coverage` is the share of reference surface
samples (evenly spaced over the surface, e.g. the part of an object's true surface the sensor
can reach) that have a scan point within the sample spacing; `covered_mask` says which ones,
so a report can show where the holes are. `laser_duty` is the share of the shots a
free-running laser fired from a scan's start to its end that ended in a stored point.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def _rows(a: np.ndarray, what: str) -> np.ndarray:
    """`a` as a (k, 3) float array of finite points (rows with a NaN or inf left out)."""
    a = np.asarray(a, float)
    if a.size == 0:
        return a.reshape(0, 3)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{what} must be (k, 3) points in mm, got shape {a.shape}")
    return a[np.all(np.isfinite(a), axis=1)]


def covered_mask(surface_mm: np.ndarray, points_mm: np.ndarray, spacing_mm: float
                 ) -> np.ndarray:
    """Per reference surface sample (m, 3, mm): True where some scan point (k, 3, mm, same
    frame) lies within `spacing_mm` of it. Non-finite scan points count as none; a
    non-finite sample is never covered."""
    if not spacing_mm > 0:
        raise ValueError(f"spacing_mm must be > 0 (got {spacing_mm})")
    surface = np.asarray(surface_mm, float)
    surface = surface.reshape(0, 3) if surface.size == 0 else surface
    if surface.ndim != 2 or surface.shape[1] != 3:
        raise ValueError(f"surface_mm must be (m, 3) points in mm, got shape {surface.shape}")
    points = _rows(points_mm, "points_mm")
    out = np.zeros(len(surface), bool)
    ok = np.all(np.isfinite(surface), axis=1)
    if len(points) == 0 or not ok.any():
        return out
    dist, _ = cKDTree(points).query(surface[ok], k=1, distance_upper_bound=spacing_mm)
    out[ok] = dist <= spacing_mm
    return out


def coverage(surface_mm: np.ndarray, points_mm: np.ndarray, spacing_mm: float) -> float:
    """Share (0..1) of the reference surface samples (m, 3, mm) that have a scan point
    (k, 3, mm, same frame) within `spacing_mm` (mm, the samples' spacing): 0.0 when there are
    no scan points, NaN when there are no surface samples."""
    mask = covered_mask(surface_mm, points_mm, spacing_mm)
    return float(mask.mean()) if len(mask) else float("nan")


def laser_duty(stored_waveforms: int, average: int, laser_hz: float, duration_s: float
               ) -> float:
    """Share (0..1) of the shots a free-running laser fired from the scan's start to its end
    (laser_hz (Hz) x duration_s (s)) that ended in a stored point: stored waveforms x shots
    averaged per waveform, capped at 1. NaN when no shot was fired (duration or rate 0)."""
    if stored_waveforms < 0 or average < 1:
        raise ValueError(f"stored_waveforms must be >= 0 and average >= 1 "
                         f"(got {stored_waveforms}, {average})")
    if not (laser_hz >= 0 and duration_s >= 0):
        raise ValueError(f"laser_hz and duration_s must be >= 0 (got {laser_hz}, {duration_s})")
    fired = laser_hz * duration_s
    if fired <= 0:
        return float("nan")
    return float(min(stored_waveforms * average / fired, 1.0))
