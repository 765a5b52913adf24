"""`dmdsm model build|export|show`: an object's 3D model from its scans, in the database, in the
files users' tools open and as a page to look at."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ..files import atomic_output, check_output, shown
from ..model.build import build_object_model
from ..model.export import FORMATS, export_model
from ..model.store import ModelError, ObjectModel, load_object_model, staleness, write_model
from .errors import CliError


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register `model build|export|show`."""
    p = sub.add_parser("model", help="3D models of objects: build, export, show")
    psub = p.add_subparsers(dest="action", required=True, metavar="ACTION")
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("object_id", help="the object (`dmdsm db list`)")
    common.add_argument("--db", type=Path, required=True, help="scan database folder")
    common.add_argument("--json", action="store_true", help="machine-readable output")
    q = psub.add_parser("build", parents=[common],
                        help="fuse every finished scan of the object into a new model version")
    q.add_argument("--classifier", type=Path,
                   help="a `dmdsm classify train` model: each vertex's material from it")
    q.add_argument("--spacing-mm", type=float, default=1.0,
                   help="the surface's grid spacing (mm, 0.3-5; default 1)")
    for name, what in (("export", "the model as PLY (sigma, support, material per vertex), "
                        "GLB or OBJ"), ("show", "the model: its figures, or --html a page")):
        q = psub.add_parser(name, parents=[common], help=what)
        q.add_argument("--version", type=int, help="model version (default: the latest)")
        if name == "export":
            q.add_argument("-o", "--output", type=Path, required=True,
                           help="FILE.ply, FILE.glb or FILE.obj")
            q.add_argument("--format", choices=FORMATS, help="instead of the file's suffix")
        else:
            q.add_argument("--html", type=Path, help="write an interactive 3D view (no "
                           "network needed to open it)")
    p.set_defaults(func=cmd_model)


def _load(args: argparse.Namespace) -> ObjectModel:
    return load_object_model(args.db, args.object_id, args.version)


def cmd_model(args: argparse.Namespace) -> int:
    """Build, export or show one object's model; one-line errors."""
    try:
        if args.action == "build":
            return _build(args)
        if args.action == "export":
            check_output(args.output, flag="-o")
            model = _load(args)
            fmt = export_model(model, args.output, args.format)
            print(json.dumps({"object_id": model.object_id, "version": model.version,
                              "format": fmt, "file": str(args.output)}) if args.json else
                  f"wrote {args.output} ({fmt}): model of {shown(model.object_id)} "
                  f"v{model.version}, {len(model.vertices_mm)} vertices")
            return 0
        model = _load(args)
        status = "; ".join(staleness(args.db, model))
        if args.html:
            write_model_page(model, args.html, status)
        show = {"object_id": model.object_id, "version": model.version,
                "created": model.created, "status": status,
                "sources": [s["scan_id"] for s in model.sources], **model.summary}
        if not args.json:
            show["supported_share"] = f"{100 * show.get('supported_share', 0):.1f} %"
            show["sigma_median_mm"] = _mm(show.get("sigma_median_mm"))
        if args.json:
            print(json.dumps(show))
        else:
            for k, v in show.items():
                print(f"{k:>16}: {shown(v)}")
            if args.html:
                print(f"wrote {args.html}")
        return 0
    except (ModelError, ValueError) as e:
        raise CliError(str(e)) from None


def _build(args: argparse.Namespace) -> int:
    if not 0.3 <= args.spacing_mm <= 5.0:
        raise CliError(f"--spacing-mm {args.spacing_mm} is outside 0.3-5 mm")
    say = (lambda s: None) if args.json else (lambda s: print(f"  {s}", file=sys.stderr))
    model = build_object_model(args.db, args.object_id, classifier=args.classifier,
                               spacing_mm=args.spacing_mm, progress=say)
    path = write_model(args.db, model)
    out = {"object_id": model.object_id, "version": model.version, "file": str(path),
           **model.summary}
    if args.json:
        print(json.dumps(out))
        return 0
    s = model.summary
    mats = ", ".join(f"{shown(k)} {v}" for k, v in s["materials"].items()) or "none"
    print(f"model of {shown(model.object_id)} v{model.version}: {s['points']} points "
          f"({s['outliers']} outliers), {s['vertices']} vertices, "
          f"{100 * s['supported_share']:.1f} % supported, sigma median "
          f"{_mm(s['sigma_median_mm'])}; materials (vertices): {mats}; {path}")
    for line in s["left_out"]:
        print(f"  {line}")
    return 0


def _mm(x: float | None) -> str:
    return "n/a" if x is None else f"{x:.3f} mm"


def write_model_page(model: ObjectModel, path: Path, status: str) -> None:
    """The model's interactive 3D view as one self-contained HTML file (atomic)."""
    from ..report.viewer import model_html

    check_output(path, flag="--html")
    notes = {"version": str(model.version), "created": model.created,
             "status": status,
             "scans": ", ".join(s["scan_id"] for s in model.sources)}
    page = model_html(f"{model.object_id}", model.vertices_mm, model.faces, model.sigma_mm,
                      model.support, model.supported, list(model.classes), model.material_prob,
                      notes=notes)
    with atomic_output(path, flag="--html") as tmp:
        Path(tmp).write_text(page, encoding="utf-8")
