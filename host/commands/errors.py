"""The command layer's error: one line shown to the user, no traceback."""

from __future__ import annotations

import os
import time
from pathlib import Path


class Terminated(KeyboardInterrupt):
    """SIGTERM, taken as Ctrl-C: every command's Ctrl-C path (disarm the board, quick-stop
    the stage, keep what was measured) runs for it too."""


def terminate(signum: int, frame: object) -> None:
    """SIGTERM handler: raise Terminated where the program is."""
    raise Terminated()


class CliError(Exception):
    """An error shown to the user as one line, without a traceback."""


def check_output(path: Path, keep_existing: bool = False) -> None:
    """Refuse an output file that cannot be written (a missing or unwritable folder, a
    folder as the file; an existing file if keep_existing), before anything is measured."""
    path = Path(path)
    kind = _not_a_regular_file(path)
    if kind:
        raise CliError(f"{path} is {kind}, not a regular file: name a new file (or a regular "
                       f"file, with --force where the command has it)")
    if keep_existing and path.exists() and not path.is_dir():
        raise CliError(f"{path} exists and holds earlier data: name another file, or pass "
                       f"--force to overwrite it")
    folder = path.parent if str(path.parent) else Path(".")
    if path.is_dir():
        raise CliError(f"{path} is a folder: name a file to write (e.g. {path / 'shots.h5'})")
    if not folder.is_dir():
        raise CliError(f"cannot write {path}: the folder {folder} does not exist; create it "
                       f"or name another file")
    if not os.access(folder, os.W_OK):
        raise CliError(f"cannot write {path}: no permission to write in {folder}")


def _not_a_regular_file(path: Path) -> str:
    """What an existing output path is if writing it would replace something that is not a
    plain file (a device node, a FIFO, a socket, a symbolic link); "" otherwise."""
    import stat

    try:
        mode = os.lstat(path).st_mode
    except OSError:
        return ""  # a new path (or one we cannot see: the folder checks say so)
    if stat.S_ISLNK(mode):
        return f"a symbolic link (to {os.readlink(path)})"
    for test, kind in ((stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                       (stat.S_ISFIFO, "a FIFO (named pipe)"), (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return kind
    return ""


def check_setting(flag: str, field: str, value: int | None) -> None:
    """CliError naming the flag if `value` (None: not given) is outside the range the
    protocol spec allows for set_config's `field`; checked before a board is touched."""
    from dmdsm.protocol import load_spec

    lo, hi = next(f for f in load_spec().by_name["set_config"].fields
                  if f.name == field).allowed()
    if value is not None and not lo <= value <= hi:
        raise CliError(f"{flag} {value} is outside {lo}..{hi}")


def keep_previous(path: Path) -> Path | None:
    """Before a calibration is written over an earlier one, move the earlier one aside to
    NAME.YYYYmmdd-HHMMSS.SUFFIX (as Klipper keeps printer.cfg on SAVE_CONFIG); its new name,
    or None if there was none."""
    path = Path(path)
    if not path.is_file():
        return None
    stamp = time.strftime("%Y%m%d-%H%M%S", time.localtime(path.stat().st_mtime))
    backup = path.with_name(f"{path.stem}.{stamp}{path.suffix}")
    k = 1
    while backup.exists():  # two in the same second: never over another backup
        backup = path.with_name(f"{path.stem}.{stamp}-{k}{path.suffix}")
        k += 1
    path.replace(backup)
    return backup
