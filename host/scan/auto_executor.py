"""Auto scans' run: the first look's fly lines, the outline from what they stored, then the
follow lines planned from it, checked against the outline's keep-out before they move, and
their coverage of that outline; resumed line by line like any fly scan.

The outline comes only from the first look's lines in the file, so a resumed scan plans the
same follow lines again and goes on after the last one stored.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dmdsm.marlin_patch import MachineLimits

from ..links.interfaces import Stage, StreamSensor
from ..links.safety import KeepOut, UnsafeMove
from ..ranging.point import PointRanger
from .auto import choose_angles, first_look_plan, follow_points
from .common import Progress, ScanStats
from .coverage import coverage
from .fly_executor import (
    FlyLine,
    fly_lines,
    fly_speed,
    joins_previous,
    line_path,
    run_fly_scan,
)
from .outline import Outline, OutlineKeepOut, check_moves, outline_from_points
from .plan import Point, ScanPlan
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


def first_look_outline(writer: ScanWriter, n_look_lines: int, plan: ScanPlan,
                       calibration: dict) -> Outline:
    """The outline from the first look's stored lines (point_index < n_look_lines), both
    modalities' points in the object frame."""
    d = writer.data
    n = writer.n_done
    idx = d["point_index"][:n]
    sel = idx < n_look_lines
    S = d["stage_position_mm"][:n][sel]
    th = d["theta_deg"][:n][sel]
    v, nn, X_R = (np.asarray(calibration[k], float) for k in ("v", "n", "X_R"))
    P = []
    for m in ("oa", "us"):
        dist = d[f"distance_{m}_mm"][:n][sel]
        ok = np.isfinite(dist)
        if ok.any():
            P.append(object_points(stage_points(S[ok], dist[ok], v), th[ok], nn, X_R))
    P = np.vstack(P) if P else np.empty((0, 3))
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
    UnsafeMove if none is safe, ValueError if the first look saw nothing."""
    v, n, X_R = (np.asarray(calibration[k], float) for k in ("v", "n", "X_R"))
    n_look = len(fly_lines(look))
    outline = first_look_outline(writer, n_look, plan, calibration)
    if not outline.closed().any():
        raise ValueError("the first look saw no surface: is the object on the table, within "
                         "radius_mm and height_mm of the plan?")
    angles, share = choose_angles(outline, plan.angles_deg, v, n, plan.max_incidence_deg,
                                  plan.max_angles)
    speed, accel = fly_speed(plan, machine)
    pts = follow_points(plan, outline, angles, v, n, X_R, speed, accel,
                        machine.junction_deviation_mm, n_look)
    for i, p in enumerate(pts):
        p.index = len(look) + i
    zones = [OutlineKeepOut(outline, X_R, n), turntable]
    front_y = look[0].y  # the first look's front plane: outside the bounding cylinder
    all_lines = fly_lines(look + pts)
    here = _line_targets(all_lines[n_look - 1], first_look_plan(plan), machine)[0][-1]
    prev: FlyLine | None = None  # the follow lines' run (FlyRun) starts with a move
    via: dict[int, list[Waypoint]] = {}
    for line in all_lines[n_look:]:
        targets, labels = _line_targets(line, plan, machine)
        # run on from the previous line's end where the geometry allows (FlyRun does the
        # same), else a move of its own; both checked, and the line itself from its run-up
        # start (a measurement taken again goes back along it)
        check_moves(targets[1:], labels[1:], targets[0], machine, zones)
        if joins_previous(prev, line, plan, machine):
            joined, jl = _line_targets(line, plan, machine, start=here)
            try:
                check_moves(joined[1:], jl[1:], here, machine, zones)
                here, prev = targets[-1], line
                continue
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
        here, prev = targets[-1], line
    return AutoPlan(outline, angles, share, pts, via)


def run_auto_scan(stage: Stage, sensor: StreamSensor, plan: ScanPlan, look: list[Point],
                  writer: ScanWriter, ranger: PointRanger, machine: MachineLimits,
                  calibration: dict, turntable: KeepOut, progress: Progress | None = None
                  ) -> tuple[ScanStats, AutoPlan]:
    """The first look (if not in the file yet), then the follow lines after the last line
    stored. Returns this run's statistics (both parts) and the follow plan."""
    stats = run_fly_scan(stage, sensor, first_look_plan(plan), look, writer, ranger, machine,
                         progress)
    auto = plan_follow(writer, look, plan, calibration, machine, turntable)
    more = run_fly_scan(stage, sensor, plan, look + auto.points, writer, ranger, machine,
                        progress, via=auto.via)
    stats.stored += more.stored
    stats.lost += more.lost
    stats.store_s += more.store_s
    stats.wall_s += more.wall_s
    for k in stats.phase_s:
        stats.phase_s[k] += more.phase_s[k]
    stats.clock = more.clock or stats.clock
    return stats, auto


def outline_coverage(writer: ScanWriter, auto: AutoPlan, calibration: dict,
                     spacing_mm: float) -> dict[str, float]:
    """Per modality, the share of the closed outline's surface with a stored point within
    spacing_mm (what `dmdsm scan` reports when no truth is known)."""
    d, n = writer.data, writer.n_done
    v, nn, X_R = (np.asarray(calibration[k], float) for k in ("v", "n", "X_R"))
    S, th = d["stage_position_mm"][:n], d["theta_deg"][:n]
    ref = auto.outline.surface_points()
    out = {}
    for m in ("oa", "us"):
        dist = d[f"distance_{m}_mm"][:n]
        ok = np.isfinite(dist)
        P = object_points(stage_points(S[ok], dist[ok], v), th[ok], nn, X_R)
        out[m] = round(float(coverage(ref, P, spacing_mm)), 4)
    return out
