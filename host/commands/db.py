"""`dmdsm db list|show|export|rebuild` and `dmdsm reconstruct`: the scan database, by hand."""

from __future__ import annotations

import argparse
import csv
import json
import sys
import tomllib
from pathlib import Path

import numpy as np

from ..files import atomic_output, shown, vector3
from ..scan.catalogue import CatalogueError, find_scan, list_scans, rebuild, verify
from ..scan.points import MODS, scan_points, validate_block
from ..scan.reconstruct import ply_text
from ..scan.scanfile import ScanData, ScanFileError, read_scan, scan_summary
from .errors import CliError, check_output


def load_truth(path: Path) -> tuple[float, float]:
    """The block's outline size (x, y in mm) from a truth TOML (shape = "box", size_mm)."""
    from .errors import CliError

    try:
        doc = tomllib.loads(Path(path).read_text())
        if "sample" in doc or "scan" in doc:
            raise CliError(f"{path} is a scan plan, not a truth file: give the block's size "
                           f"as --box-mm WIDTH DEPTH (e.g. --box-mm 50 30), or a truth file "
                           f"holding shape = \"box\" and size_mm = [x, y, z]")
        if doc.get("shape", "box") != "box":
            raise ValueError(f"shape {doc.get('shape')!r} is not supported (only \"box\")")
        size = vector3(doc["size_mm"], "size_mm")
        if not all(0 < x <= 1000 for x in size):  # the machine's bed is 410 mm
            raise ValueError(f"size_mm must be three lengths in 0..1000 mm (got {size})")
        w, d = size[:2]
    except OSError as e:
        raise CliError(f"cannot read truth {path}: {e.strerror}") from None
    except (tomllib.TOMLDecodeError, KeyError, TypeError, ValueError) as e:
        raise CliError(f"{path}: not a truth file ({e}); expected shape = \"box\" and "
                       f"size_mm = [x, y, z]") from None
    return w, d


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """Register `db` and `reconstruct`."""
    p = sub.add_parser("db", help="the scan database: list, show, export, rebuild")
    psub = p.add_subparsers(dest="action", required=True, metavar="ACTION")
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--db", type=Path, required=True, help="scan database folder")
    common.add_argument("--json", action="store_true", help="machine-readable output")
    q = psub.add_parser("list", parents=[common], help="the catalogue, with each file checked")
    q.add_argument("--object", help="only this object id")
    q.add_argument("--material", help="only this material")
    q.add_argument("--models", action="store_true",
                   help="the 3D models instead (one line per object and version, with whether "
                        "their scans changed since)")
    q = psub.add_parser("show", parents=[common], help="one scan's metadata and plan, or with "
                        "--html an object's 3D model as a page")
    q.add_argument("scan_id", metavar="ID", help="scan id (`dmdsm db list`); with --html the "
                   "object id (`dmdsm db list --models`)")
    q.add_argument("--html", type=Path, help="write the object's latest 3D model as a "
                   "self-contained interactive page (rotate, zoom, colour by material, sigma "
                   "or support; no network needed to open it)")
    q = psub.add_parser("export", parents=[common],
                        help="one scan's points as CSV and/or PLY, or scans' waveforms, poses, "
                             "distances and labels as Parquet (--format parquet)")
    q.add_argument("scan_id", nargs="*", metavar="SCAN_ID",
                   help="scan id (`dmdsm db list`); with --format parquet any number (none: "
                        "every scan)")
    q.add_argument("--csv", type=Path, help="points as CSV")
    q.add_argument("--ply", type=Path, help="object-frame point cloud as PLY")
    q.add_argument("--mcap", type=Path, help="the scan as ROS 2 messages in an MCAP file: "
                   "poses (/tf), waveforms, distances, points, the object's model "
                   "(docs/robotics.md); Foxglove replays it")
    q.add_argument("--bag", type=Path, metavar="DIR", help="the same messages as a ROS 2 bag "
                   "folder `ros2 bag` (Humble) opens as it is: DIR/DIR_0.mcap and "
                   "DIR/metadata.yaml (DIR created if missing; instead of --mcap)")
    q.add_argument("--format", choices=["parquet"],
                   help="parquet: one row per waveform of the scans (docs/formats.md), to -o")
    q.add_argument("-o", "--output", type=Path, help="the Parquet file (with --format parquet)")
    q.add_argument("--object", help="with --format parquet: only this object's scans")
    psub.add_parser("rebuild", parents=[common],
                    help="index the scan files again (a damaged catalogue is set aside)")
    p.set_defaults(func=cmd_db)
    p = sub.add_parser("reconstruct", help="object-frame points, contours, block validation")
    p.add_argument("scan", type=Path, help="scan file (DB/scans/ID.h5)")
    truth = p.add_mutually_exclusive_group()
    truth.add_argument("--box-mm", type=float, nargs=2, metavar=("WIDTH", "DEPTH"),
                       help="the block's true outline (mm, x and y): e = d(X, E) per modality "
                            "(the paper's validation)")
    truth.add_argument("--truth", type=Path, help="the same from a truth TOML (shape = "
                       "\"box\", size_mm = [x, y, z])")
    p.add_argument("--ply", type=Path, help="write the point cloud")
    p.add_argument("--plot", type=Path, help="write contours like the paper's Figs. 3-4 (PNG)")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.set_defaults(func=cmd_reconstruct)


