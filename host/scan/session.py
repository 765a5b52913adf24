"""A scan run into a database: check the plan, open or resume its file, measure, catalogue.

`run_plan` is what `dmdsm scan` does without the terminal: the plan is checked against the
machine and its keep-outs before anything moves, a scan of the same plan, calibration and
ranging resumes where it stopped, and every finished point is on disk and catalogued. Ctrl-C
or a lost board closes the file as `interrupted`; calling it again continues.
"""

from __future__ import annotations

import hashlib
import json
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dmdsm.marlin_patch import MachineLimits, load_machine

from ..files import file_hash
from ..links.interfaces import Sensor, Stage
from ..links.stage import StageStopped
from ..links.transport import LinkError
from ..ranging.calibrate import RangingSetup
from ..version import __version__
from .auto_executor import outline_coverage, run_auto_scan, stored_points
from .catalogue import connect, record
from .common import Progress, ScanStats
from .executor import run_scan
from .first_look import (
    cylinder_window,
    first_look_plan,
    first_look_points,
    set_cylinder_windows,
)
from .fly_executor import fly_lines, line_ends, run_fly_scan
from .plan import (
    AUTO_SPACING_MM,
    Point,
    ScanPlan,
    check_path,
    check_plan,
    expand,
    keep_outs,
    point_ranger,
)
from .scanfile import ScanFileError, ScanWriter, read_scan
from .sweep import Turn, beam_heights_mm, sweep_coverage, sweep_points, sweep_turns
from .sweep_executor import run_sweep_scan


@dataclass
class ScanRun:
    """What a run did: its id and file, points on disk, and this run's statistics."""

    scan_id: str
    path: Path
    points: int
    planned: int
    status: str  # "complete", "already complete" or "interrupted"
    stats: ScanStats = field(default_factory=ScanStats)
    auto: dict = field(default_factory=dict)  # an auto scan: angles, lines, coverage
    coverage: dict = field(default_factory=dict)  # an auto or sweep scan's, per modality

    def summary(self) -> dict:
        """The JSON summary `dmdsm scan --json` prints (times in s and ms, rate in points/s)."""
        s = self.stats
        return {"scan_id": self.scan_id, "file": str(self.path), "points": self.points,
                "stored_now": s.stored, "lost_waveforms": s.lost,
                "skipped_shots": s.skipped,
                "wall_s": round(s.wall_s, 2),
                "points_per_s": round(s.stored / s.wall_s, 3) if s.wall_s else 0,
                "ms_per_point": {k: round(v, 2) for k, v in s.per_point_ms().items()},
                **({"clock_sync": s.clock} if s.clock else {}),
                **({"auto": self.auto} if self.auto else {}),
                **({"coverage": self.coverage} if self.coverage else {})}


def scan_identity(plan: ScanPlan, calibration_toml: str, setup: RangingSetup) -> str:
    """sha256 (hex) of what makes two runs the same scan: plan, calibration and ranging."""
    return hashlib.sha256((plan.hash() + calibration_toml + setup.to_json()).encode()).hexdigest()


def checked_points(plan: ScanPlan, calibration: dict) -> list[Point]:
    """The plan's stage points, every move between them checked against the machine's
    envelope and the keep-outs around the object and turntable; raises UnsafeMove. Needs no
    board: call it before opening a port."""
    v, n, X_R = (np.asarray(calibration[k], float) for k in ("v", "n", "X_R"))
    points = expand(plan, v, X_R)
    machine, zones = load_machine(), keep_outs(plan, n, X_R)
    if plan.mode == "auto":  # the first look; the rest is checked once it has been seen
        points = first_look_points(plan, v, X_R, n)
        targets, labels = fly_path(points, first_look_plan(plan), machine)
        check_path(targets, labels, None, machine, zones)
        # the follow levels, as far as they are known before the first look: clear of the
        # turntable in front of the object
        y = points[0].y
        check_path([np.array([X_R[0], y, X_R[2] + h]) for h in plan.levels_mm],
                   [f"level {h:g} mm" for h in plan.levels_mm], None, machine, zones)
    elif plan.mode == "fly":  # the whole swept path, run-ups and run-outs included
        targets, labels = fly_path(points, plan, machine)
        check_path(targets, labels, None, machine, zones)
    elif plan.mode == "sweep":  # the rings: straight in X, Y, Z from turn to turn
        turns = sweep_turns(plan, v, X_R, n)
        points = sweep_points(plan, turns, machine.max_feedrate[machine.axis("A")])
        targets, labels = sweep_path(turns)
        check_path(targets, labels, None, machine, zones)
    else:
        check_plan(points, None, machine, zones)
    return points


