"""Points per modality from a scan file, and the validation block's contour error (paper §V-A)."""

from __future__ import annotations

import numpy as np

from ..ranging.calibrate import RangingSetup, distance_std_mm
from .reconstruct import fit_box, object_points, stage_points
from .scanfile import ScanData

MODS = ("oa", "us")


def scan_points(scan: ScanData) -> dict[str, dict[str, np.ndarray]]:
    """Per modality: object-frame points (mm) and their row in the file's data (`row`: a fly
    line's shots share one point index), point index, level, angle, d, S, and
    d_std (mm): each distance's own standard deviation (ranging.distance_std_mm) from its
    SNR and the scan's ranging setup (NaN if the file carries no readable setup), and
    travel (k, 3) mm, the stage's travel while the shot's waveform was averaged
    (shot_travel_mm)."""
    cal = scan.calibration
    p = scan.points
    try:
        setup = RangingSetup.from_json(scan.ranging_json)
    except (ValueError, AttributeError):
        setup = None
    travel = shot_travel_mm(p)
    out = {}
    for m in MODS:
        d = p[f"distance_{m}_mm"]
        ok = np.isfinite(d) & p["received"]
        S = p["stage_position_mm"][ok]
        X = stage_points(S, d[ok], np.asarray(cal["v"]))
        P = object_points(X, p["theta_deg"][ok], np.asarray(cal["n"]), np.asarray(cal["X_R"]))
        std = (distance_std_mm(setup, m, p[f"snr_{m}_db"][ok])
               if setup is not None and m in setup.cals else np.full(ok.sum(), np.nan))
        out[m] = {"P": P, "row": np.flatnonzero(ok), "index": p["point_index"][ok],
                  "travel": travel[ok],
                  "level": p["level"][ok],
                  "theta_deg": p["theta_deg"][ok], "d": d[ok], "d_std": std, "S": S, "X": X}
    return out


def shot_travel_mm(p: dict[str, np.ndarray]) -> np.ndarray:
    """The stage's travel (n, 3) mm in the stage frame while each waveform of a scan's data p
    was averaged: on a fly or auto line (shots sharing a point index, level and angle) the
    stage moves through the average, so the distance belongs to a stretch of the path, not to
    its centre. Velocity from the neighbouring shots (position over device time), times the
    averaging window: the line's shortest spacing in time (averages follow one another). Zero
    for a step-and-shoot point (one shot, or shots at one place)."""
    n = len(p["point_index"])
    out = np.zeros((n, 3))
    ok = np.asarray(p["received"], bool)
    S = np.asarray(p["stage_position_mm"], float)
    t = np.asarray(p["timestamp"], np.float64)
    key = np.stack([np.asarray(p[k], np.int64) for k in ("point_index", "level", "angle_index")],
                   axis=1)
    rows = np.flatnonzero(ok)
    if len(rows) < 2:
        return out
    _, group = np.unique(key[rows], axis=0, return_inverse=True)
    for g in np.unique(group):
        r = rows[group.ravel() == g]
        if len(r) < 2:
            continue
        r = r[np.argsort(t[r], kind="stable")]
        dt = np.diff(t[r])
        if not (dt > 0).any():
            continue
        window = float(np.min(dt[dt > 0]))
        vel = np.diff(S[r], axis=0) / np.where(dt > 0, dt, np.inf)[:, None]  # mm per tick
        v = np.empty((len(r), 3))
        v[0], v[-1] = vel[0], vel[-1]
        v[1:-1] = 0.5 * (vel[:-1] + vel[1:])
        out[r] = v * window
    return out


def validate_block(pts: dict, size_xy: tuple[float, float]) -> dict[str, dict]:
    """The paper's metric per modality: fitted outline pose and e = d(X_ij, E_i) (mm), as
    mean and spread (std) like the paper, the mean's standard error, and the RMS of e over
    each point's own distance std (about 1 where the per-point stds hold)."""
    out = {}
    for m in MODS:
        P = pts[m]["P"]
        if len(P) >= 4:
            f = fit_box(P, size_xy)
            std = np.asarray(pts[m].get("d_std", np.full(len(P), np.nan)), float)
            std = std[np.all(np.isfinite(P), axis=1)]
            z = f.e_mm / std
            out[m] = {"n": f.n, "e_mean_mm": f.mean_mm, "e_std_mm": f.std_mm,
                      "e_mean_se_mm": f.std_mm / np.sqrt(f.n),
                      "e_over_std_rms": float(np.sqrt(np.mean(z ** 2))) if
                      np.isfinite(z).all() else float("nan"),
                      "e_median_mm": float(np.median(f.e_mm)),
                      "pose": {"x_mm": f.pose[0], "y_mm": f.pose[1], "yaw_deg": f.pose[2]}}
    return out
