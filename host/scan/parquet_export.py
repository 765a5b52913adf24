"""The scan database as one Parquet file for training models: one row per waveform with its
pose, distances, points, label and model link (`dmdsm db export --format parquet`).

The schema (every column, its unit and meaning) is in docs/formats.md, "Parquet export".
Scans are checked first (status, content hash, readable metadata, one waveform layout), so
the schema's metadata can name every exported scan; then each is streamed in row groups of
about GROUP_BYTES of waveforms, so memory stays bounded however large the database is.
"""

from __future__ import annotations

import hashlib
import json
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..files import atomic_output, file_hash, one_line
from ..version import __version__
from .catalogue import list_scans
from .points import MODS, scan_points
from .scanfile import (
    POINT_FIELDS,
    ScanData,
    ScanFileError,
    open_scan_file,
    read_scan,
    sample_rate_hz,
)

FORMAT_NAME = "dmdsm-waveforms"
FORMAT_VERSION = "1"
GROUP_BYTES = 16 << 20  # waveform bytes per row group (8192 rows of 1024 uint16 samples)
LABELS = ("scan_id", "object_id", "material", "content_hash")  # the scan's, on every row
#: columns copied from the file's per-point datasets, in schema order
COPIED = ("point_index", "level", "column", "angle_index")
COPIED_2 = ("theta_deg", "received", "attempts", "n_average", "timestamp", "trigger_phase",
            "distance_oa_mm", "distance_us_mm", "snr_oa_db", "snr_us_db")


class ExportError(ValueError):
    """An export that cannot be made as asked; str() says why and what to do."""


class _Skip(Exception):
    """A scan left out of the export; str() is the reason."""


@dataclass
class _Ready:
    """A scan that passed the checks: what the streaming pass and the metadata need."""

    row: dict
    file_hash: str
    n_rows: int
    layout: tuple[int, str, float]  # samples per waveform, sample dtype, sample rate (Hz)
    meta: dict


def schema(n_samples: int, sample_dtype: str, metadata: Mapping[str, str] | None = None
           ) -> object:
    """The export's pyarrow schema for waveforms of n_samples samples of sample_dtype."""
    import pyarrow as pa

    label = pa.dictionary(pa.int32(), pa.string())
    typ = {k: pa.from_numpy_dtype(np.dtype(dt)) for k, (dt, _) in POINT_FIELDS.items()}
    f64 = pa.float64()
    fields = [(k, label) for k in LABELS] + [(k, typ[k]) for k in COPIED]
    fields += [(f"stage_{a}_mm", f64) for a in "xyz"] + [(k, typ[k]) for k in COPIED_2]
    fields += [(f"distance_std_{m}_mm", f64) for m in MODS]
    fields += [(f"point_{m}_{a}_mm", f64) for m in MODS for a in "xyz"]
    fields += [("host_time", typ["host_time"]),
               ("waveform", pa.list_(pa.from_numpy_dtype(np.dtype(sample_dtype)), n_samples)),
               ("model", label)]
    return pa.schema(fields, metadata=dict(metadata or {}))


