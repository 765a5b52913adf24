"""The `dmdsm demo` subcommand: its options, and the demo run they start."""

from __future__ import annotations

import argparse

from ..commands.errors import CliError


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register `demo` (host/entry.py adds it to the commands' parser)."""
    d = sub.add_parser("demo", help="run the end-to-end demo and write a report")
    d.add_argument("--out", default="out", help="output folder (default: out)")
    d.add_argument("--quick", action="store_true", help="smaller run for a first look")
    d.add_argument("--json", action="store_true",
                   help="progress to stderr, the summary as one JSON line on stdout")
    d.add_argument("--stage-firmware", default="", metavar="ELF",
                   help="run this stage firmware (Marlin.elf from `make check-marlin`) under "
                        "simavr instead of the Marlin emulator (slower: at most 2x real time)")
    d.set_defaults(func=_demo)


def _demo(args: argparse.Namespace) -> int:
    from .run import run_demo  # the pipeline and the emulator load only for the demo
    try:
        return run_demo(args.out, quick=args.quick, as_json=args.json,
                        stage_firmware=args.stage_firmware)
    except RuntimeError as e:  # the stage firmware could not be started (a bad ELF)
        raise CliError(f"--stage-firmware: {e}") from None
