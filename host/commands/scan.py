"""`dmdsm scan`: run a scan plan into the database (scan.session.run_plan), from the terminal."""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

from ..calibration.result import load_calibration
from ..files import one_line
from ..links.config import load_config, resolve_port
from ..links.sensor import SensorClient
from ..links.stage import StageClient
from ..ranging.calibrate import RangingSetup
from ..scan.plan import MODES, PlanError, load_plan
from ..scan.scanfile import ScanFileError, ScanWriter
from ..scan.session import checked_points, finished_scan, run_plan
from .errors import CliError
from .options import add_ports

log = logging.getLogger("dmdsm.scan")


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register `scan`."""
    p = sub.add_parser("scan", help="scan an object into the database (step and shoot, or fly)")
    add_ports(p)
    p.add_argument("--calibration", type=Path, default=Path("calibration.toml"),
                   help="scanner calibration from `dmdsm calibrate` (default ./calibration.toml)")
    p.add_argument("--ranging", type=Path, default=Path("ranging.json"),
                   help="ranging calibration from `dmdsm calibrate-range` (default ./ranging.json)")
    p.add_argument("--plan", type=Path, required=True, help="scan plan TOML")
    p.add_argument("--db", type=Path,
                   help="database folder (created if missing; DB/scans/ID.h5 per scan)")
    p.add_argument("-o", dest="db", type=Path, help=argparse.SUPPRESS)  # round 1's name
    p.add_argument("--object", dest="object_id", help="override [sample] object_id")
    p.add_argument("--material", help="override [sample] material")
    p.add_argument("--scan-id", help="name of the scan (default: object id + plan hash)")
    p.add_argument("--mode", choices=MODES,
                   help="override [scan] mode: step and shoot, fly (each line one "
                        "constant-speed move, shots placed by counted steps), auto (a "
                        "first look, then lines that follow the outline) or sweep (the "
                        "table turning under the sensor, a ring at each height; docs/scanning.md)")
    p.add_argument("--no-home", action="store_true", help="the stage is already homed")
    p.add_argument("--no-model", action="store_true",
                   help="auto: do not build the object's 3D model after the scan")
    p.add_argument("--classifier", type=Path,
                   help="auto: a `dmdsm classify train` model for the 3D model's materials")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.set_defaults(func=cmd_scan)


def cmd_scan(args: argparse.Namespace) -> int:
    """Check the whole plan, then measure its points; resumable; Ctrl-C stops the stage."""
    from tqdm import tqdm

    if args.db is None:
        raise CliError("give --db DIR: the scan database folder (created if missing)")
    try:
        plan = load_plan(args.plan, object_id=args.object_id, material=args.material,
                         mode=args.mode)
    except PlanError as e:
        raise CliError(str(e)) from None
    cal, cal_text = load_calibration(args.calibration)
    try:
        setup = RangingSetup.load(args.ranging)
    except ValueError as e:
        raise CliError(f"{e}; run `dmdsm calibrate-range` first") from None
    try:  # everything that needs no board is checked before a port is opened
        if args.db.exists() and not args.db.is_dir():
            raise CliError(f"{args.db} is a file, not a scan database folder: name a folder "
                           f"(a new one is created)")
        checked_points(plan, cal)
        done = finished_scan(plan, cal_text, setup, args.db, args.scan_id)
    except ScanFileError as e:
        raise CliError(str(e)) from None
    if done is not None:
        print(f"scan {done.scan_id} is complete ({done.points} points) in {done.path}; nothing "
              f"to do (--scan-id NAME starts another)")
        return 0
    cfg = load_config(args.config)
    state: dict = {}

    def on_start(writer: ScanWriter, planned: int) -> None:
        state["writer"], state["planned"] = writer, planned
        if writer.n_done:
            print(f"resuming {Path(writer.path).stem}: {writer.n_done} of {planned} points done")
        state["bar"] = tqdm(total=planned, initial=writer.n_done, unit="pt", disable=args.json)

    def progress(done: int, total: int, timing: dict) -> None:
        if total != state["planned"]:  # an auto scan plans its lines after its first look
            state["planned"] = state["bar"].total = total
        state["bar"].update(done - state["bar"].n)
        log.debug("point %d: %s", done - 1,
                  " ".join(f"{k}={v * 1e3:.1f}ms" for k, v in timing.items()))

    sensor = SensorClient(resolve_port("sensor", args.sensor, cfg))
    try:
        with StageClient(resolve_port("stage", args.stage, cfg)) as st:
            run = run_plan(sensor, st, plan, calibration=cal, calibration_toml=cal_text,
                           setup=setup, db=args.db,
                           scan_id=args.scan_id, home=not args.no_home, progress=progress,
                           on_start=on_start)
    except ScanFileError as e:
        raise CliError(str(e)) from None
    except BaseException as e:
        if "bar" in state:  # end the bar's line first: the note goes on a line of its own
            state["bar"].close()
        w = state.get("writer")
        if w is not None:  # a plan the scan showed wrong: running it again cannot help
            then = ("the plan, changed as below, starts a new scan" if isinstance(e, PlanError)
                    else "run the same command to continue")
            print(f"scan {Path(w.path).stem} stopped after {w.n_done} of {state['planned']} "
                  f"points; they are saved in {w.path}; {then}", file=sys.stderr)
        raise
    finally:
        if "bar" in state:
            state["bar"].close()
        sensor.close()
    if run.status == "already complete":
        print(f"scan {run.scan_id} is complete ({run.points} points) in {run.path}; nothing "
              f"to do (--scan-id NAME starts another)")
        return 0
    summary = run.summary()
    if run.stats.skipped:  # the plan counted on every shot: say why the points are fewer
        print(f"scan {run.scan_id}: the sensor board skipped {run.stats.skipped} laser shots, "
              f"every waveform slot waiting for the link (the host did not read in time, or "
              f"the link is slower than the plan's waveforms: a higher average); the points "
              f"are fewer than planned, none misplaced", file=sys.stderr)
    if args.json:
        print(json.dumps(summary))
    else:
        per = run.stats.per_point_ms()
        print(f"scan {run.scan_id}: {run.points} points in {run.path}; "
              f"{summary['points_per_s']} points/s; per point "
              + ", ".join(f"{k} {v:.1f} ms" for k, v in per.items()))
        if run.auto:
            a = run.auto
            print(f"auto: {a['first_look_lines']} first-look lines, {a['lines']} follow lines "
                  f"at {len(a['angles_deg'])} table angles; coverage of the measured outline "
                  f"at {a['coverage_spacing_mm']:g} mm: "
                  + ", ".join(f"{m.upper()} {100 * c:.1f} %" for m, c in a["coverage"].items())
                  + f"; the first look measured {100 * a['outline_closed_share']:.0f} % of the "
                  f"outline (the rest kept the bounding cylinder and is not counted)")
            for why in a["lines_left_out"]:  # said, not hidden
                print(f"auto: a line was left out: {why}")
            for note in a["notes"]:
                print(f"auto: note: {note}")
        elif run.coverage:  # a sweep: its band, measured by its own points
            c = run.coverage
            lo, hi = c["band_mm"]
            print(f"sweep: coverage of the band it swept (heights {lo:.1f}-{hi:.1f} mm) at "
                  f"{c['spacing_mm']:g} mm: OA {100 * c['oa']:.1f} %, US {100 * c['us']:.1f} %;"
                  f" it found the surface in {100 * c['directions']:.0f} % of the directions "
                  f"about the axis (the rest: no echo, counted as not covered)")
    if run.auto and not args.no_model:
        _build_model(args.db, plan.object_id, args.classifier, args.json)
    return 0


def _build_model(db: Path, object_id: str, classifier: Path | None, as_json: bool) -> None:
    """After an auto scan: the object's 3D model from all its scans (a new version). A model
    that cannot be built is said in one line; the scan stands."""
    from ..model.build import build_object_model
    from ..model.store import ModelError, write_model

    try:
        model = build_object_model(db, object_id, classifier=classifier)
        path = write_model(db, model)
    except (ModelError, ValueError) as e:
        print(f"dmdsm: the scan is saved, but no 3D model was built: {one_line(str(e), 300)}; "
              f"`dmdsm model build {object_id} --db {db}` tries again", file=sys.stderr)
        return
    s = model.summary
    if not as_json:
        print(f"model: {object_id} v{model.version}, {s['vertices']} vertices "
              f"({100 * s['supported_share']:.1f} % supported), {path}")
