"""The command layer's error: one line shown to the user, no traceback."""

from __future__ import annotations

from pathlib import Path

from .. import files


class Terminated(KeyboardInterrupt):
    """SIGTERM, taken as Ctrl-C: every command's Ctrl-C path (disarm the board, quick-stop
    the stage, keep what was measured) runs for it too."""


def terminate(signum: int, frame: object) -> None:
    """SIGTERM handler: raise Terminated where the program is."""
    raise Terminated()


class CliError(Exception):
    """An error shown to the user as one line, without a traceback."""


def check_output(path: Path, keep_existing: bool = False, flag: str = "-o") -> None:
    """Refuse, before anything is measured, an output that cannot be written: a device, a
    FIFO, a socket, a folder, a link to one of them or to nothing, a missing or unwritable
    folder; an existing file if keep_existing (files.check_output, as a CliError)."""
    try:
        files.check_output(path, force=not keep_existing, flag=flag)
    except files.OutputError as e:
        raise CliError(str(e)) from None


def check_setting(flag: str, field: str, value: int | None) -> None:
    """CliError naming the flag if `value` (None: not given) is outside the range the
    protocol spec allows for set_config's `field`; checked before a board is touched."""
    from dmdsm.protocol import load_spec

    lo, hi = next(f for f in load_spec().by_name["set_config"].fields
                  if f.name == field).allowed()
    if value is not None and not lo <= value <= hi:
        raise CliError(f"{flag} {value} is outside {lo}..{hi}")


keep_previous = files.keep_previous  # calibrate and calibrate-range: an earlier result is kept
