"""Calibration raw-point files (one row per raw point): CSV, or the same columns in HDF5."""

from __future__ import annotations

import csv
from pathlib import Path
from types import TracebackType

import numpy as np

from ..files import not_utf8, shown
from .solver import CalibrationError

COLUMNS = ("step", "frame", "line", "theta_deg", "sx_mm", "sy_mm", "sz_mm", "d_mm",
           "amplitude", "modality")
TEXT = ("step", "modality")
HDF5_SUFFIXES = (".h5", ".hdf5")
FORMAT_NAME = "dmdsm-calibration-raw"
FORMAT_VERSION = 1
GROUP = "raw"  # one 1-D dataset per column, all the same length
MAX_ROWS = 20_000  # raw points a file may hold: the rig procedure writes a few hundred (its
# finest rasters ~2000), and the solve's cost grows with them (a 10^6-row file once asked for
# 34.8 GiB after 15 s); refused while reading, before anything heavy


def is_hdf5(path: Path) -> bool:
    """HDF5 by suffix (.h5, .hdf5); anything else is CSV."""
    return Path(path).suffix.lower() in HDF5_SUFFIXES


def _missing(path: Path, have: list[str]) -> None:
    missing = [c for c in COLUMNS if c not in have]
    if len(missing) == len(COLUMNS):
        raise CalibrationError(f"{path} is not a calibration data file: it has none of the "
                               f"columns {', '.join(COLUMNS)} (see docs/calibration.md)")
    if missing:
        raise CalibrationError(f"{path} lacks column(s) {', '.join(missing)} (expected: "
                               f"{', '.join(COLUMNS)}; see docs/calibration.md)")


def _too_many(path: Path) -> CalibrationError:
    return CalibrationError(
        f"{path} has more than {MAX_ROWS} raw points (the rig procedure writes a few "
        f"hundred): give one calibration's tip and edge steps, or split the file")


def _read_csv(path: Path) -> dict[str, list]:
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:  # a spreadsheet's BOM
            rows = []
            for r in csv.DictReader(f):  # streamed: a huge file is refused at MAX_ROWS
                if len(rows) == MAX_ROWS:
                    raise _too_many(path)
                rows.append(r)
    except OSError as e:
        raise CalibrationError(f"cannot read {path}: {e.strerror}") from None
    except UnicodeDecodeError:
        raise CalibrationError(not_utf8(path, "CSV")) from None
    except csv.Error:
        raise CalibrationError(f"{path} is not a calibration CSV (see docs/calibration.md)"
                               ) from None
    if not rows:
        raise CalibrationError(f"{path} has no data rows")
    _missing(path, list(rows[0]))
    return {c: [r[c] if r[c] is not None else "" for r in rows] for c in COLUMNS}


def _read_hdf5(path: Path) -> dict[str, list]:
    import h5py

    try:
        f = h5py.File(path, "r")
    except FileNotFoundError:
        raise CalibrationError(f"cannot read {path}: No such file or directory") from None
    except OSError:
        raise CalibrationError(f"{path} is not an HDF5 file: give a calibration CSV or .h5 "
                               f"file (see docs/calibration.md)") from None
    with f:
        if f.attrs.get("format_name") != FORMAT_NAME or GROUP not in f:
            raise CalibrationError(f"{path} is not a dmdsm calibration data file (no /{GROUP} "
                                   f"group of format {FORMAT_NAME})")
        g = f[GROUP]
        _missing(path, list(g.keys()))
        lengths = {len(g[c]) for c in COLUMNS}
        if len(lengths) != 1:
            raise CalibrationError(f"{path}: the columns of /{GROUP} differ in length "
                                   f"(an interrupted write?): {sorted(lengths)}")
        if lengths == {0}:
            raise CalibrationError(f"{path} has no data rows")
        if lengths.pop() > MAX_ROWS:
            raise _too_many(path)
        return {c: [x.decode() if isinstance(x, bytes) else x for x in g[c][()].tolist()]
                for c in COLUMNS}


def read_raw(path: Path, notes: list[str] | None = None) -> dict[str, np.ndarray]:
    """The raw points of a calibration data file (CSV or HDF5); extra columns are ignored.

    A negative amplitude is a weak reading (noise about zero), below any threshold: it is
    taken as 0 and, if `notes` is given, one line saying how many rows had one is appended
    to it. More than MAX_ROWS rows are refused as they are read."""
    cols = _read_hdf5(path) if is_hdf5(path) else _read_csv(path)
    out: dict[str, np.ndarray] = {}
    for c in COLUMNS:
        vals = cols[c]
        if c in TEXT:
            out[c] = np.array([str(v).strip().lower() for v in vals])
            continue
        column = np.full(len(vals), np.nan)
        for i, v in enumerate(vals):
            if str(v).strip() in ("", "nan", "NaN"):
                continue
            try:
                column[i] = float(v)
            except ValueError:
                raise CalibrationError(
                    f"{path}: row {i + 1} (line {i + 2}): column {c} has {shown(str(v)[:40])!r}, "
                    f"which is not a number; fix or delete the row") from None
        out[c] = column
    _check_rows(path, out)
    weak = out["amplitude"] < 0  # NaN compares False
    if weak.any():
        out["amplitude"][weak] = 0.0
        if notes is not None:
            notes.append(f"{path}: {int(weak.sum())} raw point(s) with a negative amplitude "
                         f"(a weak reading) taken as 0, below any threshold")
    return out


