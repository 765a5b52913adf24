"""Stage safety: the machine envelope minus a keep-out cylinder around the turntable's object."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dmdsm.marlin_patch import MachineLimits

#: the paper's Table I, used until the scanner is calibrated ([calibration] in dmdsm.toml)
TABLE_I = {"v": (0.0656, 0.9955, -0.0678), "n": (-0.0007, 0.0022, 0.9999),
           "X_R": (235.21, 288.17, 0.00)}


class UnsafeMove(ValueError):
    """A move that would leave the envelope or enter the keep-out; nothing was sent."""


@dataclass(frozen=True)
class KeepOut:
    """Cylinder about the table axis (through X_R along n): radius and height in mm."""

    X_R: np.ndarray
    n: np.ndarray
    radius_mm: float
    height_mm: float
    margin_mm: float = 2.0

    def inside(self, points: np.ndarray) -> np.ndarray:
        """True for points (k, 3) within the cylinder grown by the margin."""
        n = self.n / np.linalg.norm(self.n)
        rel = np.atleast_2d(points) - self.X_R
        h = rel @ n
        r = np.linalg.norm(rel - np.outer(h, n), axis=1)
        return ((r < self.radius_mm + self.margin_mm) & (h > -self.margin_mm)
                & (h < self.height_mm + self.margin_mm))


def check_target(target: dict[str, float | None], limits: MachineLimits,
                 envelope: bool = True) -> None:
    """Raise UnsafeMove if an axis target (X, Y, Z in mm; A in deg) is not a finite number
    or, for X, Y, Z and `envelope` (an absolute target), lies outside the machine envelope.
    None means the axis stays."""
    for axis, value in target.items():
        if value is None:
            continue
        if not np.isfinite(value):
            raise UnsafeMove(f"{axis} {value} is not a position: give a finite number")
        if envelope and axis in "XYZ":
            i = "XYZ".index(axis)
            lo, hi = limits.min_pos[i], limits.max_pos[i]
            if not lo <= value <= hi:
                raise UnsafeMove(f"{axis}{value:g} is outside the machine envelope "
                                 f"({lo:g}..{hi:g} mm)")


def check_move(start: np.ndarray, target: np.ndarray, limits: MachineLimits,
               keep_out: KeepOut | None = None, steps: int = 400) -> None:
    """Raise UnsafeMove if the straight XYZ path from start to target (mm) is not allowed."""
    check_target(dict(zip("XYZ", (float(t) for t in target))), limits)
    if keep_out is None or keep_out.radius_mm <= 0:
        return
    path = start + np.linspace(0, 1, steps)[:, None] * (np.asarray(target) - start)
    hit = keep_out.inside(path)
    if hit.any():
        p = path[np.argmax(hit)]
        raise UnsafeMove(f"the move passes through the object's keep-out cylinder (radius "
                         f"{keep_out.radius_mm:g} + {keep_out.margin_mm:g} mm, height "
                         f"{keep_out.height_mm:g} mm) near X{p[0]:.1f} Y{p[1]:.1f} Z{p[2]:.1f}; "
                         f"go around it")
