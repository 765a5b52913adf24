"""The auto scan's first look (issue 32): the coarse fly pass from the bounding cylinder's
front plane that measures the object's outline, the far look where it left a row open, and
what to tell the operator when it saw no surface.

Pure functions on numpy arrays; auto.py plans the follow and hole lines from the outline.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from .outline import Outline
from .plan import Point, ScanPlan, expand

FIRST_LOOK_ANGLES = 8     # table angles of the first look (every 45 deg)
# where the first look from the plan's standoff leaves its row of the outline open, a "both"
# plan looks again from farther out: the cylinder's radius away, at most this far. A lone OA
# pulse is read only where its US reading is nearer than the cylinder (host/ranging/
# point.py), i.e. up to about the standoff behind the cylinder's front (from the front to
# the axis at a standoff of the radius), and twice this (97 mm) stays inside what a
# 1024-sample record (~104 mm of OA) and the OA ranging (80-100 mm) reach
FAR_LOOK_MAX_STANDOFF_MM = 48.0
LONE_PULSE_DB = 20.0      # a first look that saw nothing: a waveform with a pulse this strong
LONE_PULSES_MIN = 10      # ... on at least this many waveforms and this share of them is an
LONE_PULSES_SHARE = 0.02  # object answering in one modality (no_surface_reason)
TABLE_TOP_MM = 0.0        # a window reaches down to the table: the object's foot and the
# table top reflect too (with 1 mm, a pulse from the foot of the block 42 mm away read as
# a US echo at 21 mm, in mid-air, beside the corner in every first look)


def _lone_pulses(snr_oa_db: np.ndarray, snr_us_db: np.ndarray, d_oa_mm: np.ndarray,
                 d_us_mm: np.ndarray) -> tuple[int, int, int]:
    """(waveforms, waveforms with a pulse of LONE_PULSE_DB or more and no distance, waveforms
    with a distance) of a first look (per waveform: SNR dB and distance mm or NaN)."""
    snr = np.fmax(np.asarray(snr_oa_db, float), np.asarray(snr_us_db, float))
    ranged = np.isfinite(d_oa_mm) | np.isfinite(d_us_mm)
    return len(snr), int(((snr >= LONE_PULSE_DB) & ~ranged).sum()), int(ranged.sum())


_ONE_MODALITY = ("an object that answers in one modality? steel and glass give no OA pulse: "
                 "set modality = \"us\" in the plan; foam gives no US echo: modality = "
                 "\"oa\"")


def no_surface_reason(snr_oa_db: np.ndarray, snr_us_db: np.ndarray, d_oa_mm: np.ndarray,
                      d_us_mm: np.ndarray, modality: str) -> str:
    """What to tell the operator when a first look's waveforms (per waveform: SNR dB and
    distance mm or NaN, per modality) gave no surface. A "both" plan reads a lone pulse
    only where it can tell OA from US (host/ranging/point.py); an object that answers in one
    modality (steel and glass give no OA pulse, foam no US echo) leaves its waveforms full
    of pulses and its outline empty, and the way out is the plan's modality, not the
    object's place."""
    n, k, _ = _lone_pulses(snr_oa_db, snr_us_db, d_oa_mm, d_us_mm)
    if modality == "both" and k >= max(LONE_PULSES_MIN, LONE_PULSES_SHARE * n):
        return (f"the first look saw no surface at the plan's levels: {k} of its {n} "
                f"waveforms carried a pulse (>= {LONE_PULSE_DB:g} dB) it could not tell OA "
                f"or US (no OA and US pair): {_ONE_MODALITY}")
    return (f"the first look saw no surface at the plan's levels ({n} waveforms, {k} with "
            f"a pulse of >= {LONE_PULSE_DB:g} dB): is the object on the table, within "
            f"radius_mm and height_mm of the plan, and levels_mm within its height?")


def one_modality_note(snr_oa_db: np.ndarray, snr_us_db: np.ndarray, d_oa_mm: np.ndarray,
                      d_us_mm: np.ndarray, modality: str) -> str | None:
    """A note for the operator when a "both" plan's first look saw some surface but left
    more waveforms with a lone pulse it could not read than it ranged (a one-modality
    object whose flanks or foot gave a few readable pulses): the scan goes on, with few
    points; None otherwise."""
    n, k, found = _lone_pulses(snr_oa_db, snr_us_db, d_oa_mm, d_us_mm)
    if modality != "both" or k < max(LONE_PULSES_MIN, LONE_PULSES_SHARE * n) or k <= found:
        return None
    return (f"the first look ranged {found} of its {n} waveforms and could not tell OA or US "
            f"on {k} that carried a pulse: {_ONE_MODALITY}")


def far_look_standoff_mm(plan: ScanPlan) -> float:
    """The far look's standoff (mm) from the bounding cylinder: its radius, at least the
    plan's standoff, at most FAR_LOOK_MAX_STANDOFF_MM."""
    return max(plan.standoff_mm, min(plan.radius_mm, FAR_LOOK_MAX_STANDOFF_MM))


def first_look_plan(plan: ScanPlan) -> ScanPlan:
    """The first look: a fly pass from the bounding cylinder's front plane (`standoff_mm`
    in front of it), levels every first_look_step_mm over the heights the follow lines
    scan (one step beyond them either way, within the object's height), FIRST_LOOK_ANGLES
    table angles, the plan's step."""
    h, dz = plan.height_mm, plan.first_look_step_mm
    lo = max(min(plan.levels_mm) - dz, min(dz / 2, h / 2))
    hi = min(max(plan.levels_mm) + dz, h)
    levels = [round(float(z), 3) for z in np.arange(lo, hi + 1e-9, dz)] or [
        round(min(lo, h / 2), 3)]
    angles = [360.0 * k / FIRST_LOOK_ANGLES for k in range(FIRST_LOOK_ANGLES)]
    return replace(plan, mode="fly", levels_mm=levels, angles_deg=angles,
                   half_width_mm=plan.radius_mm)


