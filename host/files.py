"""Files the host writes and reads back: content hashes, checks of what a user's file holds,
and output files written atomically (bottom layer: imports no dmdsm)."""

from __future__ import annotations

import contextlib
import errno
import hashlib
import math
import os
import re
import secrets
import stat
import time
from pathlib import Path


def one_line(text: str, limit: int = 200) -> str:
    """Text from a hostile file made fit for a one-line error: control characters
    escaped, cut to `limit` characters."""
    text = "".join(ch if ch.isprintable() else repr(ch)[1:-1] for ch in str(text))
    return text if len(text) <= limit else text[:limit] + "..."


def file_hash(path: Path) -> str:
    """sha256 of a file's bytes (hex)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def vector3(value: object, what: str, nonzero: bool = False) -> list[float]:
    """`value` as three finite numbers (a direction when nonzero: not all zero); ValueError
    naming `what` otherwise, fit for a one-line error."""
    ok = isinstance(value, list) and len(value) == 3 and all(
        isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)
        for x in value)
    if not ok:
        raise ValueError(f"{what} must be three finite numbers, e.g. [0.0, 1.0, 0.0] "
                         f"(got {one_line(repr(value), 40)})")
    if nonzero and not any(value):
        raise ValueError(f"{what} is a direction and cannot be [0, 0, 0]")
    return [float(x) for x in value]


def not_utf8(path: Path, kind: str) -> str:
    """One line for a text file that is not UTF-8: what it seems to be and what to do."""
    try:
        with open(path, "rb") as f:
            head = f.read(4)
    except OSError:
        head = b""
    if head[:2] in (b"\xff\xfe", b"\xfe\xff"):
        seen = "UTF-16 text"
    elif head[:4] in (b"\xff\xfe\x00\x00", b"\x00\x00\xfe\xff"):
        seen = "UTF-32 text"
    else:
        seen = "not UTF-8 text"
    return f"{path} is {seen}: save the {kind} as UTF-8 (the editor's 'Save with encoding')"


def shown(text: object) -> str:
    """Text for a terminal: control and other unprintable characters as escapes (\\x1b,
    \\u200b), so a name from a file can neither recolour the terminal nor ring its bell."""
    s = str(text)
    if s.isprintable():
        return s
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in s)


class OutputError(Exception):
    """An output path that must not be written (a device, a FIFO, a folder ...) or a write
    that failed (a full disk): one line that names the path and what to give instead."""


# what a failed write means to the user, by errno; anything else: its strerror
_WRITE_FAILED = {
    errno.ENOSPC: "no space left on the device holding {path}: free some space or give "
                  "another {flag}",
    errno.EDQUOT: "the disk quota is used up on the device holding {path}: free some space "
                  "or give another {flag}",
    errno.EFBIG: "{path} would be larger than its file system allows: give another {flag} on "
                 "another file system",
    errno.EIO: "the device holding {path} failed to write (input/output error): check the "
               "disk, or give another {flag}",
    errno.EROFS: "{path} is on a read-only file system: give another {flag}",
}


def _kind(mode: int) -> str:
    """What a file of this st_mode is, for a one-line refusal; "" for a regular file."""
    for test, kind in ((stat.S_ISREG, ""), (stat.S_ISDIR, "a folder"),
                       (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                       (stat.S_ISFIFO, "a FIFO (named pipe)"), (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return kind
    return "not a regular file"


def _through_proc(path: Path) -> bool:
    """Whether a chain of symbolic links from `path` passes through /proc (/dev/stdout,
    /dev/fd/N): a process's open file, whose real name is no file the user gave."""
    p = os.path.abspath(path)
    for _ in range(40):
        p = os.path.join(os.path.realpath(os.path.dirname(p)), os.path.basename(p))
        if p == "/proc" or p.startswith("/proc/"):
            return True
        if not os.path.islink(p):
            return False
        p = os.path.normpath(os.path.join(os.path.dirname(p), os.readlink(p)))
    return False


def output_kind(path: Path) -> str:
    """Why an existing output path must not be written ("a character device", "a symbolic
    link to a FIFO (named pipe)", ...); "" for a new path, a regular file or a symbolic link
    to one (written through: the link stays, its target is replaced)."""
    try:
        mode = os.lstat(path).st_mode
    except OSError:
        return ""  # a new path (or one we cannot see: the folder checks say so)
    if not stat.S_ISLNK(mode):
        return _kind(mode)
    link = one_line(os.readlink(path), 120)
    try:
        inner = _kind(os.stat(path).st_mode)
    except OSError:
        return f"a symbolic link to nothing ({link} does not exist)"
    if inner:
        return f"a symbolic link to {inner} ({link})"
    if _through_proc(Path(path)):
        return f"a symbolic link to a process's open file ({link})"
    return ""


