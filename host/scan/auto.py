"""Auto scans' paths (issue 32): lines that follow the outline the first look measured
(first_look.py), at the table angles that see each part of it, and the hole lines after them.

Pure functions on numpy arrays. A follow line keeps one table angle and one level; along it
the sensor moves X and Y together so the beam meets the outline `standoff_mm` away. Its Y
never comes nearer than that (under a lower envelope of the wanted Y with a bounded slope),
every junction of it can be taken at the line speed by Marlin's planner (junction
deviation), and of such lines it runs the nearest (a linear program). X always advances,
so the counted X steps place each shot (docs/scanning.md).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.optimize import linprog

from ..calibration.geometry import rodrigues
from .first_look import cylinder_window
from .fly import junction_speed_mm_s
from .outline import Outline, OutlineKeepOut
from .plan import Point, ScanPlan
from .reconstruct import table_frame

MAX_SLOPE = 1.0           # |dY/dX| of a follow line: X moves at >= 71 % of the path speed
CANDIDATE_STEP_DEG = 15.0  # table angles the angle choice picks from
EDGE_COLUMNS = 3          # columns a follow line runs on beside the surface (flat), each side
CLEARANCE_MM = 1.0        # a follow line keeps this far outside the keep-out (the checks'
# sampling and the chords between its vertices)


def _to_stage(P_obj: np.ndarray, theta_deg: float, n: np.ndarray, X_R: np.ndarray
              ) -> np.ndarray:
    """Object-frame points (k, 3) in the stage frame with the table at theta (mm)."""
    R = rodrigues(np.asarray(n, float), math.radians(theta_deg))
    return np.asarray(X_R, float) + P_obj @ (R @ table_frame(n)).T


def outline_ring(outline: Outline, z_mm: float) -> np.ndarray:
    """(nphi, 3) object-frame points of the outline at height z (mm): the measured radius
    where the cell is closed, the bounding cylinder where it is not (a sector the first
    look saw nothing in keeps the cylinder)."""
    nphi = outline.r_mm.shape[0]
    j = int(np.clip(np.searchsorted(outline.z_edges_mm, z_mm) - 1, 0, outline.r_mm.shape[1] - 1))
    phi = np.radians((np.arange(nphi) + 0.5) * outline.phi_step_deg)
    r = outline.filled_r_mm()[:, j]
    r = np.where(np.isfinite(r), r, outline.radius_mm)
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), np.full(nphi, z_mm)])


def beam_hits_y(outline: Outline, theta_deg: float, level_mm: float, xs: np.ndarray,
                ys: np.ndarray, v: np.ndarray, n: np.ndarray, X_R: np.ndarray) -> np.ndarray:
    """Stage Y (mm) where the beam of a sensor at (xs, ys) meets the outline ring at the
    level's height, the table at theta; NaN where it misses. In the XY plane: the beam's
    lines (along v's XY direction, from well behind the sensor) against the ring's edges."""
    ring = _to_stage(outline_ring(outline, level_mm), theta_deg, n, X_R)[:, :2]
    a, b = ring, np.roll(ring, -1, axis=0)
    d = np.asarray(v, float)[:2] / np.linalg.norm(np.asarray(v, float)[:2])
    o = np.column_stack([xs, np.broadcast_to(ys, np.shape(xs))]) - 400.0 * d
    e = b - a  # (m, 2)
    den = d[0] * e[:, 1] - d[1] * e[:, 0]  # cross(d, e)
    w = a[None, :, :] - o[:, None, :]      # (k, m, 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (w[..., 0] * e[:, 1] - w[..., 1] * e[:, 0]) / den
        u = (w[..., 0] * d[1] - w[..., 1] * d[0]) / den
    ok = (np.abs(den) > 1e-12) & (u >= 0) & (u <= 1) & (t > 0)
    t = np.where(ok, t, np.inf).min(axis=1)
    return np.where(np.isfinite(t), o[:, 1] + t * d[1], np.nan)


def follow_y(xs: np.ndarray, y_want: np.ndarray, v_mm_s: float, accel_mm_s2: float,
             junction_deviation_mm: float, every: int = 3,
             y_cap: np.ndarray | None = None) -> np.ndarray:
    """Sensor Y (mm) per column X (xs, evenly spaced) never above y_want (farther from the
    object; NaN: no surface there), with slope <= MAX_SLOPE, straight between its vertices
    (every `every`-th column, FlyLine.vertices) and bent at each so little that Marlin's
    planner takes every junction at v_mm_s: of those lines, the one nearest the surface
    (a linear program); the line flat at its lowest wanted Y if the solver fails."""
    ok = np.isfinite(y_want)
    if not ok.any():
        raise ValueError("the beam meets nothing along the line")
    # beside the surface the line runs on flat at its edges' Y, as its run-up and run-out do
    filled = np.interp(xs, xs[ok], y_want[ok])
    if y_cap is not None:  # and never into the keep-out, beside the surface too
        filled = np.minimum(filled, y_cap)
    env = np.min(filled[None, :] + MAX_SLOPE * np.abs(xs[:, None] - xs[None, :]), axis=1)
    keep = np.arange(len(xs)) % every == 0
    keep[[0, -1]] = True
    vi = np.flatnonzero(keep)
    y = _nearest_bent_line(xs, env, vi, _max_bend_rad(v_mm_s, accel_mm_s2,
                                                      junction_deviation_mm))
    if y is None or not _takes_at_speed(xs[vi], y[vi], v_mm_s, accel_mm_s2,
                                        junction_deviation_mm):
        return np.full(len(xs), float(np.min(env)))  # flat at the lowest wanted Y
    return np.minimum(y, env)  # the solver's last ulp


def _max_bend_rad(v_mm_s: float, accel_mm_s2: float, junction_deviation_mm: float) -> float:
    """The largest turn (rad) between two joined moves that Marlin's junction deviation lets
    the planner take at v_mm_s (junction_speed_mm_s solved for the angle), with a margin."""
    k = v_mm_s ** 2 / (accel_mm_s2 * junction_deviation_mm)
    return 0.9 * 2.0 * math.acos(min(k / (1.0 + k), 1.0))


def _nearest_bent_line(xs: np.ndarray, env: np.ndarray, vi: np.ndarray, bend_rad: float
                       ) -> np.ndarray | None:
    """Y (mm) per column of the line through vertices at columns vi (straight between them)
    with the largest sum of Y, under env at every column, |slope| <= MAX_SLOPE and each
    slope within bend_rad of the one before (flat run-up and run-out at the ends); since
    |atan a - atan b| <= |a - b| every turn is then within bend_rad. None if unsolved."""
    m, vx = len(vi), xs[vi]
    W = np.zeros((len(xs), m))  # column Y from vertex Y: linear between vertices
    seg = np.clip(np.searchsorted(vx, xs, side="right") - 1, 0, m - 2)
    t = (xs - vx[seg]) / (vx[seg + 1] - vx[seg])
    W[np.arange(len(xs)), seg] = 1.0 - t
    W[np.arange(len(xs)), seg + 1] = t
    D = np.zeros((m - 1, m))  # slopes of the segments
    idx = np.arange(m - 1)
    D[idx, idx], D[idx, idx + 1] = -1.0 / np.diff(vx), 1.0 / np.diff(vx)
    B = np.vstack([D[:1], np.diff(D, axis=0), -D[-1:]])  # turns, with the flat ends
    A = np.vstack([W, D, -D, B, -B])
    b = np.concatenate([env, np.full(2 * (m - 1), MAX_SLOPE), np.full(2 * len(B), bend_rad)])
    r = linprog(-W.sum(axis=0), A_ub=A, b_ub=b, bounds=[(None, None)] * m, method="highs")
    return W @ r.x if r.status == 0 else None


def _takes_at_speed(vx: np.ndarray, vy: np.ndarray, v_mm_s: float, accel_mm_s2: float,
                    junction_deviation_mm: float) -> bool:
    """True if Marlin's planner takes every junction of the vertices (and of the flat run-up
    and run-out) at v_mm_s."""
    seg = np.vstack([[1.0, 0.0], np.column_stack([np.diff(vx), np.diff(vy)]), [1.0, 0.0]])
    seg /= np.linalg.norm(seg, axis=1, keepdims=True)
    return all(junction_speed_mm_s(seg[i], seg[i + 1], accel_mm_s2, junction_deviation_mm)
               >= v_mm_s for i in range(len(seg) - 1))


def incidence_cos(outline: Outline, theta_deg: float, v: np.ndarray, n: np.ndarray
                  ) -> np.ndarray:
    """(nphi, nz) cosine of the angle between the beam and each outline cell's outward
    normal (in the table plane, from r(phi)) with the table at theta; <= 0: facing away."""
    nphi = outline.r_mm.shape[0]
    phi = np.radians((np.arange(nphi) + 0.5) * outline.phi_step_deg)
    r = outline.filled_r_mm()
    r = np.where(np.isfinite(r), r, outline.radius_mm)
    dr = (np.roll(r, -1, axis=0) - np.roll(r, 1, axis=0)) / (2 * np.radians(
        outline.phi_step_deg))
    c, s = np.cos(phi)[:, None], np.sin(phi)[:, None]
    tx, ty = dr * c - r * s, dr * s + r * c        # d/dphi of (r cos, r sin)
    nx, ny = ty, -tx
    norm = np.maximum(np.hypot(nx, ny), 1e-12)
    B = table_frame(n)
    R = rodrigues(np.asarray(n, float), math.radians(-theta_deg))
    b = B.T @ R @ (np.asarray(v, float) / np.linalg.norm(v))   # the beam in the object frame
    bn = math.hypot(b[0], b[1])
    return -(nx * b[0] + ny * b[1]) / norm / max(bn, 1e-12)


def choose_angles(outline: Outline, base_deg: list[float], v: np.ndarray, n: np.ndarray,
                  max_incidence_deg: float, max_angles: int) -> tuple[list[float], float]:
    """The table angles of the follow lines: the plan's, then greedily the candidate (every
    CANDIDATE_STEP_DEG) that sees the most closed outline cells not yet seen within
    max_incidence_deg, until all are seen or max_angles are taken. Returns the angles in
    ascending order and the share of closed cells seen."""
    closed = outline.closed()
    lim = math.cos(math.radians(max_incidence_deg))
    cands = list(np.arange(0.0, 360.0, CANDIDATE_STEP_DEG))
    sees = {a: (incidence_cos(outline, a, v, n) >= lim) & closed for a in set(cands) | set(
        base_deg)}
    chosen = list(dict.fromkeys(float(a) for a in base_deg))
    seen = np.zeros_like(closed)
    for a in chosen:
        seen |= sees[a]
    while len(chosen) < max_angles:
        gain = {a: int((sees[a] & ~seen).sum()) for a in cands if a not in chosen}
        best = max(gain, key=gain.get, default=None)
        if best is None or gain[best] == 0:
            break
        chosen.append(float(best))
        seen |= sees[best]
    share = float(seen.sum() / closed.sum()) if closed.any() else 0.0
    return sorted(chosen), share


def follow_keep_out(plan: ScanPlan, outline: Outline, X_R: np.ndarray, n: np.ndarray
                    ) -> OutlineKeepOut:
    """What the follow and hole lines keep out of. A plan that reads OA: the outline grown
    by its margin (the laser's path to an OA pulse is free space, and OA answers at up to
    60 deg of incidence, so what sticks out is in the outline). A US-only plan: the first
    look's own distance, standoff_mm outside the bounding cylinder, everywhere; a US echo
    comes back only head on, so a handle or a rim the outline never saw may stand anywhere
    beside the surfaces it did (a steel mug's handle gave no echo at all in the emulator),
    and the lines range from where the first look stood (US reaches 40 mm)."""
    X_R, n = np.asarray(X_R, float), np.asarray(n, float)
    if plan.modality != "us":
        return OutlineKeepOut(outline, X_R, n)
    margin = OutlineKeepOut.margin_mm
    R = max(plan.radius_mm + plan.standoff_mm - margin - CLEARANCE_MM, plan.radius_mm)
    stood = Outline(outline.phi_step_deg, outline.z_edges_mm, np.full_like(outline.r_mm, R),
                    R, outline.height_mm, outline.max_gap)
    return OutlineKeepOut(stood, X_R, n, margin)


def follow_points(plan: ScanPlan, outline: Outline, angles_deg: list[float], v: np.ndarray,
                  n: np.ndarray, X_R: np.ndarray, v_mm_s: float, accel_mm_s2: float,
                  junction_deviation_mm: float, first_line: int) -> list[Point]:
    """The follow lines' points in execution order (angle by angle, level by level, X back
    and forth), lines numbered from first_line: per line the columns where the beam meets
    the outline and EDGE_COLUMNS either side, Y from follow_y, no nearer than
    follow_keep_out allows."""
    v = np.asarray(v, float) / np.linalg.norm(v)
    keep = follow_keep_out(plan, outline, X_R, n)
    half = plan.radius_mm + EDGE_COLUMNS * plan.step_mm
    xs_all = X_R[0] + np.arange(-half, half + 1e-9, plan.step_mm)
    pts: list[Point] = []
    k = 0
    for ai, th in enumerate(angles_deg):
        for li, h in enumerate(plan.levels_mm):
            z_hit = h + plan.standoff_mm * v[2]  # where the beam meets the surface
            ys = np.full(len(xs_all), X_R[1] - (plan.radius_mm + plan.standoff_mm) * v[1])
            for _ in range(3):  # the sensor's X stays, its Y moves along the line: the beam
                yh = beam_hits_y(outline, th, z_hit, xs_all, ys, v, n, X_R)  # shifts a bit
                ys = np.where(np.isfinite(yh), yh - plan.standoff_mm * v[1], ys)
            hit = np.nonzero(np.isfinite(yh))[0]
            if not len(hit):
                continue
            sel = slice(max(hit[0] - EDGE_COLUMNS, 0), min(hit[-1] + EDGE_COLUMNS + 1,
                                                           len(xs_all)))
            xs, want = xs_all[sel], yh[sel] - plan.standoff_mm * v[1]
            if len(xs) < 2:
                continue
            front = X_R[1] - (plan.radius_mm + plan.standoff_mm) * v[1]  # outside it all
            cap = keep_out_cap(keep, xs, X_R[2] + h, th, front, float(np.nanmax(want)))
            y = follow_y(xs, want, v_mm_s, accel_mm_s2, junction_deviation_mm, y_cap=cap)
            expect = (yh[sel] - y) / v[1]  # where the outline says the beam meets it
            order = range(len(xs)) if k % 2 == 0 else range(len(xs) - 1, -1, -1)
            for ci in order:
                pts.append(Point(len(pts), float(xs[ci]), float(y[ci]), float(X_R[2] + h),
                                 float(th), li, ci, ai, first_line + k, float(expect[ci])))
            k += 1
    if pts:  # a US-only outline may miss what stands before it: the cylinder's window
        S = np.array([[p.x, p.y, p.z] for p in pts], float)
        near, far = cylinder_window(S, v, n, X_R, outline.radius_mm, outline.height_mm) \
            if plan.modality == "us" else outline_window(
                S, np.array([p.theta_deg for p in pts]), outline, v, n, X_R)
        for p, a, b in zip(pts, near, far):
            p.window_mm = (float(a), float(b))
    return pts


def outline_window(S: np.ndarray, theta_deg: np.ndarray, outline: Outline, v: np.ndarray,
                   n: np.ndarray, X_R: np.ndarray, step_mm: float = 0.25
                   ) -> tuple[np.ndarray, np.ndarray]:
    """(near, far) beam distances (mm, (k,) each) where the object can be along the beams of
    sensors at S (k, 3) with the table at theta_deg (k,): from where the beam enters the
    outline's keep-out without margin (the object lies inside it: the premise of its
    safety), found every step_mm along the beam, to where it leaves the bounding cylinder
    (cylinder_window); NaN where the beam misses either."""
    S = np.asarray(S, float).reshape(-1, 3)
    v = np.asarray(v, float) / np.linalg.norm(v)
    lo, far = cylinder_window(S, v, n, X_R, outline.radius_mm, outline.height_mm)
    keep = OutlineKeepOut(outline, np.asarray(X_R, float), np.asarray(n, float), 0.0)
    near = np.full(len(S), np.nan)
    th = np.broadcast_to(np.asarray(theta_deg, float), (len(S),))
    for i in np.flatnonzero(np.isfinite(lo)):
        d = np.arange(lo[i], far[i] + step_mm, step_mm)
        inside = keep.inside(S[i] + d[:, None] * v, th[i])
        if inside.any():
            near[i] = d[int(np.argmax(inside))]
    ok = np.isfinite(near)
    return near, np.where(ok, far, np.nan)


def hole_lines(outline: Outline, holes: list[tuple[np.ndarray, float]],
               angles_done: list[float], levels_mm: list[float], standoff_mm: float,
               v: np.ndarray, n: np.ndarray, line_s: float, budget_s: float,
               spacing_mm: float = 2.0) -> list[tuple[float, int, float]]:
    """(table angle deg, level index, sensor height mm) of the lines scanned again for the
    holes: per modality, the closed outline cells ((nphi, nz) bool) with no point of it near
    them after the follow lines, and the incidence (deg) within which a line must meet a
    cell to give that modality a point there (OA the plan's max_incidence_deg, US 15 deg).
    Greedily the candidate angle (every CANDIDATE_STEP_DEG, not yet scanned) and outline
    row whose line meets the most holes of the row within their incidences, while the
    lines' estimated time (line_s each) stays within budget_s.

    A row's line runs where its beam meets the row's centre height (a hole is the cell's
    centre with no point within spacing_mm): at the plan level nearest to that when one is
    within spacing_mm / 2 of it, else at the centre's own height, numbered as the nearest
    level, if that lies between the plan's lowest and highest level; rows outside the
    plan's levels are not scanned again."""
    vz = (np.asarray(v, float) / np.linalg.norm(v))[2]
    levels = np.asarray(levels_mm, float)
    centres = 0.5 * (outline.z_edges_mm[:-1] + outline.z_edges_mm[1:]) - standoff_mm * vz
    rows: dict[int, tuple[int, float]] = {}  # row: (level index, sensor height mm)
    for j, h in enumerate(centres):
        li = int(np.argmin(np.abs(levels - h)))
        if abs(levels[li] - h) <= spacing_mm / 2:
            rows[j] = (li, float(levels[li]))
        elif levels.min() <= h <= levels.max():
            rows[j] = (li, round(float(h), 3))
    left = [mask.copy() for mask, _ in holes]
    lims = [math.cos(math.radians(deg)) for _, deg in holes]
    cands = [a for a in np.arange(0.0, 360.0, CANDIDATE_STEP_DEG)
             if not any(abs((a - b + 180) % 360 - 180) < 1e-6 for b in angles_done)]
    cos = {a: incidence_cos(outline, a, v, n) for a in cands}
    sees = {a: [c >= lim for lim in lims] for a, c in cos.items()}
    chosen: list[tuple[float, int]] = []  # (angle, row)
    while (len(chosen) + 1) * line_s <= budget_s:
        best, gain = None, (0, 0.0)
        for a in cands:
            for j in rows:
                hits = [s_[:, j] & h[:, j] for s_, h in zip(sees[a], left)]
                # more holes met, then met nearer head on
                g = (sum(int(h.sum()) for h in hits),
                     sum(float(cos[a][h, j].sum()) for h in hits))
                if g[0] and g > gain and (float(a), j) not in chosen:
                    best, gain = (float(a), j), g
        if best is None:
            break
        chosen.append(best)
        a, j = best
        for s_, h in zip(sees[a], left):
            h[:, j] &= ~s_[:, j]
    return [(a, *rows[j]) for a, j in chosen]


def keep_out_cap(keep: OutlineKeepOut, xs: np.ndarray, z_mm: float, theta_deg: float,
                 y_front: float, y_far: float) -> np.ndarray:
    """Per column X, the largest sensor Y (mm) CLEARANCE_MM short of the outline's keep-out,
    searched from the front plane y_front (outside it) towards y_far in 0.25 mm steps; no
    cap (inf) where the keep-out is not met before y_far."""
    ys = np.arange(y_front, y_far + 0.25, 0.25)
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    S = np.column_stack([X.ravel(), Y.ravel(), np.full(X.size, z_mm)])
    inside = keep.inside(S, theta_deg).reshape(X.shape)
    first = np.where(inside.any(axis=1), inside.argmax(axis=1), -1)
    return np.where(first >= 0, ys[np.maximum(first, 0)] - CLEARANCE_MM, np.inf)
