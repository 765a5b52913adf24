"""Unit vectors, rotations (eq. 5) and tangent planes on the sphere, for the calibration solver."""

from __future__ import annotations

import numpy as np


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


def retract(u: np.ndarray, basis: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """u moved on the sphere by the tangent step basis @ delta (no pole singularity)."""
    return unit(u + basis @ delta)


def same_angle(a_deg: float, b_deg: float, tol_deg: float = 1.0) -> bool:
    """True if two turntable readings are the same angle modulo a turn (within tol_deg)."""
    return bool(abs((a_deg - b_deg + 180.0) % 360.0 - 180.0) < tol_deg)


def skew(a: np.ndarray) -> np.ndarray:
    """[a]_x: the matrix with [a]_x b = a x b."""
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