def _scan_file(args: argparse.Namespace) -> ScanData:
    from .errors import CliError

    try:
        row = find_scan(args.db, args.scan_id)
        if row["status"].startswith("refused"):
            raise CliError(f"{args.scan_id}: {row['status']}; run `dmdsm db rebuild --db "
                           f"{args.db}` to index the files in the database again")
        return read_scan(Path(row["path"]))
    except (CatalogueError, ScanFileError) as e:
        raise CliError(str(e)) from None


def cmd_db(args: argparse.Namespace) -> int:
    """List the catalogue, show one scan, export its points, or re-index the files."""
    from .errors import CliError

    try:
        if args.action == "list" and args.models:
            return _list_models(args)
        if args.action == "list":
            rows = list_scans(args.db, args.object, args.material)
            for r in rows:
                r["check"] = verify(r)
            if args.json:
                print(json.dumps(rows))
            elif not rows:
                print(f"{args.db}: no scans")
            for r in ([] if args.json else rows):
                print(f"{shown(r['scan_id']):<32} {shown(r['object_id']):<18} "
                      f"{shown(r['material']):<10} "
                      f"{r['status']:<11} {r['n_points']:>6} pts  {r['started']}  "
                      f"{_coverage(r['coverage']):<20} {r['check']}")
            return 0
        if args.action == "rebuild":
            n, skipped = rebuild(args.db)
            for line in skipped:
                print(f"dmdsm: skipped {line}", file=sys.stderr)
            if args.json:
                print(json.dumps({"indexed": n, "skipped": skipped}))
            else:
                print(f"indexed {n} scan files in {args.db}" +
                      (f"; {len(skipped)} left out (above)" if skipped else ""))
            return 0
    except CatalogueError as e:
        raise CliError(str(e)) from None
    if args.action == "export":
        if args.format == "parquet":
            return _export_parquet(args)
        args.scan_id = _one_scan_id(args)
    if args.action == "show" and args.html:
        return _show_model(args)
    scan = _scan_file(args)
    if args.action == "show":
        s = scan_summary(scan)
        if args.json:
            print(json.dumps(s))
        else:
            for k, v in s.items():
                print(f"{k:>12}: {shown(v)}" if k != "plan" else
                      f"{k:>12}:\n" + "\n".join(shown(x) for x in str(v).splitlines()))
        return 0
    if not (args.csv or args.ply or args.mcap or args.bag):
        raise CliError("db export needs --csv FILE and/or --ply FILE (or --mcap FILE, --bag DIR)")
    if args.mcap and args.bag:
        raise CliError("db export: --mcap FILE and --bag DIR both write the messages: give one")
    for out, flag in ((args.csv, "--csv"), (args.ply, "--ply"), (args.mcap, "--mcap")):
        if out:
            check_output(out, flag=flag)
    if args.bag:
        from ..robotics.bag_metadata import bag_file
        bag_file(args.bag)  # refused before anything is written (one line)
    pts = scan_points(scan)
    if args.csv:
        with atomic_output(args.csv, flag="--csv") as tmp:
            write_points_csv(tmp, pts)
    if args.ply:
        with atomic_output(args.ply, flag="--ply") as tmp:
            write_ply(tmp, pts)
    mcap = _export_mcap(args, scan) if args.mcap or args.bag else None
    n = sum(len(pts[m]["P"]) for m in MODS)
    print(json.dumps({"scan_id": args.scan_id, "points": n, "csv": str(args.csv or ""),
                      "ply": str(args.ply or ""), "mcap": mcap}) if args.json else
          f"exported {n} points of {args.scan_id}" +
          (f"; {mcap['messages']} ROS 2 messages to {shown(mcap['path'])}" if mcap else "")
          + (f" (ROS 2 bag {shown(args.bag)})" if args.bag else ""))
    return 0


