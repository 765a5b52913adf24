"""Points per modality from a scan file, and the validation block's contour error (paper §V-A)."""

from __future__ import annotations

import numpy as np

from .reconstruct import fit_box, object_points, stage_points
from .scanfile import ScanData

MODS = ("oa", "us")


def scan_points(scan: ScanData) -> dict[str, dict[str, np.ndarray]]:
    """Per modality: object-frame points (mm) and their point index, level, angle, d, S."""
    cal = scan.calibration
    p = scan.points
    out = {}
    for m in MODS:
        d = p[f"distance_{m}_mm"]
        ok = np.isfinite(d) & p["received"]
        S = p["stage_position_mm"][ok]
        X = stage_points(S, d[ok], np.asarray(cal["v"]))
        P = object_points(X, p["theta_deg"][ok], np.asarray(cal["n"]), np.asarray(cal["X_R"]))
        out[m] = {"P": P, "index": p["point_index"][ok], "level": p["level"][ok],
                  "theta_deg": p["theta_deg"][ok], "d": d[ok], "S": S, "X": X}
    return out


def validate_block(pts: dict, size_xy: tuple[float, float]) -> dict[str, dict]:
    """The paper's metric per modality: fitted outline pose and e = d(X_ij, E_i) (mm)."""
    out = {}
    for m in MODS:
        if len(pts[m]["P"]) >= 4:
            f = fit_box(pts[m]["P"], size_xy)
            out[m] = {"n": f.n, "e_mean_mm": f.mean_mm, "e_std_mm": f.std_mm,
                      "e_median_mm": float(np.median(f.e_mm)),
                      "pose": {"x_mm": f.pose[0], "y_mm": f.pose[1], "yaw_deg": f.pose[2]}}
    return out
