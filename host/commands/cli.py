"""The `dmdsm` command: one entry point, one subcommand per job (argparse, pySerial style)."""

from __future__ import annotations

import argparse
import signal
import sys
from collections.abc import Callable, Iterable

from dmdsm.protocol import tool as protocol_tool

from ..calibration.solver import CalibrationError
from ..classify.materials import ClassifyError
from ..files import OutputError, one_line
from ..links.config import ConfigError
from ..links.safety import UnsafeMove
from ..links.transport import LinkError
from ..scan.catalogue import CatalogueError
from ..scan.plan import PlanError
from ..scan.scanfile import ScanFileError
from ..version import __version__
from . import calibrate, campaign, classify, db, devices, flash, live, model, plan, range, scan, sim
from .errors import CliError, Terminated, terminate

AddParser = Callable[[argparse._SubParsersAction], None]


def build_parser(extra: Iterable[AddParser] = ()) -> argparse.ArgumentParser:
    """The argument parser of `dmdsm` with all subcommands of this layer, then those `extra`
    registers (the layers above: host/entry.py adds `dmdsm demo`)."""
    ap = argparse.ArgumentParser(
        prog="dmdsm",
        description="Object scanner for the DMDSM pretouch sensor (host side).")
    ap.add_argument("--version", action="version", version=f"dmdsm {__version__}")
    sub = ap.add_subparsers(dest="command", required=True, metavar="COMMAND")
    protocol_tool.add_parser(sub)
    flash.add_parser(sub)
    sim.add_parser(sub)
    devices.add_parsers(sub)
    range.add_parsers(sub)
    calibrate.add_parser(sub)
    plan.add_parser(sub)
    scan.add_parser(sub)
    campaign.add_parser(sub)
    db.add_parsers(sub)
    model.add_parser(sub)
    classify.add_parser(sub)
    live.add_parser(sub)
    for add_parser in extra:
        add_parser(sub)
    return ap


def main(argv: list[str] | None = None, extra: Iterable[AddParser] = ()) -> int:
    """Run `dmdsm` (with the subcommands `extra` registers); returns the process exit code (2
    for user errors, 130 for Ctrl-C, 143 for SIGTERM)."""
    args = build_parser(extra).parse_args(argv)
    try:
        previous = signal.signal(signal.SIGTERM, terminate)
    except ValueError:  # not the main thread (a test or the demo calling main): leave it
        previous = None
    try:
        return _run(args)
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


def _run(args: argparse.Namespace) -> int:
    try:
        return args.func(args)
    except (CliError, protocol_tool.ToolError, flash.FlashError, LinkError, ConfigError,
            UnsafeMove, CalibrationError, CatalogueError, PlanError, ScanFileError,
            ClassifyError, OutputError) as e:
        print(f"dmdsm: error: {one_line(str(e), 400)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as e:
        if isinstance(e, Terminated) or isinstance(e.__cause__, Terminated):
            print("dmdsm: terminated", file=sys.stderr)
            return 143
        print("dmdsm: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        sys.stderr.close()  # output piped into `head` and closed: not an error
        return 0
