"""`dmdsm scan`: run a scan plan into the database, resuming an unfinished scan of the same plan."""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import sys
import tomllib
from pathlib import Path

import numpy as np

from . import __version__
from .catalogue import connect, file_hash, record
from .range_cal import RangingSetup
from .safety import UnsafeMove
from .scan import PointRanger, run_scan
from .scan_plan import PlanError, check_plan, expand, keep_outs, load_plan
from .scandb import ScanFileError, ScanWriter, read_scan
from .transport import LinkError

log = logging.getLogger("dmdsm.scan")


def load_calibration(path: Path) -> tuple[dict, str]:
    """v, n, X_R (and stds) from a `dmdsm calibrate` result TOML, and its text."""
    from .cli import CliError

    try:
        text = Path(path).read_text()
        cal = tomllib.loads(text)["calibration"]
        out = {k: [float(x) for x in cal[k]] for k in ("v", "n", "X_R")}
    except OSError as e:
        raise CliError(f"cannot read calibration {path}: {e.strerror}; run `dmdsm "
                       f"calibrate` first") from None
    except (tomllib.TOMLDecodeError, KeyError, TypeError, ValueError) as e:
        raise CliError(f"{path} is not a dmdsm calibration ({e}); run `dmdsm calibrate`") \
            from None
    for k in ("v_std", "n_std", "X_R_std"):
        if k in cal:
            out[k] = [float(x) for x in cal[k]]
    out["source"] = str(path)
    return out, text


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register `scan`."""
    p = sub.add_parser("scan", help="scan an object into the database (step and shoot)")
    p.add_argument("--sensor", help="sensor port (or DMDSM_SENSOR_PORT, dmdsm.toml)")
    p.add_argument("--stage", help="stage port (or DMDSM_STAGE_PORT, dmdsm.toml)")
    p.add_argument("--config", type=Path, default=None)
    p.add_argument("--calibration", type=Path, default=Path("calibration.toml"))
    p.add_argument("--ranging", type=Path, default=Path("ranging.json"))
    p.add_argument("--plan", type=Path, required=True, help="scan plan TOML")
    p.add_argument("-o", "--db", type=Path, required=True, help="database directory")
    p.add_argument("--object", dest="object_id", help="override [sample] object_id")
    p.add_argument("--material", help="override [sample] material")
    p.add_argument("--scan-id", help="name of the scan (default: object id + plan hash)")
    p.add_argument("--no-home", action="store_true", help="the stage is already homed")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.set_defaults(func=cmd_scan)


def cmd_scan(args: argparse.Namespace) -> int:
    """Check the whole plan, then measure its points; resumable; Ctrl-C stops the stage."""
    from tqdm import tqdm

    from dmdsm.marlin_patch import load_machine

    from .cli import CliError
    from .config import load_config, resolve_port
    from .sensor import SensorClient
    from .stage import StageClient

    try:
        plan = load_plan(args.plan, object_id=args.object_id, material=args.material)
    except PlanError as e:
        raise CliError(str(e)) from None
    cal, cal_text = load_calibration(args.calibration)
    try:
        setup = RangingSetup.load(args.ranging)
    except ValueError as e:
        raise CliError(f"{e}; run `dmdsm calibrate-range` first") from None
    v, n, X_R = (np.asarray(cal[k]) for k in ("v", "n", "X_R"))
    points = expand(plan, v, X_R)
    try:  # every move between points is checked before anything moves
        check_plan(points, None, load_machine(), keep_outs(plan, n, X_R))
    except UnsafeMove as e:
        raise CliError(str(e)) from None
    ident = plan.hash() + cal_text + setup.to_json()
    run_hash = hashlib.sha256(ident.encode()).hexdigest()
    scan_id = args.scan_id or f"{plan.object_id}-{run_hash[:8]}"
    path = args.db / "scans" / f"{scan_id}.h5"
    connect(args.db, create=True).close()
    if path.exists():
        try:
            done = read_scan(path, waveforms=False)
        except ScanFileError as e:
            raise CliError(str(e)) from None
        if done.entry.get("status") == "complete":
            print(f"scan {scan_id} is complete ({done.n_points} points) in {path}; nothing "
                  f"to do (--scan-id NAME starts another)")
            return 0
    cfg = load_config(args.config)
    sensor = SensorClient(resolve_port("sensor", args.sensor, cfg))
    writer = None
    status = "interrupted"
    try:
        with StageClient(resolve_port("stage", args.stage, cfg)) as st:
            if not args.no_home:
                st.home()
            here = st.where()
            check_plan(points[:1], np.array([here["X"], here["Y"], here["Z"]]),
                       load_machine(), keep_outs(plan, n, X_R))
            sc = sensor.configure(n_samples=plan.samples, n_average=plan.average,
                                  pretrigger=0, trigger_timeout_ms=2000)
            ident_fields = dict(sensor.identity.fields)
            ident_fields["spec_hash"] = f"{ident_fields['spec_hash']:016x}"
            sensor_attrs = {**ident_fields, "port": sensor.port_name,
                            **{f"config_{k}": v for k, v in sc.items()}}
            try:
                if path.exists():
                    writer = ScanWriter.resume(path, run_hash)
                    print(f"resuming {scan_id}: {writer.n_done} of {len(points)} points done")
                else:
                    writer = ScanWriter.create(
                        path, scan_id=scan_id, plan_text=plan.to_toml(), plan_hash=run_hash,
                        n_samples=sc["n_samples"], sensor=sensor_attrs, calibration=cal,
                        calibration_toml=cal_text, ranging_json=setup.to_json(),
                        sample={"name": plan.object_id, "material": plan.material,
                                "notes": plan.notes, "radius_mm": plan.radius_mm,
                                "height_mm": plan.height_mm},
                        program_version=__version__)
            except ScanFileError as e:
                raise CliError(str(e)) from None
            record(args.db, scan_id, n_planned=len(points))
            ranger = PointRanger(setup, plan, sc["n_samples"], sensor.identity.tick_hz)
            with tqdm(total=len(points), initial=writer.n_done, unit="pt",
                      disable=args.json) as bar:
                def progress(done: int, total: int, timing: dict) -> None:
                    bar.update(done - bar.n)
                    log.debug("point %d: %s", done - 1,
                              " ".join(f"{k}={v * 1e3:.1f}ms" for k, v in timing.items()))
                stats = run_scan(st, sensor, plan, points, writer, ranger, progress)
            st.move(x=here["X"], y=points[0].y, z=here["Z"], feed_mm_min=plan.feed_mm_min)
            st.wait()
            status = "complete"
    except KeyboardInterrupt:
        try:
            sensor.disarm()  # the stage was quick-stopped by its context manager
        except LinkError:
            pass
        raise
    finally:
        if writer is not None:
            writer.close(status)
            record(args.db, scan_id, n_planned=len(points),
                   content_hash=file_hash(path) if status == "complete" else "")
            if status != "complete":
                print(f"scan {scan_id} stopped after {writer.n_done} of {len(points)} points; "
                      f"they are saved in {path}; run the same command to continue",
                      file=sys.stderr)
        sensor.close()
    per = stats.per_point_ms()
    summary = {"scan_id": scan_id, "file": str(path), "points": writer.n_done,
               "stored_now": stats.stored, "lost_waveforms": stats.lost,
               "wall_s": round(stats.wall_s, 2),
               "points_per_s": round(stats.stored / stats.wall_s, 3) if stats.wall_s else 0,
               "ms_per_point": {k: round(v, 2) for k, v in per.items()}}
    if args.json:
        print(json.dumps(summary))
    else:
        print(f"scan {scan_id}: {writer.n_done} points in {path}; {summary['points_per_s']} "
              f"points/s; per point " + ", ".join(f"{k} {v:.1f} ms" for k, v in per.items()))
    return 0