def fly_path(points: list[Point], plan: ScanPlan, machine: MachineLimits
             ) -> tuple[list[np.ndarray], list[str]]:
    """Every point a fly scan's stage passes through in a straight move (run-up start, then
    run-out end, line by line), with labels for the refusal message."""
    targets, labels = [], []
    for line in fly_lines(points):
        p = line.points[0]
        xs, xe = line_ends(line, plan, machine)
        targets += [np.array([xs, p.y, p.z]), np.array([xe, p.y, p.z])]
        labels += [f"line {line.index}'s run-up start", f"line {line.index}'s run-out end"]
    return targets, labels


def sweep_path(turns: list[Turn]) -> tuple[list[np.ndarray], list[str]]:
    """The points a sweep's stage passes through in straight moves (X, Y, Z: the table's turn
    moves no point of the stage), with labels for the refusal message."""
    targets = [np.array([turns[0].x, turns[0].y, turns[0].z0])]
    labels = ["turn 0's start"]
    for t in turns:
        if not np.array_equal(targets[-1], [t.x, t.y, t.z0]):  # up to a ring, or across
            targets.append(np.array([t.x, t.y, t.z0]))
            labels.append(f"turn {t.index}'s start")
        targets.append(np.array([t.x, t.y, t.z1]))
        labels.append(f"turn {t.index}'s end")
    return targets, labels


SCAN_ID = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,99}")


def scan_path(plan: ScanPlan, calibration_toml: str, setup: RangingSetup, db: Path,
              scan_id: str | None = None) -> tuple[str, Path]:
    """The scan's id (default: object id + the first 8 hex digits of scan_identity) and file,
    always db/scans/<id>.h5: an id that is a path (/, .., absolute) is refused."""
    scan_id = scan_id or f"{plan.object_id}-{scan_identity(plan, calibration_toml, setup)[:8]}"
    if not SCAN_ID.fullmatch(scan_id) or ".." in scan_id:
        raise ScanFileError(f"scan id {scan_id!r} is not a name: use letters, digits, '.', '_' "
                            f"and '-' (at most 100, no '..'); the file goes in {db}/scans/")
    return scan_id, Path(db) / "scans" / f"{scan_id}.h5"


def finished_scan(plan: ScanPlan, calibration_toml: str, setup: RangingSetup, db: Path,
                  scan_id: str | None = None) -> ScanRun | None:
    """The scan of this plan if it is already complete in `db` (nothing left to do), else
    None; raises ScanFileError if its file is not a readable scan. Needs no board."""
    return _complete(*scan_path(plan, calibration_toml, setup, db, scan_id))


def _complete(scan_id: str, path: Path) -> ScanRun | None:
    """The ScanRun of a complete scan file at path, None if absent or unfinished."""
    if not path.exists():
        return None
    done = read_scan(path, waveforms=False)
    if done.entry.get("status") != "complete":
        return None
    return ScanRun(scan_id, path, done.n_points, done.n_points, "already complete")


