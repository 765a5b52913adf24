"""`dmdsm plan new`: a first scan plan for an object from its size, written as the TOML that
`dmdsm scan --plan` reads (docs/scanning.md describes every key)."""

from __future__ import annotations

import argparse
import json
from dataclasses import asdict
from pathlib import Path

from ..files import atomic_output, check_output
from ..scan.plan import MODALITIES, MODES, PlanError, load_plan, plan_for_size
from .errors import CliError


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register `plan new` and `plan show`."""
    p = sub.add_parser("plan", help="write or check a scan plan (TOML)")
    actions = p.add_subparsers(dest="action", required=True, metavar="ACTION")
    n = actions.add_parser(
        "new", help="a first plan for an object from its size",
        description="Write OBJECT_ID.toml (or -o FILE): the object's bounding cylinder, one "
                    "level at half its height (at most 40 mm), four angles, the middle 70 % "
                    "of its width. `dmdsm sim --list-scenes` gives the emulator's objects' "
                    "sizes; measure a real one with a ruler.")
    n.add_argument("object_id", metavar="OBJECT_ID", help="the object's name in the database")
    n.add_argument("--size-mm", type=float, nargs=3, required=True,
                   metavar=("WIDTH", "DEPTH", "HEIGHT"),
                   help="the object's width (x), depth (y) and height (mm), standing centred on "
                        "the turntable")
    n.add_argument("--round", action="store_true",
                   help="the object is round about the table axis (a can, a cup): its bounding "
                        "cylinder is its own, not a box's diagonal")
    n.add_argument("--reach-mm", type=float, default=None, metavar="R",
                   help="the farthest any part of the object is from the table axis (mm), "
                        "when it is not centred by its footprint (a mug centred by its body: "
                        "to the handle's end); the bounding cylinder is then R + 1 mm")
    n.add_argument("--material", default="", help="the object's material label (for "
                   "classification; one of the paper's seven or your own)")
    n.add_argument("--mode", choices=MODES, default="step",
                   help="step: step and shoot every 4 mm; fly: each line one move, every 2 mm "
                        "(needs the sync wire: docs/firmware.md); auto: a first look, then "
                        "lines that follow its outline; sweep: the table turning under the "
                        "sensor, a ring every 2 mm of height (a box in passes across the "
                        "beam, as many as its faces need: docs/scanning.md) (default step)")
    n.add_argument("--modality", choices=MODALITIES, default=None,
                   help="which distances the scan is for (default: the material's; us for "
                        "glass and steel, which give no OA pulse, oa for foam, else both)")
    n.add_argument("-o", "--output", type=Path, default=None,
                   help="the plan file (default OBJECT_ID.toml)")
    n.add_argument("--force", action="store_true", help="overwrite an existing plan file")
    n.add_argument("--json", action="store_true", help="machine-readable output")
    n.set_defaults(func=cmd_plan_new)
    s = actions.add_parser("show", help="check a plan file and print what it scans")
    s.add_argument("plan", type=Path, metavar="PLAN", help="the plan file (TOML)")
    s.add_argument("--json", action="store_true", help="machine-readable output")
    s.set_defaults(func=cmd_plan_show)


def cmd_plan_new(args: argparse.Namespace) -> int:
    """Write the plan; print where and what it scans."""
    out = args.output or Path(f"{args.object_id}.toml")
    try:
        plan = plan_for_size(args.object_id, tuple(args.size_mm), args.round, args.material,
                             args.mode, args.modality, reach_mm=args.reach_mm)
    except PlanError as e:
        raise CliError(str(e)) from None
    check_output(out, args.force)
    with atomic_output(out, args.force) as tmp:
        tmp.write_text(plan.to_toml())
    _say(args, plan, f"wrote {out}", out)
    return 0


def cmd_plan_show(args: argparse.Namespace) -> int:
    """Load and check a plan (the checks `scan` makes before opening a board)."""
    try:
        plan = load_plan(args.plan)
    except PlanError as e:
        raise CliError(str(e)) from None
    _say(args, plan, str(args.plan), args.plan)
    return 0


def _say(args: argparse.Namespace, plan: object, head: str, path: Path) -> None:
    """The plan's summary as one line, or as JSON (the file and every key) with --json."""
    if args.json:
        print(json.dumps({"file": str(path), "points": plan.n_points(), **asdict(plan)}))
    else:
        print(f"{head}: {_summary(plan)}")
        if plan.notes:
            print(f"note: {plan.notes}")


def _summary(plan: object) -> str:
    head = f"{plan.object_id} ({plan.material or 'no material'}), {plan.mode}, " \
        f"{plan.n_points()} points: "
    if plan.mode == "sweep":
        lo, hi = min(plan.levels_mm), max(plan.levels_mm)
        offsets = plan.offsets_mm
        return (head + f"the table turning at each height from {lo:g} to {hi:g} mm, "
                f"{plan.step_mm:g} mm apart, {plan.standoff_mm:g} mm outside a "
                f"{plan.radius_mm:g} mm cylinder"
                + (f"; {len(offsets)} passes, the beam "
                   + ", ".join(f"{d:+g}" for d in offsets) + " mm off the table axis"
                   if offsets != [0.0] else ""))
    levels = ", ".join(f"{x:g}" for x in plan.levels_mm)
    angles = ", ".join(f"{x:g}" for x in plan.angles_deg)
    return (head + f"levels [{levels}] mm, angles [{angles}] deg, x ±{plan.half_width_mm:g} "
            f"mm every {plan.step_mm:g} mm")
