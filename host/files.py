"""Files the host writes and reads back: content hashes and checks of what a user's file
holds (bottom layer: imports no dmdsm)."""

from __future__ import annotations

import hashlib
import math
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