def run_plan(sensor: Sensor, stage: Stage, plan: ScanPlan, *, calibration: dict,
             setup: RangingSetup, db: Path, calibration_toml: str | None = None,
             scan_id: str | None = None, home: bool = True,
             progress: Progress | None = None,
             on_start: Callable[[ScanWriter, int], None] | None = None) -> ScanRun:
    """Scan `plan` with open clients into the database folder `db` (created if missing).

    calibration is v, n, X_R from `load_calibration` (calibration_toml: the file's text, kept
    in the scan file; by default written from those three); raises UnsafeMove before any motion if
    a move of the plan leaves the envelope or enters a keep-out, ScanFileError if the file
    cannot be resumed. The stage should be an open StageClient (its context manager
    quick-stops it on Ctrl-C); the sensor is disarmed on Ctrl-C here."""
    points = checked_points(plan, calibration)  # every move, before any motion
    if calibration_toml is None:
        calibration_toml = "[calibration]\n" + "".join(
            f"{k} = {np.asarray(calibration[k], float).tolist()}\n" for k in ("v", "n", "X_R"))
    n, X_R = (np.asarray(calibration[k], float) for k in ("n", "X_R"))
    machine, keep = load_machine(), keep_outs(plan, n, X_R)
    run_hash = scan_identity(plan, calibration_toml, setup)
    scan_id, path = scan_path(plan, calibration_toml, setup, db,
                              scan_id or f"{plan.object_id}-{run_hash[:8]}")
    done = _complete(scan_id, path)
    if done is not None:
        return done
    if home:
        stage.home()
    here = stage.where()
    here_xyz = np.array([here["X"], here["Y"], here["Z"]])
    v = np.asarray(calibration["v"], float)
    if plan.mode in ("step", "fly") and plan.modality != "both":
        # a one-modality plan reads every lone pulse as its own modality: only the window
        # tells it from the other's (a steel can's paper label, met 40 deg off head on
        # ~18 mm away, gives an OA pulse read as an echo in mid-air at ~9 mm). A "both"
        # plan (the paper's block) keeps its readings: it reads a lone pulse by continuity
        set_cylinder_windows(points, v, n, X_R, plan.radius_mm, plan.height_mm)
    turns = sweep_turns(plan, v, X_R, n) if plan.mode == "sweep" else []
    if plan.mode == "sweep":
        targets, labels = sweep_path(turns)
        check_path(targets[:1], labels[:1], here_xyz, machine, keep)
    elif plan.mode != "step":
        targets, labels = fly_path(points[:1], plan, machine)
        check_path(targets[:1], labels[:1], here_xyz, machine, keep)
    else:
        check_plan(points[:1], here_xyz, machine, keep)
    sc = sensor.configure(n_samples=plan.samples, n_average=plan.average, pretrigger=0,
                          trigger_timeout_ms=2000)
    ident = dict(sensor.identity.fields)
    ident["spec_hash"] = f"{ident['spec_hash']:016x}"
    sensor_attrs = {**ident, "port": sensor.port_name,
                    **{f"config_{k}": val for k, val in sc.items()}}
    connect(Path(db), create=True).close()  # only now: a refused scan leaves no folder
    if path.exists():
        writer = ScanWriter.resume(path, run_hash)
    else:
        writer = ScanWriter.create(
            path, scan_id=scan_id, plan_text=plan.to_toml(), plan_hash=run_hash,
            n_samples=sc["n_samples"], sensor=sensor_attrs, calibration=calibration,
            calibration_toml=calibration_toml, ranging_json=setup.to_json(),
            sample={"name": plan.object_id, "material": plan.material, "notes": plan.notes,
                    "radius_mm": plan.radius_mm, "height_mm": plan.height_mm},
            program_version=__version__)
    run = ScanRun(scan_id, path, writer.n_done, len(points), "interrupted")
    try:
        record(Path(db), scan_id, n_planned=len(points))
        if on_start is not None:
            on_start(writer, len(points))
        ranger = point_ranger(plan, setup, sc["n_samples"], sensor.identity.tick_hz)
        if plan.mode == "auto":
            run.stats, auto = run_auto_scan(stage, sensor, plan, points, writer, ranger,
                                            machine, calibration, keep[1], progress)
            run.planned = len(points) + len(auto.far_points) + len(auto.points) + len(
                auto.hole_points)
            n_far = len(fly_lines(auto.far_points))
            run.auto = {"angles_deg": auto.angles_deg, "lines": len(fly_lines(auto.points)),
                        "first_look_lines": len(fly_lines(points)) + n_far,
                        "far_look_lines": n_far,
                        "outline_seen_share": round(auto.seen_share, 4),
                        "outline_closed_share": round(float(auto.outline.closed().mean()), 4),
                        "holes_after_follow": round(auto.hole_share, 4),
                        "lines_left_out": auto.skipped, "notes": auto.notes,
                        "hole_lines": len(fly_lines(auto.hole_points)),
                        "coverage": outline_coverage(writer, auto, calibration,
                                                     AUTO_SPACING_MM),
                        "coverage_spacing_mm": AUTO_SPACING_MM}
            run.coverage = {**run.auto["coverage"], "spacing_mm": AUTO_SPACING_MM}
        elif plan.mode == "fly":
            run.stats = run_fly_scan(stage, sensor, plan, points, writer, ranger, machine,
                                     progress)
        elif plan.mode == "sweep":  # each shot's window, at its own height
            def window_of(S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
                return cylinder_window(S, v, n, X_R, plan.radius_mm, plan.height_mm)
            run.stats = run_sweep_scan(stage, sensor, plan, turns, len(points), writer,
                                       ranger, machine, progress, window_of)
            run.coverage = swept_coverage(writer, plan, turns, calibration)
        else:
            run.stats = run_scan(stage, sensor, plan, points, writer, ranger, progress)
        stage.move(x=here["X"], y=points[0].y, z=here["Z"], feed_mm_min=plan.feed_mm_min)
        stage.wait()
        run.status = "complete"
    except (KeyboardInterrupt, StageStopped):  # Ctrl-C, or `dmdsm stage stop` elsewhere
        try:
            sensor.disarm()  # the stage is quick-stopped by its context manager
        except LinkError:
            pass
        raise
    finally:
        run.points = writer.n_done
        writer.close(run.status, {"coverage": json.dumps(run.coverage)} if run.coverage
                     else None)
        record(Path(db), scan_id, n_planned=len(points),
               content_hash=file_hash(path) if run.status == "complete" else "")
    return run


def swept_coverage(writer: ScanWriter, plan: ScanPlan, turns: list[Turn], calibration: dict
                   ) -> dict:
    """A sweep's coverage of its band (sweep.sweep_coverage) from every point in its file,
    at the auto plans' spacing; with the band (object-frame heights, mm): from the lowest
    ring's bottom to the highest one's top (each pitch / 2 about its Z), where the beam
    crosses them at every radius."""
    v, n, X_R = (np.asarray(calibration[k], float) for k in ("v", "n", "X_R"))
    z = [h for t in turns
         for h in (min(t.z0, t.z1) - t.pitch / 2, max(t.z0, t.z1) + t.pitch / 2)]
    x, y = turns[0].x, turns[0].y  # the first pass's (the beam through the axis: offset 0)
    first = beam_heights_mm(np.array([x, y, min(z)]), v, n, X_R, plan.radius_mm)
    last = beam_heights_mm(np.array([x, y, max(z)]), v, n, X_R, plan.radius_mm)
    band = (max(first), min(last))  # crossed at every radius (v dips or climbs: either end)
    cov = sweep_coverage({m: stored_points(writer, np.inf, calibration, (m,))
                          for m in ("oa", "us")}, plan.radius_mm, plan.height_mm, band,
                         AUTO_SPACING_MM)
    return {**cov, "spacing_mm": AUTO_SPACING_MM, "band_mm": [round(b, 2) for b in band]}