def far_look_plan(plan: ScanPlan, levels_mm: list[float]) -> ScanPlan:
    """The far look at some of the first look's levels: the same lines from
    far_look_standoff_mm in front of the bounding cylinder."""
    return replace(first_look_plan(plan), levels_mm=list(levels_mm),
                   standoff_mm=far_look_standoff_mm(plan))


def far_look_levels(plan: ScanPlan, outline: Outline, v: np.ndarray) -> list[float]:
    """The first look's levels (mm) to look at again from farther out: for a "both" plan
    (a lone pulse of an "oa" or "us" plan is read as theirs already) those whose row of
    the outline (at the height the beam reaches standoff_mm away) has a cell left open,
    when the far look stands farther out than the first."""
    if plan.modality != "both" or far_look_standoff_mm(plan) <= plan.standoff_mm:
        return []
    closed = outline.closed()
    out = []
    for z in first_look_plan(plan).levels_mm:
        j = int(np.clip(np.searchsorted(outline.z_edges_mm, z + plan.standoff_mm * v[2],
                                        side="right") - 1, 0, closed.shape[1] - 1))
        if not closed[:, j].all():
            out.append(z)
    return out


def first_look_points(plan: ScanPlan, v: np.ndarray, X_R: np.ndarray,
                      n: np.ndarray | None = None, levels_mm: list[float] | None = None,
                      first_line: int = 0, first_index: int = 0) -> list[Point]:
    """The first look's points in execution order, each line numbered (from first_line,
    indices from first_index); with levels_mm, the far look's at those levels instead.
    With the table axis n, each with its window_mm: where its beam crosses the bounding
    cylinder (the ranger reads a lone pulse by it)."""
    look = first_look_plan(plan) if levels_mm is None else far_look_plan(plan, levels_mm)
    pts = _numbered(expand(look, v, X_R), first_line)
    for p in pts:
        p.index += first_index
    if n is not None:
        set_cylinder_windows(pts, v, n, X_R, plan.radius_mm, plan.height_mm)
    return pts


def set_cylinder_windows(points: list[Point], v: np.ndarray, n: np.ndarray, X_R: np.ndarray,
                         radius_mm: float, height_mm: float) -> None:
    """Set each point's window_mm to where its beam crosses the bounding cylinder
    (cylinder_window; NaN where it misses): the ranger reads a lone pulse by it."""
    if not points:
        return
    S = np.array([[p.x, p.y, p.z] for p in points], float)
    near, far = cylinder_window(S, v, n, X_R, radius_mm, height_mm)
    for p, a, b in zip(points, near, far):
        p.window_mm = (float(a), float(b))


def cylinder_window(S: np.ndarray, v: np.ndarray, n: np.ndarray, X_R: np.ndarray,
                    radius_mm: float, height_mm: float, z_min_mm: float = TABLE_TOP_MM
                    ) -> tuple[np.ndarray, np.ndarray]:
    """(near, far) beam distances (mm, (k,) each) over which the beams X = S + d v of
    sensors at S (k, 3) cross the bounding cylinder (axis X_R along n, radius_mm, heights
    z_min_mm .. height_mm above the table); NaN where a beam misses it or it lies behind
    the sensor."""
    v = np.asarray(v, float) / np.linalg.norm(v)
    n = np.asarray(n, float) / np.linalg.norm(n)
    rel = np.asarray(S, float).reshape(-1, 3) - np.asarray(X_R, float)
    z0, vz = rel @ n, float(v @ n)                     # height and its rate along the beam
    p, q = rel - z0[:, None] * n, v - vz * n           # across the axis
    a = float(q @ q)
    b, c = p @ q, np.einsum("ij,ij->i", p, p) - radius_mm ** 2
    near = np.full(len(rel), -np.inf)
    far = np.full(len(rel), np.inf)
    if a > 1e-12:
        disc = b * b - a * c
        root = np.sqrt(np.where(disc >= 0, disc, np.nan))
        near, far = (-b - root) / a, (-b + root) / a
    elif radius_mm > 0:  # along the axis: inside the radius or nowhere
        near = np.where(c <= 0, near, np.nan)
        far = np.where(c <= 0, far, np.nan)
    if abs(vz) > 1e-12:
        t1, t2 = (z_min_mm - z0) / vz, (height_mm - z0) / vz
        near, far = np.maximum(near, np.minimum(t1, t2)), np.minimum(far, np.maximum(t1, t2))
    else:
        inside = (z0 >= z_min_mm) & (z0 <= height_mm)
        near, far = np.where(inside, near, np.nan), np.where(inside, far, np.nan)
    near = np.maximum(near, 0.0)
    bad = ~(np.isfinite(near) & np.isfinite(far) & (far > near))
    return np.where(bad, np.nan, near), np.where(bad, np.nan, far)


def _numbered(pts: list[Point], first_line: int) -> list[Point]:
    """Number the lines (same angle and level, consecutive) from first_line on."""
    line, key = first_line - 1, None
    for p in pts:
        if (p.angle_index, p.level) != key:
            line, key = line + 1, (p.angle_index, p.level)
        p.line = line
    return pts
