"""Files the host writes and reads back: content hashes (bottom layer: imports no dmdsm)."""

from __future__ import annotations

import hashlib
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
