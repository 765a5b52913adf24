"""`dmdsm calibrate`: scan a step of the procedure into a raw-point file, or solve from one;
the result file (TOML)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ..calibration.center_points import center_points
from ..calibration.result import result_dict, write_result
from ..calibration.rig_file import RawWriter, drop_step, read_raw, steps_in
from ..calibration.solver import CalibrationError, solve
from ..files import atomic_output
from .options import add_ports


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register `calibrate`."""
    from ..calibration.procedure import RigPlan

    p = sub.add_parser("calibrate", help="scan the rig and solve v, n, X_R (paper §IV)")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--from-data", type=Path,
                     help="solve from a calibration data file (CSV, or HDF5 if .h5)")
    src.add_argument("--step", choices=["tip", "edge"],
                     help="scan tip frames (filament horizontal) or edge frames (vertical), "
                          "appending to --data; after the edge step the data is solved")
    add_ports(p)
    p.add_argument("--ranging", type=Path, default=Path("ranging.json"),
                   help="from dmdsm calibrate-range")
    p.add_argument("--data", type=Path, default=Path("rig.csv"),
                   help="raw points: CSV, or HDF5 if it ends in .h5 (docs/calibration.md)")
    p.add_argument("--replace", action="store_true",
                   help="drop the step's raw points already in --data (a repeated or "
                        "interrupted step) before scanning it again")
    p.add_argument("--at", type=float, nargs=3, metavar=("X", "Y", "Z"),
                   help="stage position facing the tip (tip step) or the filament at "
                        "angle 0 (edge step; Z is ignored)")
    p.add_argument("--angles", type=float, nargs="+", default=[0.0, 180.0],
                   help="turntable angles of the edge frames (deg)")
    p.add_argument("--modality", choices=["oa", "us"], default="oa",
                   help="which pulse ranges the filament (default oa)")
    d = RigPlan.__dataclass_fields__
    p.add_argument("--tip-depths", type=float, nargs="+", metavar="MM",
                   default=list(d["tip_depth_steps"].default),
                   help="Y steps back from --at for the tip frames (mm)")
    p.add_argument("--tip-half", type=float, default=d["tip_half_mm"].default,
                   help="half width of the tip frames' X-Z raster (mm)")
    p.add_argument("--tip-step", type=float, default=d["tip_step_mm"].default,
                   help="raster step (mm)")
    p.add_argument("--edge-levels", type=float, nargs="+", metavar="MM",
                   default=list(d["edge_z_levels"].default),
                   help="Z levels of the edge sweeps (mm)")
    p.add_argument("--edge-half", type=float, default=d["edge_half_mm"].default,
                   help="half width of the X sweeps across the filament (mm)")
    p.add_argument("--edge-step", type=float, default=d["edge_step_mm"].default,
                   help="sweep step (mm)")
    p.add_argument("--average", type=int, default=d["average"].default,
                   help="laser shots averaged on the board per raw point")
    p.add_argument("--threshold", type=float, default=0.5,
                   help="keep raw points above this fraction of the frame's max amplitude")
    p.add_argument("--radius", type=float, default=0.25, help="filament radius (mm)")
    p.add_argument("--spot-radius", type=float, default=0.25,
                   help="laser spot radius at the filament (mm): where on the filament's "
                        "front the ranged depth lies (docs/calibration.md)")
    p.add_argument("--table-std", type=float, default=0.01, metavar="DEG",
                   help="std of the turntable's angle reading (deg; default 0.01): two edge "
                        "frames cannot tell it from the filament's position, so it is yours "
                        "to give")
    p.add_argument("-o", "--output", type=Path, default=Path("calibration.toml"),
                   help="calibration to write (default ./calibration.toml)")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.set_defaults(func=cmd_calibrate)