def export_parquet(db_dir: Path, out_path: Path, *, object_id: str | None = None,
                   scan_ids: list[str] | None = None,
                   model_links: Mapping[str, str] | None = None,
                   rows_per_group: int | None = None) -> dict:
    """Write the selected complete scans of the database (all, one object's, or the named
    ones, in catalogue order) to out_path atomically, zstd-compressed. model_links maps an
    object id to a reference to its 3D model (the `model` column; "" if absent).
    rows_per_group: waveforms per row group (default: GROUP_BYTES of waveforms).
    Returns a summary: path, rows, scans, scan_ids, bytes (file size), row_groups, seconds,
    skipped ([{scan_id, reason}]: unfinished, damaged, another layout) and changed
    ([{scan_id, catalogue_hash, file_hash}]: exported, but the file is not the one the
    catalogue recorded). ExportError if nothing can be exported."""
    import pyarrow.parquet as pq

    t0 = time.monotonic()
    rows = _select(Path(db_dir), object_id, scan_ids)
    ready, skipped = [], []
    for row in rows:
        try:
            ready.append(_prepare(row))
        except _Skip as e:
            skipped.append({"scan_id": row["scan_id"], "reason": str(e)})
    if ready:
        first = ready[0].layout
        for r in [r for r in ready if r.layout != first]:
            ready.remove(r)
            skipped.append({"scan_id": r.row["scan_id"], "reason": (
                f"its waveforms are {_layout_text(r.layout)}, the export's are "
                f"{_layout_text(first)}: export it on its own (name it)")})
    if not ready:
        why = "; ".join(f"{s['scan_id']}: {s['reason']}" for s in skipped[:3])
        raise ExportError(one_line(f"nothing to export: every selected scan was left out "
                                   f"({why})", 400))
    n_samples, dtype, rate = ready[0].layout
    step = rows_per_group or max(1, GROUP_BYTES // (n_samples * np.dtype(dtype).itemsize))
    sch = schema(n_samples, dtype, _metadata(ready, rate, n_samples, dtype))
    links, groups = model_links or {}, 0
    with atomic_output(out_path) as tmp:
        writer = pq.ParquetWriter(str(tmp), sch, compression="zstd")
        try:
            for r in ready:
                groups += _write_scan(writer, sch, r, step,
                                      str(links.get(r.row["object_id"], "")))
        finally:
            writer.close()
    return {"path": str(out_path), "rows": sum(r.n_rows for r in ready), "scans": len(ready),
            "scan_ids": [r.row["scan_id"] for r in ready], "bytes": Path(out_path).stat().st_size,
            "row_groups": groups, "seconds": round(time.monotonic() - t0, 3),
            "skipped": skipped,
            "changed": [{"scan_id": r.row["scan_id"], "catalogue_hash": r.row["content_hash"],
                         "file_hash": r.file_hash} for r in ready if r.meta.get("changed")]}


def _select(db_dir: Path, object_id: str | None, scan_ids: list[str] | None) -> list[dict]:
    """Catalogue rows of the selection; ExportError naming what is known if it is empty or a
    named scan is absent (or of another object)."""
    rows = list_scans(db_dir)
    known = {r["scan_id"]: r for r in rows}
    for sid in scan_ids or []:
        if sid not in known:
            names = one_line(", ".join(list(known)[:10]) or "none")
            raise ExportError(f"no scan {sid!r} in {db_dir} (known: {names})")
        if object_id and known[sid]["object_id"] != object_id:
            raise ExportError(f"scan {sid!r} is of object {known[sid]['object_id']!r}, not "
                              f"{object_id!r}: drop it or the object filter")
    if scan_ids:
        rows = [r for r in rows if r["scan_id"] in set(scan_ids)]
    if object_id:
        objects = sorted({r["object_id"] for r in rows})
        rows = [r for r in rows if r["object_id"] == object_id]
        if not rows:
            raise ExportError(f"no scans of object {object_id!r} in {db_dir} (objects: "
                              f"{one_line(', '.join(objects[:10]) or 'none')})")
    if not rows:
        raise ExportError(f"{db_dir} holds no scans to export")
    return rows


def _prepare(row: dict) -> _Ready:
    """Check one catalogue row and its file before anything is written; _Skip says why not.
    A file whose hash differs from the catalogue's has its waveforms read through once."""
    status = str(row["status"])
    if status.startswith(("refused", "damaged")):
        raise _Skip(status)
    if status == "running":
        raise _Skip("being written (status running): export it once the scan has finished")
    if status != "complete":
        raise _Skip(f"unfinished (status {status}, {row['n_points']} points stored): finish "
                    f"it (`dmdsm scan` resumes it) or leave it out")
    path = Path(row["path"])
    try:
        digest = file_hash(path)
    except OSError as e:
        raise _Skip(f"cannot read {path} ({e.strerror}); `dmdsm db rebuild` re-indexes the "
                    f"files") from None
    changed = digest != row["content_hash"]
    try:
        scan = read_scan(path, waveforms=False)
        if scan.entry.get("status") != "complete":
            raise _Skip(f"the file says status {scan.entry.get('status')!r}, not complete")
        n_samples, dtype = _waveform_layout(path, scan.n_points, read_all=changed)
        _point_columns(scan)  # the calibration and ranging setup are usable
        rate = sample_rate_hz(scan)
    except ScanFileError as e:
        raise _Skip(f"damaged: {e}") from None
    except (KeyError, ValueError, TypeError, IndexError, OSError) as e:
        raise _Skip(f"damaged: {path} ({type(e).__name__}: {one_line(str(e))}); restore it "
                    f"from a copy or scan again") from None
    meta = {"object_id": row["object_id"], "material": row["material"],
            "content_hash": digest, "rows": scan.n_points,
            "start_time": scan.entry.get("start_time", ""),
            "end_time": scan.entry.get("end_time", ""),
            "plan_hash": scan.entry.get("plan_hash", ""), "plan": scan.entry.get("plan", ""),
            "sensor": {k: v for k, v in scan.sensor.items() if k != "NX_class"},
            "calibration": {k: v for k, v in scan.calibration.items() if k != "NX_class"},
            "ranging_json": scan.ranging_json}
    if changed:
        meta.update(changed=True, catalogue_hash=row["content_hash"])
    return _Ready(row, digest, scan.n_points, (n_samples, dtype, rate), meta)


def _waveform_layout(path: Path, n: int, read_all: bool) -> tuple[int, str]:
    """Samples per waveform and the sample dtype; with read_all every waveform is read (and
    dropped) so that damaged compressed data shows now, not halfway through the export."""
    with open_scan_file(path) as f:
        ds = f["/entry/data/waveforms"]
        step = max(1, GROUP_BYTES // max(1, ds.shape[1] * ds.dtype.itemsize))
        for a in range(0, n if read_all else 0, step):
            ds[a:min(n, a + step)]
        dtype, n_samples = np.dtype(ds.dtype), int(ds.shape[1])
    if dtype.kind not in "ui" or dtype.byteorder == ">":
        raise ValueError(f"waveforms of dtype {dtype} (expected unsigned integers)")
    return n_samples, dtype.name


def _layout_text(layout: tuple[int, str, float]) -> str:
    n, dtype, rate = layout
    return f"{n} {dtype} samples at {rate:.6g} Hz"


def _point_columns(scan: ScanData) -> dict[str, np.ndarray]:
    """Every per-row column but the labels and the waveform, as numpy arrays over the scan's
    rows: the file's datasets, and each modality's object-frame point and distance std from
    scan_points (NaN where the row has none), matched row for row by point_index."""
    p = scan.points
    n = scan.n_points
    cols = {k: p[k] for k in (*COPIED, *COPIED_2, "host_time")}
    for i, a in enumerate("xyz"):
        cols[f"stage_{a}_mm"] = p["stage_position_mm"][:, i]
    pts = scan_points(scan)
    for m in MODS:
        ok = np.isfinite(p[f"distance_{m}_mm"]) & p["received"]  # scan_points' selection
        if not np.array_equal(pts[m]["index"], p["point_index"][ok]):
            raise RuntimeError(f"scan_points no longer selects the rows with a {m} distance")
        std = np.full(n, np.nan)
        std[ok] = pts[m]["d_std"]
        cols[f"distance_std_{m}_mm"] = std
        for i, a in enumerate("xyz"):
            xyz = np.full(n, np.nan)
            xyz[ok] = pts[m]["P"][:, i]
            cols[f"point_{m}_{a}_mm"] = xyz
    return cols


def _metadata(ready: list[_Ready], rate: float, n_samples: int, dtype: str) -> dict[str, str]:
    """The schema's metadata: format, sample layout, and per scan its labels, hash, plan,
    sensor and calibration, with its ranging setup named by key in `ranging_setups`."""
    scans, setups = {}, {}
    for r in ready:
        meta = dict(r.meta)
        text = meta.pop("ranging_json")
        key = hashlib.sha256(text.encode()).hexdigest()[:16]
        try:
            setups[key] = json.loads(text)
        except ValueError:
            setups[key] = text  # kept as the file holds it
        scans[r.row["scan_id"]] = {**meta, "ranging_setup": key}
    return {"format_name": FORMAT_NAME, "format_version": FORMAT_VERSION,
            "sample_rate_hz": repr(rate), "n_samples": str(n_samples), "sample_dtype": dtype,
            "program_version": __version__,
            "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "scans": json.dumps(scans), "ranging_setups": json.dumps(setups)}


def _write_scan(writer: object, sch: object, r: _Ready, step: int, model: str) -> int:
    """Stream one scan into the writer, a row group per `step` waveforms; returns the row
    groups. A failure to read the scan is an ExportError (the output is then dropped); a
    failure to write is not caught here (atomic_output names it)."""
    tables = _tables(sch, r, step, model)
    try:
        return _drain(writer, tables, r)
    finally:
        tables.close()  # its scan file too, if the writer failed


def _drain(writer: object, tables: Iterator[object], r: _Ready) -> int:
    """Write each table as one row group; a table that cannot be read is an ExportError."""
    groups = 0
    while True:
        try:
            table = next(tables, None)
        except (ScanFileError, KeyError, ValueError, TypeError, IndexError, OSError) as e:
            raise ExportError(one_line(
                f"{r.row['scan_id']} changed or broke while it was exported "
                f"({type(e).__name__}: {e}); nothing was written: export again, or leave it "
                f"out", 400)) from None
        if table is None:
            return groups
        writer.write_table(table, row_group_size=table.num_rows)
        groups += 1


def _tables(sch: object, r: _Ready, step: int, model: str) -> Iterator[object]:
    """The scan's rows as pyarrow tables of at most `step` rows, read as they are needed."""
    import pyarrow as pa

    path = Path(r.row["path"])
    scan = read_scan(path, waveforms=False)
    if scan.n_points != r.n_rows:
        raise ValueError(f"it holds {scan.n_points} points, {r.n_rows} when checked")
    cols = _point_columns(scan)
    labels = {"scan_id": r.row["scan_id"], "object_id": r.row["object_id"],
              "material": r.row["material"], "content_hash": r.file_hash, "model": model}
    with open_scan_file(path) as f:
        ds = f["/entry/data/waveforms"]
        for a in range(0, r.n_rows, step):
            b = min(r.n_rows, a + step)
            wave = np.ascontiguousarray(ds[a:b])
            arrays = []
            for fld in sch:
                if fld.name in labels:
                    arrays.append(pa.DictionaryArray.from_arrays(
                        pa.array(np.zeros(b - a, np.int32)),
                        pa.array([labels[fld.name]], pa.string())))
                elif fld.name == "waveform":
                    arrays.append(pa.FixedSizeListArray.from_arrays(
                        pa.array(wave.reshape(-1), fld.type.value_type), wave.shape[1]))
                else:
                    arrays.append(pa.array(cols[fld.name][a:b], fld.type))
            yield pa.Table.from_arrays(arrays, schema=sch)