LIMIT_MM = 10_000.0  # no stage position or distance of this machine comes near it


def _check_rows(path: Path, raw: dict[str, np.ndarray]) -> None:
    """Refuse rows no procedure writes, naming the first (its line in a CSV file)."""
    def bad(mask: np.ndarray, what: str) -> None:
        if mask.any():
            i = int(np.argmax(mask))
            raise CalibrationError(f"{path}: row {i + 1} (line {i + 2}): {what}; fix or delete "
                                   f"the row, or record the step again with --replace")

    bad(~np.isin(raw["step"], ("tip", "edge")), "step must be tip or edge")
    bad(~np.isin(raw["modality"], ("oa", "us")), "modality must be oa or us")
    for c in ("sx_mm", "sy_mm", "sz_mm"):
        bad(~(np.abs(raw[c]) < LIMIT_MM), f"{c} must be a stage position in mm")
    for c in ("frame", "line"):
        v = raw[c]
        bad(~((v >= 0) & (v < 1e6) & (v == np.round(v))), f"{c} must be a whole number >= 0")
    d = raw["d_mm"]  # NaN: no echo at that point
    bad(~np.isnan(d) & ~((d >= 0) & (d < LIMIT_MM)), "d_mm must be a distance >= 0 mm or "
        "empty (no echo)")
    a = raw["amplitude"]
    # a negative amplitude is a weak reading (read_raw takes it as 0); only an infinite one
    # is unusable
    bad(np.isinf(a), "amplitude must be a finite number or empty")
    th = raw["theta_deg"]
    bad(~np.isnan(th) & ~(np.abs(th) < 1e5), "theta_deg must be an angle in degrees or empty")


class RawWriter:
    """Appends raw points to a data file, each flushed as it comes, so an interrupted scan
    leaves a readable file with every point measured so far."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.n_written = 0
        if is_hdf5(self.path):
            import h5py

            new = not self.path.exists()
            try:
                self._h5 = h5py.File(self.path, "a")
            except OSError:
                raise CalibrationError(f"{self.path} is not an HDF5 file we can append to"
                                       ) from None
            if new or (not self._h5.keys() and not self._h5.attrs.keys()):
                self._h5.attrs.update(format_name=FORMAT_NAME, format_version=FORMAT_VERSION)
                g = self._h5.create_group(GROUP)
                for c in COLUMNS:
                    dt = h5py.string_dtype("utf-8") if c in TEXT else "f8"
                    g.create_dataset(c, (0,), maxshape=(None,), dtype=dt, chunks=(256,))
            elif self._h5.attrs.get("format_name") != FORMAT_NAME or GROUP not in self._h5:
                self._h5.close()
                raise CalibrationError(f"{self.path} is not a dmdsm calibration data file")
            self._csv = None
        else:
            new = not self.path.exists() or self.path.stat().st_size == 0
            self._h5 = None
            self._csv = open(self.path, "a", newline="")
            self._w = csv.DictWriter(self._csv, fieldnames=list(COLUMNS), extrasaction="ignore")
            if new:
                self._w.writeheader()

    def write(self, rows: list[dict]) -> None:
        """Append rows (dicts with every name of COLUMNS) and flush them to disk."""
        if not rows:
            return
        if self._h5 is not None:
            g = self._h5[GROUP]
            n = len(g[COLUMNS[0]])
            for c in COLUMNS:  # every column resized and filled before the flush
                g[c].resize(n + len(rows), axis=0)
                g[c][n:] = [str(r[c]) if c in TEXT else float(r[c]) for r in rows]
            self._h5.flush()
        else:
            for r in rows:
                self._w.writerow({k: ("nan" if isinstance(v, float) and np.isnan(v) else v)
                                  for k, v in r.items()})
            self._csv.flush()
        self.n_written += len(rows)

    def close(self) -> None:
        """Close the file (idempotent)."""
        if self._h5 is not None:
            self._h5.close()
            self._h5 = None
        if self._csv is not None:
            self._csv.close()
            self._csv = None

    def __enter__(self) -> RawWriter:
        return self

    def __exit__(self, exc_type: type | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()


def append_rows(path: Path, rows: list[dict]) -> None:
    """Add raw points to a calibration data file (CSV header or HDF5 layout written once)."""
    with RawWriter(path) as w:
        w.write(rows)


def drop_step(path: Path, step: str) -> int:
    """Remove one step's raw points from a data file (`calibrate --replace`): rewrites the file
    with the other rows; returns how many rows were dropped."""
    path = Path(path)
    if not path.exists():
        return 0
    raw = read_raw(path)
    keep = raw["step"] != step
    if keep.all():
        return 0
    rows = [{c: raw[c][i].item() for c in COLUMNS} for i in np.flatnonzero(keep)]
    if rows:
        tmp = path.with_name(".partial-" + path.name)  # same suffix: same format
        tmp.unlink(missing_ok=True)
        append_rows(tmp, rows)
        tmp.replace(path)  # atomic: the old file stays whole until the new one is complete
    else:
        path.unlink()
    return int((~keep).sum())


def steps_in(path: Path) -> set[str]:
    """The steps (tip, edge) a data file already holds; empty if there is no file."""
    if not Path(path).exists() or Path(path).stat().st_size == 0:
        return set()
    try:
        return set(read_raw(path)["step"].tolist())
    except CalibrationError as e:
        if "no data rows" in str(e):
            return set()
        raise