def _export_mcap(args: argparse.Namespace, scan: ScanData) -> dict:
    """`db export SCAN --mcap FILE` (or `--bag DIR`): the scan (and its object's latest
    model, if any) as ROS 2 messages; the summary of robotics.scan_export."""
    from ..model.store import ModelError, load_object_model
    from ..robotics.scan_export import export_scan_bag, export_scan_mcap
    from .errors import CliError

    try:
        model = load_object_model(args.db, str(scan.sample.get("name", "")))
    except ModelError:
        model = None  # no model of the object (or none readable): the scan alone
    try:
        if args.bag:
            return export_scan_bag(scan, args.bag, model=model)
        return export_scan_mcap(scan, args.mcap, model=model)
    except ValueError as e:  # host times no ROS stamp can hold: a damaged file
        raise CliError(str(e)) from None


def _one_scan_id(args: argparse.Namespace) -> str:
    """The scan of a CSV/PLY export; CliError for a Parquet option or not one id."""
    from .errors import CliError

    if args.output or args.object:
        flag = "-o" if args.output else "--object"
        raise CliError(f"db export: {flag} belongs to --format parquet; give --format parquet "
                       f"-o FILE, or one SCAN_ID with --csv FILE and/or --ply FILE")
    if not args.scan_id:
        raise CliError("db export needs a SCAN_ID (`dmdsm db list`) for --csv/--ply, or "
                       "--format parquet -o FILE for the waveforms of many scans")
    if len(args.scan_id) > 1:
        raise CliError(f"db export --csv/--ply takes one SCAN_ID (got {len(args.scan_id)}); "
                       f"several scans go to one file with --format parquet -o FILE")
    return args.scan_id[0]


def model_links(db: Path) -> dict[str, str]:
    """Per object, its latest 3D model file relative to the database ("" for none), with
    " (stale)" where its scans changed since: the Parquet export's `model` column."""
    from ..model.store import list_models

    latest: dict[str, dict] = {}
    for r in list_models(db):
        if r.get("version") and r["version"] >= latest.get(r["object_id"], {}).get("version", 0):
            latest[r["object_id"]] = r
    out = {}
    for oid, r in latest.items():
        try:
            rel = str(Path(r["path"]).resolve().relative_to(Path(db).resolve()))
        except ValueError:
            continue
        out[oid] = rel + ("" if r["status"] == "ok" else " (stale)")
    return out


