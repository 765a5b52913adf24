"""Calibration results on disk: the calibration.toml that `dmdsm calibrate` writes, scans read."""

from __future__ import annotations

import datetime
import json
import tomllib
from pathlib import Path

import numpy as np

from ..files import file_hash, vector3
from ..version import __version__
from .solver import CalibrationError, CalibrationResult


def load_calibration(path: Path) -> tuple[dict, str]:
    """v, n, X_R (and stds) from a `dmdsm calibrate` result TOML, and its text."""
    try:
        text = Path(path).read_text()
        cal = tomllib.loads(text)["calibration"]
        out = {k: vector3(cal[k], k, nonzero=k != "X_R") for k in ("v", "n", "X_R")}
    except OSError as e:
        raise CalibrationError(f"cannot read calibration {path}: {e.strerror}; run `dmdsm "
                       f"calibrate` first") from None
    except (tomllib.TOMLDecodeError, KeyError, TypeError, ValueError) as e:
        raise CalibrationError(f"{path} is not a dmdsm calibration ({e}); run `dmdsm calibrate`") \
            from None
    for k in ("v_std", "n_std", "X_R_std"):
        if k in cal:
            out[k] = [float(x) for x in cal[k]]
    for k in ("v_angle_std_deg", "n_angle_std_deg"):  # absent from files before issue 30
        if isinstance(cal.get(k), (int, float)):
            out[k] = float(cal[k])
    if "cov" in cal:  # absent from files before the joint covariance was written
        c = joint_covariance(cal["cov"])
        if c is None:
            raise CalibrationError(f"{path}: cov must be the symmetric 9 x 9 covariance of v, "
                                   f"n, X_R; run `dmdsm calibrate` again")
        out["cov"] = c.tolist()
    if "modality" in cal:  # absent from files before 2026-12-06 (they were OA's, the default)
        if cal["modality"] not in ("oa", "us"):
            raise CalibrationError(f"{path}: modality must be \"oa\" or \"us\" (the distances "
                                   f"the calibration used), not {cal['modality']!r}")
        out["modality"] = cal["modality"]
    out["source"] = str(path)
    return out, text


def joint_covariance(value: object) -> np.ndarray | None:
    """A calibration's `cov` as a 9 x 9 array (v, n, X_R) when it is one - finite, symmetric,
    positive semi-definite - else None."""
    try:
        c = np.array(value, dtype=float)
    except (TypeError, ValueError):
        return None
    if c.shape != (9, 9) or not np.isfinite(c).all() or \
            not np.allclose(c, c.T, rtol=1e-6, atol=1e-300):
        return None
    scale = float(np.abs(c).max(initial=0.0))
    return c if np.linalg.eigvalsh(0.5 * (c + c.T)).min() >= -1e-9 * scale else None


def result_dict(r: CalibrationResult) -> dict:
    """The JSON form `dmdsm calibrate --json` prints: `angle_std_deg` holds the angular std
    (deg) of v and n, the one a unit vector's error should be read against; `std` the
    per-component stds (X_R: mm, x and y in the table plane, z the gauge)."""
    return {"v": r.v.tolist(), "n": r.n.tolist(), "X_R": r.X_R.tolist(),
            "angle_std_deg": dict(r.angle_std_deg),
            "std": {k: np.asarray(v).tolist() for k, v in r.std.items()},
            "rms_residual_mm": r.rms_residual_mm,
            "depth_scatter_mm": {"tip": r.tip_depth_scatter_mm, "edge": r.edge_depth_scatter_mm},
            "lateral_scale": r.lateral_scale,
            "residuals": {"tip_mm": r.residuals["tip"].tolist(),
                          "edge_mm": r.residuals["edge"].tolist(),
                          "theta_deg": r.residuals["theta_deg"].tolist()}}


def write_result(r: CalibrationResult, path: Path, source: str, modality: str = "oa") -> None:
    """The calibration TOML that dmdsm commands load ([calibration] section); modality: the
    one whose distances placed the centre points (its ranging offset went into X_R, so a
    model's points of that modality do not carry it again: model.build)."""
    def vec(x: np.ndarray) -> str:
        return "[" + ", ".join(f"{float(a):.9g}" for a in x) + "]"
    lines = ["# dmdsm scanner calibration (paper Table I layout)", "[calibration]",
             f"v = {vec(r.v)}", f"n = {vec(r.n)}", f"X_R = {vec(r.X_R)}",
             f"v_std = {vec(r.std['v'])}", f"n_std = {vec(r.std['n'])}",
             f"X_R_std = {vec(r.std['X_R'])}",
             *(f"{k}_angle_std_deg = {r.angle_std_deg[k]:.6g}" for k in ("v", "n")
               if k in r.angle_std_deg),
             *([] if r.cov is None else
               ["# joint covariance of v, n (unitless) and X_R (mm), 9 x 9 in that order",
                "cov = [" + ", ".join(vec(row) for row in 0.5 * (r.cov + r.cov.T)) + "]"]),
             f"rms_residual_mm = {r.rms_residual_mm:.6g}",
             f"tip_depth_scatter_mm = {r.tip_depth_scatter_mm:.6g}",
             f"edge_depth_scatter_mm = {r.edge_depth_scatter_mm:.6g}",
             f"lateral_scale = {r.lateral_scale:.6g}",
             f"modality = {json.dumps(modality)}  # the distances the centre points came from",
             f"source = {json.dumps(source)}",
             f"source_sha256 = \"{file_hash(Path(source))}\"",
             f"date = {json.dumps(datetime.datetime.now().isoformat(timespec='seconds'))}",
             f"software = \"dmdsm {__version__}\""]
    Path(path).write_text("\n".join(lines) + "\n")
