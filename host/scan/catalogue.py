"""The scan database: a directory with scans/<scan_id>.h5 and a SQLite catalogue of them.

The catalogue is an index, not the data: every row can be rebuilt from the scan files
(`rebuild`), and a row's content hash tells whether its file changed since it was finished.
"""

from __future__ import annotations

import sqlite3
from pathlib import Path

from ..files import file_hash
from .scanfile import ScanFileError, read_scan, writer_alive

SCHEMA = """
CREATE TABLE IF NOT EXISTS scans (
    scan_id TEXT PRIMARY KEY,
    object_id TEXT NOT NULL,
    material TEXT NOT NULL,
    started TEXT NOT NULL,
    finished TEXT NOT NULL DEFAULT '',
    status TEXT NOT NULL,
    path TEXT NOT NULL,          -- relative to the database directory
    n_points INTEGER NOT NULL,
    n_planned INTEGER NOT NULL,
    plan_hash TEXT NOT NULL,
    content_hash TEXT NOT NULL DEFAULT '',  -- sha256 of the file once complete
    coverage TEXT NOT NULL DEFAULT ''       -- an auto or sweep scan's coverage (JSON)
);
"""
COLUMNS = ("scan_id", "object_id", "material", "started", "finished", "status", "path",
           "n_points", "n_planned", "plan_hash", "content_hash", "coverage")


class CatalogueError(ValueError):
    """A database directory that cannot be used; str() says what to do."""


def connect(db_dir: Path, create: bool = False) -> sqlite3.Connection:
    """Open DB/catalogue.sqlite (creating the directory and table if asked)."""
    db_dir = Path(db_dir)
    if db_dir.exists() and not db_dir.is_dir():
        raise CatalogueError(f"{db_dir} is a file, not a scan database folder: name a folder "
                             f"(a new one is created)")
    if not db_dir.is_dir():
        if not create:
            raise CatalogueError(f"{db_dir} is not a scan database (no such directory); "
                                 f"`dmdsm scan --db {db_dir}` creates one")
        (db_dir / "scans").mkdir(parents=True)
    path = db_dir / "catalogue.sqlite"
    try:
        con = sqlite3.connect(path, timeout=30)
        con.execute(SCHEMA)
        have = {r[1] for r in con.execute("PRAGMA table_info(scans)")}
        if "coverage" not in have and "scan_id" in have:  # a catalogue from before auto scans
            con.execute("ALTER TABLE scans ADD COLUMN coverage TEXT NOT NULL DEFAULT ''")
            con.commit()
            have.add("coverage")
        bad = [c for c in COLUMNS if c not in have]
        if bad:
            con.close()
            raise sqlite3.DatabaseError(f"table scans lacks {', '.join(bad)}")
    except sqlite3.DatabaseError as e:
        raise CatalogueError(f"{path} is damaged ({e}); `dmdsm db rebuild --db {db_dir}` "
                             f"makes a new one from the scan files") from None
    return con


def record(db_dir: Path, scan_id: str, *, n_planned: int, content_hash: str = "") -> None:
    """Insert or update the row of one scan from its file."""
    db_dir = Path(db_dir)
    path = db_dir / "scans" / f"{scan_id}.h5"
    s = read_scan(path, waveforms=False)
    status = str(s.entry.get("status", ""))
    if status == "running" and not writer_alive(path):
        status = "interrupted"  # its writer was killed
    row = (scan_id, str(s.sample.get("name", "")), str(s.sample.get("material", "")),
           str(s.entry.get("start_time", "")), str(s.entry.get("end_time", "")),
           status, str(path.relative_to(db_dir)), s.n_points,
           n_planned, str(s.entry.get("plan_hash", "")), content_hash,
           str(s.entry.get("coverage", "")))
    with connect(db_dir) as con:
        con.execute(f"INSERT OR REPLACE INTO scans ({', '.join(COLUMNS)}) VALUES "
                    f"({', '.join('?' * len(COLUMNS))})", row)
    con.close()


def list_scans(db_dir: Path, object_id: str | None = None,
               material: str | None = None) -> list[dict]:
    """Catalogue rows (dicts with COLUMNS; `path` made absolute), oldest first."""
    con = connect(db_dir)
    q, args = f"SELECT {', '.join(COLUMNS)} FROM scans", []
    where = [(c, v) for c, v in (("object_id", object_id), ("material", material)) if v]
    if where:
        q += " WHERE " + " AND ".join(f"{c} = ?" for c, _ in where)
        args = [v for _, v in where]
    rows = [dict(zip(COLUMNS, r)) for r in con.execute(q + " ORDER BY started, scan_id", args)]
    con.close()
    scans = (Path(db_dir) / "scans").resolve()
    for r in rows:
        p = (Path(db_dir) / r["path"]).resolve()
        if p.parent != scans:  # a row pointing elsewhere (edited, or absolute) is not opened
            r["status"] = f"refused: {r['path']!r} is not a file in {scans}"
            p = scans / f"{r['scan_id']}.refused"
        r["path"] = str(p)
        if r["status"] == "running":  # the row is written at start and end: ask the file
            _live_row(r, p)
    return rows


def _live_row(row: dict, path: Path) -> None:
    """A running row as its file and writer say now: the points on disk, and `interrupted`
    if the process writing it is gone (kill -9, power loss)."""
    if not writer_alive(path):
        row["status"] = "interrupted"
    try:
        row["n_points"] = read_scan(path, waveforms=False).n_points
    except ScanFileError as e:
        row["status"] = f"damaged: {e}"


def find_scan(db_dir: Path, scan_id: str) -> dict:
    """One catalogue row; CatalogueError naming the known ids if absent."""
    rows = list_scans(db_dir)
    for r in rows:
        if r["scan_id"] == scan_id:
            return r
    known = ", ".join(r["scan_id"] for r in rows[:10]) or "none"
    raise CatalogueError(f"no scan {scan_id!r} in {db_dir} (known: {known})")


def verify(row: dict) -> str:
    """'ok', 'changed' (hash differs), 'missing', 'unfinished' or 'refused' (its path leads
    out of the database) for a catalogue row."""
    p = Path(row["path"])
    if str(row.get("status", "")).startswith("refused"):
        return "refused"
    if not p.exists():
        return "missing"
    if not row["content_hash"]:
        return "unfinished"
    return "ok" if file_hash(p) == row["content_hash"] else "changed"


def rebuild(db_dir: Path) -> tuple[int, list[str]]:
    """Re-index every readable scans/*.h5 (after copying files in, or over a damaged
    catalogue, which is kept aside as catalogue.sqlite.damaged); returns the rows written and
    one line per file left out."""
    db_dir = Path(db_dir)
    try:
        connect(db_dir).close()
    except CatalogueError:
        if not db_dir.is_dir():
            raise
        (db_dir / "catalogue.sqlite").replace(db_dir / "catalogue.sqlite.damaged")
        connect(db_dir).close()
    n, skipped = 0, []
    for path in sorted((db_dir / "scans").glob("*.h5")):
        try:
            s = read_scan(path, waveforms=False)
        except ScanFileError as e:
            skipped.append(str(e))
            continue
        done = s.entry.get("status") == "complete"
        record(db_dir, path.stem, n_planned=s.n_points if done else -1,
               content_hash=file_hash(path) if done else "")
        n += 1
    return n, skipped