def _scan(args: argparse.Namespace) -> None:
    """One step of the procedure against the boards, appended to args.data."""
    from tqdm import tqdm

    from dmdsm.marlin_patch import load_machine

    from ..calibration.procedure import NoEcho, RigPlan, check_plan, scan_rig
    from ..links.config import load_config, resolve_port
    from ..links.safety import UnsafeMove, check_target
    from ..links.sensor import SensorClient
    from ..links.stage import StageClient
    from ..links.transport import LinkError
    from ..ranging.calibrate import RangingSetup
    from .errors import CliError, check_setting

    if args.at is None:
        raise CliError("give --at X Y Z: the stage position facing the tip (or the filament)")
    x, y, z = args.at
    plan = RigPlan(tip_start=(x, y, z), edge_start=(x, y, 0.0),
                   edge_angles_deg=tuple(args.angles), modality=args.modality,
                   tip_depth_steps=tuple(args.tip_depths), tip_half_mm=args.tip_half,
                   tip_step_mm=args.tip_step, edge_z_levels=tuple(args.edge_levels),
                   edge_half_mm=args.edge_half, edge_step_mm=args.edge_step,
                   average=args.average)
    try:
        check_plan(plan, args.step)
        check_target({"X": x, "Y": y, "Z": z}, load_machine())  # before a board is touched
    except ValueError as e:
        raise CliError(f"--at: {e}" if isinstance(e, UnsafeMove) else str(e)) from None
    check_setting("--average", "n_average", args.average)
    try:
        setup = RangingSetup.load(args.ranging)
    except ValueError as e:
        raise CliError(f"{e}; run `dmdsm calibrate-range` first") from None
    have = _steps_in(args.data)
    if args.step in have and not args.replace:
        raise CliError(f"{args.data} already holds {args.step} raw points: add --replace to "
                       f"scan the {args.step} step again, or give another --data file")
    if args.step == "edge" and "tip" not in have:
        raise CliError(f"{args.data} holds no tip raw points: run `dmdsm calibrate --step tip` "
                       f"with this --data first")
    cfg = load_config(args.config)
    sc = SensorClient(resolve_port("sensor", args.sensor, cfg))
    writer = None
    try:
        with StageClient(resolve_port("stage", args.stage, cfg)) as st, \
                tqdm(unit="point", disable=args.json, desc=f"{args.step} frames") as bar:
            def progress(i: int, total: int) -> None:
                bar.total = total
                bar.update(i - bar.n)
            if args.replace:
                drop_step(args.data, args.step)
            writer = RawWriter(args.data)
            scan_rig(st, sc, setup, plan, args.step, progress,
                     on_row=lambda row: writer.write([row]))
    except NoEcho as e:  # nothing of this step is worth keeping: the same command re-runs
        writer.close()
        drop_step(args.data, args.step)
        raise CliError(f"{e}; nothing of the {args.step} step was kept") from None
    except (ValueError, CalibrationError) as e:
        raise CliError(str(e)) from None
    except LinkError as e:  # the stage was quick-stopped by its context manager
        saved = writer.n_written if writer is not None else 0
        raise CliError(f"{e}; the {args.step} step stopped after {saved} raw points, saved "
                       f"in {args.data}: run the step again with --replace") from None
    except KeyboardInterrupt:
        if writer is not None:
            print(f"{args.step} step stopped after {writer.n_written} raw points; they are "
                  f"saved in {args.data}; run the step again with --replace",
                  file=sys.stderr)
        raise
    finally:
        if writer is not None:
            writer.close()
        sc.close()


def _steps_in(path: Path) -> set[str]:
    """Steps already in the data file, with a one-line error if it cannot be read."""
    from .errors import CliError

    try:
        return steps_in(path)
    except CalibrationError as e:
        raise CliError(f"{e}: give another --data file") from None


def cmd_calibrate(args: argparse.Namespace) -> int:
    """Scan a step, or solve from a data file; save the TOML, print Table I with +- std."""
    from .errors import CliError, check_output

    if not args.table_std > 0:  # NaN too
        raise CliError(f"--table-std must be a positive angle in degrees, not {args.table_std}")
    if args.step != "tip":
        check_output(args.output)  # before the edge step measures anything
    if args.step is not None:
        _scan(args)
        if args.step == "tip":
            if not args.json:
                print(f"tip frames saved in {args.data}; mount the filament vertically and "
                      f"run the edge step")
            else:
                print(json.dumps({"data": str(args.data), "step": "tip"}))
            return 0
    source = args.from_data or args.data
    notes: list[str] = []
    try:
        raw = read_raw(source, notes)
        for note in notes:  # one line each, e.g. how many weak (negative) amplitudes
            print(note, file=sys.stderr)
        data = center_points(raw, args.modality, args.threshold, args.radius,
                             sigma_theta_deg=args.table_std, spot_radius_mm=args.spot_radius)
        r = solve(data)
    except CalibrationError as e:
        raise CliError(str(e)) from None
    out = atomic_output(args.output, keep_previous=True)  # the earlier one is moved aside
    with out as tmp:
        write_result(r, tmp, str(source), args.modality)
    previous = out.previous
    kept = f" (the earlier one is kept as {previous})" if previous else ""
    if args.json:
        print(json.dumps({**result_dict(r), "file": str(args.output),
                          "previous": str(previous) if previous else None}))
        return 0
    for name in ("v", "n"):  # a unit vector's error is an angle
        print(f"{name:<9} [" + "; ".join(f"{a:9.4f}" for a in getattr(r, name))
              + f"] ± {r.angle_std_deg[name]:.4f} deg")
    print("X_R (mm)  [" + "; ".join(f"{a:9.4f} ± {b:.4f}" for a, b in zip(r.X_R[:2],
                                                                     r.std["X_R"][:2]))
          + f"; {r.X_R[2]:9.4f}] (z = 0: the gauge)")
    print(f"rms residual {r.rms_residual_mm * 1000:.1f} um; depth scatter beyond the raw "
          f"points' spread: tips {r.tip_depth_scatter_mm * 1000:.0f} um, edges "
          f"{r.edge_depth_scatter_mm * 1000:.0f} um; saved {args.output}{kept}")
    return 0