def _show_model(args: argparse.Namespace) -> int:
    """`db show OBJECT --html FILE`: the object's latest model as a page (commands/model)."""
    from ..model.store import ModelError, load_object_model, staleness
    from .model import write_model_page

    try:
        model = load_object_model(args.db, args.scan_id)
        write_model_page(model, args.html, "; ".join(staleness(args.db, model)))
    except (ModelError, ValueError) as e:
        raise CliError(str(e)) from None
    print(json.dumps({"object_id": model.object_id, "version": model.version,
                      "html": str(args.html)}) if args.json else
          f"wrote {args.html}: model of {shown(model.object_id)} v{model.version}")
    return 0


def _export_parquet(args: argparse.Namespace) -> int:
    """`db export --format parquet -o FILE [--object ID] [SCAN_ID ...]`: the summary on
    stdout, each scan left out on stderr."""
    from ..scan.parquet_export import ExportError, export_parquet
    from .errors import CliError

    if args.csv or args.ply or args.mcap or args.bag:
        raise CliError("db export: --csv/--ply write one scan's points (--mcap/--bag its "
                       "messages); --format parquet writes to -o FILE only (drop "
                       "--csv/--ply/--mcap/--bag or --format)")
    if not args.output:
        raise CliError("db export --format parquet needs -o FILE (e.g. -o scans.parquet)")
    check_output(args.output, flag="-o")
    try:
        s = export_parquet(args.db, args.output, object_id=args.object,
                           scan_ids=list(dict.fromkeys(args.scan_id)) or None,
                           model_links=model_links(args.db))
    except (CatalogueError, ExportError) as e:
        raise CliError(str(e)) from None
    for k in s["skipped"]:
        print(f"dmdsm: skipped {shown(k['scan_id'])}: {shown(k['reason'])}", file=sys.stderr)
    for k in s["changed"]:
        print(f"dmdsm: {shown(k['scan_id'])} was exported, but its file is not the one the "
              f"catalogue recorded (sha256 {k['file_hash'][:12]}, catalogue "
              f"{k['catalogue_hash'][:12] or 'none'}); `dmdsm db list` shows it",
              file=sys.stderr)
    if args.json:
        print(json.dumps(s))
    else:
        print(f"exported {s['rows']} waveforms of {s['scans']} scans to {shown(args.output)} "
              f"({s['bytes'] / 1e6:.1f} MB, {s['row_groups']} row groups)" +
              (f"; {len(s['skipped'])} scans left out (above)" if s["skipped"] else ""))
    return 0


def write_points_csv(path: Path, pts: dict) -> None:
    """One row per (point, modality): indices, pose, d, stage-frame and object-frame X (mm)."""
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["point_index", "modality", "level", "theta_deg", "sx_mm", "sy_mm",
                    "sz_mm", "d_mm", "x_mm", "y_mm", "z_mm"])
        for m in MODS:
            q = pts[m]
            for i in range(len(q["P"])):
                w.writerow([int(q["index"][i]), m, int(q["level"][i]), q["theta_deg"][i],
                            *np.round(q["S"][i], 4), round(float(q["d"][i]), 5),
                            *np.round(q["P"][i], 5)])


def write_ply(path: Path, pts: dict) -> None:
    """Both modalities' object-frame points as one PLY (modality 0 OA, 1 US)."""
    P = np.vstack([pts[m]["P"] for m in MODS])
    mod = np.concatenate([np.full(len(pts[m]["P"]), i) for i, m in enumerate(MODS)])
    lvl = np.concatenate([pts[m]["level"] for m in MODS])
    Path(path).write_text(ply_text(P, mod, lvl))


def _check_figure_type(path: Path) -> None:
    """Refuse a --plot name whose suffix matplotlib cannot write, before the work (it chooses
    the format from the suffix; none is PNG)."""
    from matplotlib.backend_bases import FigureCanvasBase

    from .errors import CliError

    kinds = FigureCanvasBase.get_supported_filetypes()
    if path.suffix and path.suffix[1:].lower() not in kinds:
        raise CliError(f"--plot {path}: a figure cannot be written as {path.suffix}; give a "
                       f".png, .pdf or .svg file")