def check_output(path: Path, force: bool = True, flag: str = "-o") -> None:
    """OutputError unless `path` is a new file in a writable folder or a regular file (or a
    link to one; an existing one only with force): run before any device is opened, so a bad
    output fails before a scan starts rather than after it."""
    path = Path(path)
    kind = output_kind(path)
    if kind == "a folder":
        raise OutputError(f"{path} is a folder, not a file: give a file path for {flag} "
                          f"(e.g. {path / 'NAME'})")
    if kind:
        raise OutputError(f"{path} is {kind}, not a regular file: give a new file path or a "
                          f"regular file for {flag}")
    if not force and os.path.lexists(path):
        raise OutputError(f"{path} exists and holds earlier data: name another file, or "
                          f"pass --force to overwrite it")
    check_folder(path, f"write {path}", f"another file for {flag}", flag)


def check_folder(path: Path, action: str, another: str, flag: str) -> None:
    """OutputError unless the folder `path` goes into exists and this user may write in it;
    `action` ("write FILE") and `another` ("another file for -o") word the one line."""
    folder = Path(os.path.realpath(path)).parent
    if not folder.is_dir():
        raise OutputError(f"cannot {action}: the folder {Path(path).parent} does not exist; "
                          f"create it or name {another}")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise OutputError(f"cannot {action}: no permission to write in {folder}; give "
                          f"another {flag}")


def write_failed(path: Path, error: OSError, flag: str = "-o") -> OutputError:
    """The one line for an OSError met while writing `path` (ENOSPC: no space left ...)."""
    code = error.errno
    if code is None:  # h5py puts the C errno into its message only
        m = re.search(r"errno = (\d+)", str(error))
        code = int(m.group(1)) if m else None
    if code in _WRITE_FAILED:
        return OutputError(_WRITE_FAILED[code].format(path=path, flag=flag))
    why = error.strerror or (os.strerror(code) if code else one_line(str(error), 120))
    return OutputError(f"cannot write {path}: {why}; give another {flag}")


class AtomicOutput:
    """A context manager for one output file: it checks the path (check_output), yields a
    temporary path beside the target to write, and on success fsyncs it and renames it over
    the target (os.replace), so a failed or interrupted write leaves the old file or nothing.
    A symbolic link to a regular file is written through (the link stays). keep_previous:
    the earlier file is first renamed NAME.YYYYmmdd-HHMMSS.SUFFIX (self.previous)."""

    def __init__(self, path: Path, force: bool = True, flag: str = "-o",
                 keep_previous: bool = False) -> None:
        """Remember what to write; nothing is touched before the with block."""
        self.path, self.force, self.flag, self.keep = Path(path), force, flag, keep_previous
        self.previous: Path | None = None
        self.tmp: Path | None = None

    def __enter__(self) -> Path:
        """Check the target and create the temporary file (umask's mode, as a new file)."""
        check_output(self.path, self.force, self.flag)
        self.target = Path(os.path.realpath(self.path))
        while self.tmp is None:
            tmp = self.target.with_name(  # the name's suffix, read by savefig and savetxt
                f".{self.target.stem}-{secrets.token_hex(4)}-part{self.path.suffix}")
            try:
                os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
            except FileExistsError:
                continue
            except OSError as e:
                raise write_failed(self.path, e, self.flag) from None
            self.tmp = tmp
        return self.tmp

    def __exit__(self, kind: type[BaseException] | None, error: BaseException | None,
                 tb: object) -> None:
        """Commit the temporary file on success; otherwise remove it and name the failure."""
        assert self.tmp is not None
        try:
            if kind is None:
                self._commit(self.tmp)
        except OSError as e:
            kind, error = type(e), e
        if kind is None:
            return
        with contextlib.suppress(OSError):
            self.tmp.unlink()
        if isinstance(error, OSError):
            raise write_failed(self.path, error, self.flag) from None

    def _commit(self, tmp: Path) -> None:
        """fsync the written file, keep the previous one if asked, rename, fsync the folder."""
        with contextlib.suppress(OSError):  # an existing file keeps its permissions
            os.chmod(tmp, stat.S_IMODE(os.stat(self.target).st_mode))
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        if self.keep:
            self.previous = keep_previous(self.target)
        os.replace(tmp, self.target)
        with contextlib.suppress(OSError):  # some file systems cannot fsync a folder
            fd = os.open(self.target.parent, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)


def atomic_output(path: Path, force: bool = True, flag: str = "-o",
                  keep_previous: bool = False) -> AtomicOutput:
    """`with atomic_output(path) as tmp: write(tmp)`: see AtomicOutput."""
    return AtomicOutput(path, force, flag, keep_previous)


def keep_previous(path: Path) -> Path | None:
    """Before a result is written over an earlier one, move the earlier one aside to
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
