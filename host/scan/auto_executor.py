"""Auto scans' run: the first look's fly lines, the outline from what they stored, then the
follow lines planned from it, checked against the outline's keep-out before they move, and
their coverage of that outline; resumed line by line like any fly scan.

The outline comes only from the first look's lines in the file, so a resumed scan plans the
same follow lines again and goes on after the last one stored.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from dmdsm.marlin_patch import MachineLimits

from ..links.interfaces import Stage, StreamSensor
from ..links.safety import KeepOut, UnsafeMove
from ..ranging.point import PointRanger
from .auto import (
    choose_angles,
    follow_keep_out,
    follow_points,
    hole_lines,
)
from .common import Progress, ScanStats
from .coverage import coverage, covered_mask
from .first_look import (
    far_look_levels,
    far_look_plan,
    first_look_plan,
    first_look_points,
    no_surface_reason,
    one_modality_note,
)
from .fly import ramp_mm
from .fly_executor import (
    TRANSITION_MM,
    FlyLine,
    fly_lines,
    fly_speed,
    joins_previous,
    line_path,
    run_fly_scan,
)
from .outline import Outline, check_moves, outline_from_points
from .plan import AUTO_SPACING_MM, PlanError, Point, ScanPlan, keep_outs
from .reach import US_MAX_INCIDENCE_DEG
from .reconstruct import object_points, stage_points
from .scanfile import ScanWriter

Waypoint = tuple[float, float, float, float]  # X, Y, Z (mm), A (deg)


@dataclass
class AutoPlan:
    """An auto scan's lines once the first look is in: the outline, the table angles chosen
    and the share of the outline they see within the plan's incidence, the follow points
    (numbered after the first look's) and the waypoints around the object by line index."""

    outline: Outline
    angles_deg: list[float]
    seen_share: float
    points: list[Point]
    via: dict[int, list[Waypoint]] = field(default_factory=dict)
    hole_share: float = 0.0  # closed outline cells with no point after the follow lines
    hole_points: list[Point] = field(default_factory=list)  # the lines scanned again
    skipped: list[str] = field(default_factory=list)  # lines left out: no safe move to them
    far_points: list[Point] = field(default_factory=list)  # the far look's (first look's)
    notes: list[str] = field(default_factory=list)  # for the operator: what may be wrong


def first_look_outline(writer: ScanWriter, n_look_lines: int, plan: ScanPlan,
                       calibration: dict) -> Outline:
    """The outline from the first look's stored lines (point_index < n_look_lines), both
    modalities' points in the object frame."""
    P = stored_points(writer, n_look_lines, calibration)
    return outline_from_points(P, plan.radius_mm, plan.height_mm,
                               z_step_mm=plan.first_look_step_mm)


def _line_targets(line: FlyLine, plan: ScanPlan, machine: MachineLimits,
                  start: Waypoint | None = None) -> tuple[list[Waypoint], list[str]]:
    """Run-up start (or `start`, where the stage stands, for a line joined to the one
    before), vertices and run-out end of a line as waypoints, labelled."""
    p0 = line.points[0]
    path = line_path(line, plan, machine, None if start is None else start[:2])
    t = [(float(x), float(y), p0.z, p0.theta_deg) for x, y in zip(path.x, path.y)]
    if start is not None:
        t[0] = start
    labels = [f"line {line.index}'s run-up start"] + [
        f"line {line.index} (X{x:.1f})" for x in path.x[1:-1]] + [
        f"line {line.index}'s run-out end"]
    return t, labels


def plan_follow(writer: ScanWriter, look: list[Point], plan: ScanPlan, calibration: dict,
                machine: MachineLimits, turntable: KeepOut) -> AutoPlan:
    """Plan the follow lines from the first look in the file and check every move of them
    (with the ways around the object between lines) against the outline's keep-out; raises
    UnsafeMove if none is safe, PlanError if the first look saw nothing in the outline's
    rows the plan's levels scan (no_surface_reason says why it may have)."""
    v, n, X_R = (np.asarray(calibration[k], float) for k in ("v", "n", "X_R"))
    n_look = len(fly_lines(look))
    outline = first_look_outline(writer, n_look, plan, calibration)
    rows = outline.rows_at(np.asarray(plan.levels_mm, float) + plan.standoff_mm * v[2]
                           / np.linalg.norm(v))
    d, m = writer.data, writer.n_done
    sel = d["point_index"][:m] < n_look
    look_data = [d[k][:m][sel] for k in ("snr_oa_db", "snr_us_db", "distance_oa_mm",
                                         "distance_us_mm")]
    if not outline.closed()[:, rows].any():  # nothing to follow where the plan scans
        raise PlanError(no_surface_reason(*look_data, plan.modality))
    note = one_modality_note(*look_data, plan.modality)
    angles, share = choose_angles(outline, plan.angles_deg, v, n, plan.max_incidence_deg,
                                  plan.max_angles)
    speed, accel = fly_speed(plan, machine)
    pts = follow_points(plan, outline, angles, v, n, X_R, speed, accel,
                        machine.junction_deviation_mm, n_look)
    for i, p in enumerate(pts):
        p.index = len(look) + i
    here = _line_targets(fly_lines(look)[-1], first_look_plan(plan), machine)[0][-1]
    pts, via, skipped = _safe_lines(look, pts, here, plan, machine,
                                    [follow_keep_out(plan, outline, X_R, n), turntable])
    return AutoPlan(outline, angles, share, pts, via, skipped=skipped,
                    notes=[note] if note else [])


class _LineUnsafe(Exception):
    """A line (or the way to it) that no checked move reaches: it is left out."""

    def __init__(self, index: int, why: str) -> None:
        super().__init__(why)
        self.index = index


def _safe_lines(before: list[Point], pts: list[Point], here: Waypoint, plan: ScanPlan,
                machine: MachineLimits, zones: list
                ) -> tuple[list[Point], dict[int, list[Waypoint]], list[str]]:
    """The lines of pts (after the points `before`) whose every move passes the checks, the
    rest left out with the reason (one line each); numbered on from `before`'s lines."""
    skipped: list[str] = []
    n_first = len(fly_lines(before))
    while True:
        lines = fly_lines(before + pts)[n_first:]
        try:
            return pts, _check_lines(lines, here, plan, machine, zones, before[0].y), skipped
        except _LineUnsafe as e:
            skipped.append(str(e))
            gone = lines[e.index - n_first].points[0].line
            pts = [p for p in pts if p.line != gone]
            for k, line in enumerate(fly_lines(before + pts)[n_first:]):
                for p in line.points:
                    p.line = n_first + k
            for i, p in enumerate(pts):
                p.index = len(before) + i


def _check_lines(lines: list[FlyLine], here: Waypoint, plan: ScanPlan,
                 machine: MachineLimits, zones: list, front_y: float
                 ) -> dict[int, list[Waypoint]]:
    """Check every move of the lines, from `here` (where the stage stands before the first
    of them, which FlyRun starts with a move of its own); the ways around the object by line
    index (an empty list: a move of its own, not joined to the line before). Raises
    UnsafeMove with the one-line reason. front_y: the first look's front plane, outside the
    bounding cylinder."""
    prev: FlyLine | None = None
    via: dict[int, list[Waypoint]] = {}
    for line in lines:
        try:
            here = _check_line(line, prev, here, plan, machine, zones, front_y, via)
        except UnsafeMove as e:
            raise _LineUnsafe(line.index, str(e)) from None
        prev = line
    return via


def _check_line(line: FlyLine, prev: FlyLine | None, here: Waypoint, plan: ScanPlan,
                machine: MachineLimits, zones: list, front_y: float,
                via: dict[int, list[Waypoint]]) -> Waypoint:
    """Check one line and the way to it from `here` (joined to prev where it may be, else a
    move of its own, around the object if need be, entered in via); its run-out end."""
    targets, labels = _line_targets(line, plan, machine)
    # run on from the previous line's end where the geometry allows (FlyRun does the
    # same), else a move of its own; both checked, and the line itself from its run-up
    # start (a measurement taken again goes back along it)
    check_moves(targets[1:], labels[1:], targets[0], machine, zones)
    if joins_previous(prev, line, plan, machine):
        joined, jl = _line_targets(line, plan, machine, start=here)
        try:
            check_moves(joined[1:], jl[1:], here, machine, zones)
            return targets[-1]
        except UnsafeMove:
            pass
    start = targets[0]
    try:
        check_moves([start], [f"the way to line {line.index}"], here, machine, zones)
    except UnsafeMove:  # back out to the front plane, across, and in again
        way = [(here[0], front_y, here[2], here[3]), (start[0], front_y, start[2],
                                                        start[3])]
        check_moves(way + [start], [f"the way back from line {line.index - 1}",
                                    f"the way across to line {line.index}",
                                    f"the way in to line {line.index}"], here, machine,
                    zones)
        via[line.index] = way
    via.setdefault(line.index, [])  # a move of its own: not joined
    return targets[-1]


def plan_holes(writer: ScanWriter, n_before: int, auto: AutoPlan, look: list[Point],
               plan: ScanPlan, calibration: dict, machine: MachineLimits,
               turntable: KeepOut) -> tuple[list[Point], dict[int, list[Waypoint]], float]:
    """The lines scanned again for the holes the first look and the follow lines (the
    file's lines before n_before) left in the outline, per modality of the plan (a place
    with OA points and no US echo is a hole of a "both" plan): at new table angles that
    see them (auto.hole_lines, within plan.rescan_budget_s), checked like the follow lines.
    Returns their points, their ways around the object and the share of closed cells that
    were holes."""
    v, n, X_R = (np.asarray(calibration[k], float) for k in ("v", "n", "X_R"))
    outline = auto.outline
    closed = outline.closed()
    i, j = np.nonzero(np.isfinite(outline.filled_r_mm()))  # surface_points' order
    ref = outline.surface_points()
    per_mod = []  # a hole of either: OA points do not cover a US hole
    for m in plan_modalities(plan):
        mask = np.zeros_like(closed)
        mask[i, j] = ~covered_mask(ref, stored_points(writer, n_before, calibration, (m,)),
                                   AUTO_SPACING_MM)
        per_mod.append((mask, plan.max_incidence_deg if m == "oa" else
                        min(plan.max_incidence_deg, US_MAX_INCIDENCE_DEG)))
    holes = np.logical_or.reduce([mask for mask, _ in per_mod])
    share = float(holes.sum() / max(closed.sum(), 1))
    speed, accel = fly_speed(plan, machine)
    a_ax, z_ax = machine.axis("A"), machine.axis("Z")
    turn_s = move_s(HOLE_TURN_DEG, machine.max_feedrate[a_ax], machine.max_acceleration[a_ax])
    rise_s = move_s(plan.first_look_step_mm, machine.max_feedrate[z_ax],
                    machine.max_acceleration[z_ax])
    # a line and its way there, about, each at its own table angle and row: 4.4 s on the
    # bench's bottle, whose hole lines took 3.2-6.2 s (2.6 s without the turn and rise)
    line_s = (2 * plan.radius_mm + 2 * (ramp_mm(speed, accel, plan.step_mm) + TRANSITION_MM)
              ) / speed + 1.0 + turn_s + rise_s
    pairs = hole_lines(outline, per_mod, auto.angles_deg, plan.levels_mm, plan.standoff_mm,
                       v, n, line_s, plan.rescan_budget_s, AUTO_SPACING_MM)
    pts: list[Point] = []
    for k, (a, li, height_mm) in enumerate(pairs):
        one = replace(plan, levels_mm=[height_mm])
        for p in follow_points(one, outline, [a], v, n, X_R, speed, accel,
                               machine.junction_deviation_mm, n_before + len(fly_lines(pts))):
            p.level, p.angle_index = li, len(auto.angles_deg) + k
            pts.append(p)
    for q, p in enumerate(pts):
        p.index = len(look) + len(auto.points) + q
    if not pts:
        return [], {}, share
    here = _line_targets(fly_lines(look + auto.points)[-1], plan, machine)[0][-1]
    pts, via, skipped = _safe_lines(look + auto.points, pts, here, plan, machine,
                                    [follow_keep_out(plan, outline, X_R, n), turntable])
    auto.skipped += skipped
    return pts, via, share


HOLE_TURN_DEG = 90.0  # the table's turn to a hole line, on average (its angles are chosen
# by what they see, not in order: 0-180 deg)


def move_s(distance: float, feed: float, accel: float) -> float:
    """Seconds of a move of `distance` (mm or deg) from rest to rest at most at `feed` (per
    s) with `accel` (per s^2): a trapezoid, or a triangle if it never reaches the feed."""
    if distance <= 0:
        return 0.0
    if distance >= feed * feed / accel:
        return distance / feed + feed / accel
    return 2.0 * (distance / accel) ** 0.5


def plan_modalities(plan: ScanPlan) -> tuple[str, ...]:
    """The modalities a plan's scan is for ("both": OA and US)."""
    return ("oa", "us") if plan.modality == "both" else (plan.modality,)


def stored_points(writer: ScanWriter, n_lines: float, calibration: dict,
                   modalities: tuple[str, ...] = ("oa", "us")) -> np.ndarray:
    """Object-frame points (mm) of the modalities, from the file's lines before n_lines."""
    d, m = writer.data, writer.n_done
    sel = d["point_index"][:m] < n_lines
    v, nn, X_R = (np.asarray(calibration[k], float) for k in ("v", "n", "X_R"))
    S, th = d["stage_position_mm"][:m][sel], d["theta_deg"][:m][sel]
    out = [np.empty((0, 3))]
    for mod in modalities:
        dist = d[f"distance_{mod}_mm"][:m][sel]
        ok = np.isfinite(dist)
        out.append(object_points(stage_points(S[ok], dist[ok], v), th[ok], nn, X_R))
    return np.vstack(out)


def plan_far_look(writer: ScanWriter, look: list[Point], plan: ScanPlan, calibration: dict,
                  machine: MachineLimits, turntable: KeepOut
                  ) -> tuple[list[Point], dict[int, list[Waypoint]], ScanPlan | None]:
    """The far look (first_look.far_look_levels) after the first look's lines in the file: its
    points (lines and indices numbered on), their ways by line index and its plan; every
    move of it, from where the first look ends, checked against the bounding cylinder and
    the turntable (raises UnsafeMove). Nothing if the outline needs none."""
    v, n, X_R = (np.asarray(calibration[k], float) for k in ("v", "n", "X_R"))
    n_look = len(fly_lines(look))
    levels = far_look_levels(plan, first_look_outline(writer, n_look, plan, calibration), v)
    if not levels:
        return [], {}, None
    far = first_look_points(plan, v, X_R, n, levels, first_line=n_look,
                            first_index=len(look))
    fplan = far_look_plan(plan, levels)
    zones = [keep_outs(plan, n, X_R)[0], turntable]
    end = _line_targets(fly_lines(look)[-1], first_look_plan(plan), machine)[0][-1]
    here = (end[0], far[0].y, end[2], end[3])  # FlyRun's approach: along Y first
    check_moves([here], ["the approach to the far look"], end, machine, zones)
    try:
        via = _check_lines(fly_lines(look + far)[n_look:], here, fplan, machine, zones,
                           far[0].y)
    except _LineUnsafe as e:
        raise UnsafeMove(str(e)) from None
    return far, via, fplan


def run_auto_scan(stage: Stage, sensor: StreamSensor, plan: ScanPlan, look: list[Point],
                  writer: ScanWriter, ranger: PointRanger, machine: MachineLimits,
                  calibration: dict, turntable: KeepOut, progress: Progress | None = None
                  ) -> tuple[ScanStats, AutoPlan]:
    """The first look (if not in the file yet), the far look where it left the outline
    open, then the follow lines after the last line stored. Returns this run's statistics
    (all parts) and the follow plan."""
    stats = run_fly_scan(stage, sensor, first_look_plan(plan), look, writer, ranger, machine,
                         progress)
    far, far_via, fplan = plan_far_look(writer, look, plan, calibration, machine, turntable)
    if fplan is not None:  # from farther out: its own depth gate
        far_ranger = PointRanger(ranger.setup, ranger.n, ranger.tick_hz, ranger.modality,
                                 fplan.depth_gate_mm(), ranger.pair_mm,
                                 answers_both=ranger.answers_both)
        _add(stats, run_fly_scan(stage, sensor, fplan, look + far, writer, far_ranger,
                                 machine, progress, via=far_via))
    auto = plan_follow(writer, look + far, plan, calibration, machine, turntable)
    auto.far_points = far
    look = look + far
    _add(stats, run_fly_scan(stage, sensor, plan, look + auto.points, writer, ranger,
                             machine, progress, via=auto.via))
    n_before = len(fly_lines(look + auto.points))
    holes, via, auto.hole_share = plan_holes(writer, n_before, auto, look, plan, calibration,
                                             machine, turntable)
    auto.hole_points = holes
    if holes:
        _add(stats, run_fly_scan(stage, sensor, plan, look + auto.points + holes, writer,
                                 ranger, machine, progress, via={**auto.via, **via}))
    return stats, auto


def _add(stats: ScanStats, more: ScanStats) -> None:
    """Add a later part's statistics to the run's."""
    stats.stored += more.stored
    stats.lost += more.lost
    stats.skipped += more.skipped
    stats.store_s += more.store_s
    stats.wall_s += more.wall_s
    for k in stats.phase_s:
        stats.phase_s[k] += more.phase_s[k]
    stats.clock = more.clock or stats.clock


def outline_coverage(writer: ScanWriter, auto: AutoPlan, calibration: dict,
                     spacing_mm: float) -> dict[str, float]:
    """Per modality, the share of the closed outline's surface with a stored point within
    spacing_mm (what `dmdsm scan` reports when no truth is known)."""
    ref = auto.outline.surface_points()
    return {m: round(float(coverage(ref, stored_points(writer, np.inf, calibration, (m,)),
                                    spacing_mm)), 4) for m in ("oa", "us")}