def cmd_reconstruct(args: argparse.Namespace) -> int:
    """Object-frame points of a scan; with --truth the block validation per modality."""
    from .errors import CliError, check_output

    for out, flag in ((args.ply, "--ply"), (args.plot, "--plot")):
        if out:
            check_output(out, flag=flag)
    if args.plot:
        _check_figure_type(args.plot)
    try:
        scan = read_scan(args.scan, waveforms=False)
    except ScanFileError as e:
        raise CliError(str(e)) from None
    pts = scan_points(scan)
    result: dict = {"scan": str(args.scan), "points": {m: len(pts[m]["P"]) for m in MODS}}
    fits, size = None, None
    if args.box_mm:
        size = tuple(args.box_mm)
        if not all(0 < x <= 1000 for x in size):  # also refuses nan
            raise CliError(f"--box-mm takes two lengths in 0..1000 mm (got {size[0]:g} "
                           f"{size[1]:g})")
    elif args.truth:
        size = load_truth(args.truth)
    if size is not None:
        fits = validate_block(pts, size)
        result["validation"] = fits
    if args.ply:
        with atomic_output(args.ply, flag="--ply") as tmp:
            write_ply(tmp, pts)
        result["ply"] = str(args.ply)
    if args.plot:
        from ..report.plots import contour_figure
        with atomic_output(args.plot, flag="--plot") as tmp:
            contour_figure(pts, tmp, size, fits,
                           title=str(scan.sample.get("name", "")))
        result["plot"] = str(args.plot)
    if args.json:
        print(json.dumps(result))
        return 0
    print(f"{args.scan}: {result['points']['oa']} OA points, {result['points']['us']} US "
          f"points (object frame, mm)")
    for m, f in (fits or {}).items():
        print(f"{m.upper()}: e = {f['e_mean_mm']:.3f} +/- {f['e_std_mm']:.3f} mm over {f['n']} "
              f"points (paper: {'0.06 +/- 0.06' if m == 'oa' else '0.15 +/- 0.11'}); "
              f"block at x {f['pose']['x_mm']:.3f} y {f['pose']['y_mm']:.3f} mm, yaw "
              f"{f['pose']['yaw_deg']:.3f} deg")
    return 0


def _list_models(args: argparse.Namespace) -> int:
    """`db list --models`: one line per model file (object, version, created, vertices, points,
    supported share, largest material, status); --material keeps the models that hold it."""
    from ..model.store import ModelError, list_models
    from .errors import CliError

    try:
        rows = list_models(args.db, args.object)
    except ModelError as e:
        raise CliError(str(e)) from None
    rows = [r for r in rows if not args.material or args.material in r["materials"]]
    if args.json:
        print(json.dumps(rows))
    elif not rows:
        print(f"{args.db}: no models")
    for r in ([] if args.json else rows):
        share = r["materials"].get(r["material"], 0.0)
        material = f"{shown(r['material'])} {100 * share:.0f}%" if r["material"] else "-"
        print(f"{shown(r['object_id']):<18} v{r['version']:<3} {shown(r['created']):<25} "
              f"{r['n_vertices']:>7} vtx {r['n_points']:>7} pts "
              f"{100 * r['supported']:5.1f}% supported  {material:<16} {shown(r['status'])}")
    return 0


def _coverage(text: str) -> str:
    """An auto or sweep scan's coverage for the list ("cov OA 98% US 97%"), "" for others."""
    try:
        c = json.loads(text) if text else {}
        if not c:
            return ""
        return "cov " + " ".join(f"{m.upper()} {100 * float(c[m]):.0f}%" for m in ("oa", "us")
                                 if m in c)
    except (ValueError, TypeError, AttributeError):
        return "cov ?"
