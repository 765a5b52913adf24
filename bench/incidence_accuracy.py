"""Accuracy of a scan's points against the emulator's truth, by the incidence at which the
beam met the true surface (for bench/scan_coverage.py's figures).

A point's incidence is the angle between its beam (the calibrated direction v, turned into
the object frame at its table angle) and the true surface's normal at the nearest true
point; its error is its distance to that point. The paper's accuracies (0.06 +- 0.06 mm OA,
0.15 +- 0.11 mm US, mean and std of |error|) are of flat faces met head on: the < 10 deg bin
is the one to hold against them.
"""

from __future__ import annotations

import numpy as np

BINS_DEG = (0.0, 10.0, 20.0, 30.0, 45.0, 90.0)
PAPER_MM = {"oa": (0.06, 0.06), "us": (0.15, 0.11)}  # mean, std of |error| (Table I)
MAX_POINTS = 5000  # per modality and scan (a fixed-seed draw): bounds the nearest-point time


def beam_in_object_frame(S: np.ndarray, theta_deg: np.ndarray, v: np.ndarray, n: np.ndarray,
                         X_R: np.ndarray, object_frame) -> np.ndarray:
    """Unit beam directions (k, 3) in the object frame of points shot from stage positions S
    (k, 3, mm) at table angles theta_deg (k,): the frame map of S + v less that of S."""
    v = np.asarray(v, float) / np.linalg.norm(v)
    d = object_frame(S + v, theta_deg, n, X_R) - object_frame(S, theta_deg, n, X_R)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def nearest_on_truth(P: np.ndarray, truths: list) -> tuple[np.ndarray, np.ndarray]:
    """(distance mm, unit outward normal in the object frame) of each point (k, 3) to the
    nearest true surface of any mounted object."""
    best = np.full(len(P), np.inf)
    normal = np.zeros((len(P), 3))
    for t in truths:
        R = np.asarray(t.R, float)
        local = t.to_object(P)
        _, dist, tri = t.mesh.nearest.on_surface(local)
        closer = dist < best
        best[closer] = dist[closer]
        normal[closer] = np.asarray(t.mesh.face_normals, float)[tri[closer]] @ R.T
    return best, normal


def by_incidence(P: np.ndarray, S: np.ndarray, theta_deg: np.ndarray, v: np.ndarray,
                 n: np.ndarray, X_R: np.ndarray, truths: list, object_frame) -> list[dict]:
    """Per incidence bin (BINS_DEG): points, mean and std of |error| (mm)."""
    P, S, th = (np.asarray(a, float) for a in (P, S, theta_deg))
    if len(P) > MAX_POINTS:
        pick = np.random.default_rng(0).choice(len(P), MAX_POINTS, replace=False)
        P, S, th = P[pick], S[pick], th[pick]
    if not len(P) or not truths:
        return []
    err, normal = nearest_on_truth(P, truths)
    beam = beam_in_object_frame(S, th, v, n, X_R, object_frame)
    inc = np.degrees(np.arccos(np.clip(np.abs(np.sum(beam * normal, axis=1)), 0.0, 1.0)))
    out = []
    for lo, hi in zip(BINS_DEG[:-1], BINS_DEG[1:]):
        sel = (inc >= lo) & (inc < hi)
        e = err[sel]
        out.append({"from_deg": lo, "to_deg": hi, "n": int(sel.sum()),
                    "mean_mm": float(e.mean()) if len(e) else float("nan"),
                    "std_mm": float(e.std()) if len(e) > 1 else float("nan")})
    return out


def pooled(rows: list[list[dict]]) -> list[dict]:
    """The bins of several scans pooled (weighted by their points): mean and std of |error|
    over all their points, from each bin's n, mean and std."""
    out = []
    for k, (lo, hi) in enumerate(zip(BINS_DEG[:-1], BINS_DEG[1:])):
        parts = [r[k] for r in rows if r and r[k]["n"] > 1]
        n = sum(p["n"] for p in parts)
        if not n:
            out.append({"from_deg": lo, "to_deg": hi, "n": 0, "mean_mm": float("nan"),
                        "std_mm": float("nan")})
            continue
        mean = sum(p["n"] * p["mean_mm"] for p in parts) / n
        second = sum(p["n"] * (p["std_mm"] ** 2 + p["mean_mm"] ** 2) for p in parts) / n
        out.append({"from_deg": lo, "to_deg": hi, "n": n, "mean_mm": mean,
                    "std_mm": float(np.sqrt(max(second - mean * mean, 0.0)))})
    return out


def text(bins: list[dict]) -> str:
    """'0-10: 0.052 +- 0.041 (1234)  10-20: ...' for a row of bins ('-' where empty)."""
    def one(b: dict) -> str:
        if not b["n"]:
            return f"{b['from_deg']:g}-{b['to_deg']:g}: -"
        return (f"{b['from_deg']:g}-{b['to_deg']:g}: {b['mean_mm']:.3f} +- "
                f"{b['std_mm']:.3f} ({b['n']})")
    return "  ".join(one(b) for b in bins)
