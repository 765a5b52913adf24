"""3D model files: one HDF5 file per object and version in DB/models, written atomically, read
with the checks a hostile file needs, and listed with their staleness against the scans."""

from __future__ import annotations

import contextlib
import datetime
import errno
import json
import os
import re
import secrets
import stat
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..files import one_line, shown, write_failed
from ..scan.catalogue import list_scans, verify
from ..version import __version__

FORMAT_NAME, FORMAT_VERSION = "dmdsm-model", "1"
MAX_ROWS = 5_000_000        # points, vertices or faces in one model file
MAX_CLASSES = 64            # material classes
MAX_SOURCES = 10_000        # scans one model is built from
MAX_JSON = 1 << 20          # characters of one JSON attribute
MAX_ID = 100                # characters of an object id (a scan id holds it: scan/session.py)
UNIT_TOL = 1e-3             # how far a normal's length may be from 1
VERSION_FILE = re.compile(r"v([1-9][0-9]{0,8})\.h5")
AGAIN = "build the model again or remove the file"
# name -> (stored dtype, rows: N points / V vertices / F faces, shape after the rows; C classes)
ARRAYS: dict[str, tuple[str, str, tuple]] = {
    "points_mm": ("f8", "N", (3,)), "points_cov_mm2": ("f8", "N", (3, 3)),
    "points_modality": ("u1", "N", ()), "points_scan": ("i4", "N", ()),
    "points_row": ("i4", "N", ()), "points_outlier": ("b1", "N", ()),
    "vertices_mm": ("f8", "V", (3,)), "faces": ("i4", "F", (3,)), "normals": ("f8", "V", (3,)),
    "sigma_mm": ("f8", "V", ()), "support": ("i4", "V", ()), "supported": ("b1", "V", ()),
    "material_prob": ("f4", "V", ("C",)),
}
FINITE = ("points_mm", "points_cov_mm2", "vertices_mm", "normals")
JSON_ATTRS = ("sources", "params", "summary", "classes")


class ModelError(ValueError):
    """A 3D model, model file or object id that cannot be used; str() says what to fix."""


def utc_now() -> str:
    """Now as ISO 8601 UTC to the second ("2026-12-03T17:23:59+00:00")."""
    return datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")


def _empty(name: str) -> np.ndarray:
    dtype, _, tail = ARRAYS[name]
    return np.zeros((0, *(0 if d == "C" else d for d in tail)), dtype)


def _arr(name: str) -> object:
    return field(default_factory=lambda: _empty(name))


@dataclass(eq=False)
class ObjectModel:
    """One object's 3D model: N fused points, a surface of V vertices and F triangles, and the
    probability of C material classes per vertex (lengths in mm, variances in mm^2)."""

    object_id: str
    version: int = 0                   # 0 until written; then 1, 2, ... per object
    created: str = field(default_factory=utc_now)  # ISO 8601 UTC
    sources: list[dict] = field(default_factory=list)  # per scan: scan_id, content_hash, material
    params: dict = field(default_factory=dict)   # build parameters (JSON-able)
    summary: dict = field(default_factory=dict)  # figures of the build (JSON-able)
    points_mm: np.ndarray = _arr("points_mm")            # (N, 3) object frame
    points_cov_mm2: np.ndarray = _arr("points_cov_mm2")  # (N, 3, 3) covariance
    points_modality: np.ndarray = _arr("points_modality")  # (N,) 0 = OA, 1 = US
    points_scan: np.ndarray = _arr("points_scan")        # (N,) index into sources
    points_row: np.ndarray = _arr("points_row")        # (N,) its row in that scan file
    points_outlier: np.ndarray = _arr("points_outlier")  # (N,) rejected by the fusion
    vertices_mm: np.ndarray = _arr("vertices_mm")        # (V, 3) object frame
    faces: np.ndarray = _arr("faces")                    # (F, 3) vertex indices
    normals: np.ndarray = _arr("normals")                # (V, 3) unit, outward
    sigma_mm: np.ndarray = _arr("sigma_mm")              # (V,) 1-sigma; NaN = unsupported
    support: np.ndarray = _arr("support")                # (V,) points supporting the vertex
    supported: np.ndarray = _arr("supported")            # (V,)
    classes: list[str] = field(default_factory=list)     # C material names
    material_prob: np.ndarray = _arr("material_prob")    # (V, C); NaN row = no waveform near

    @property
    def material(self) -> np.ndarray:
        """(V,) the most probable class per vertex; "" where it has no probabilities."""
        p = np.asarray(self.material_prob, float)
        if p.ndim != 2 or p.shape[1] == 0:
            return np.full(len(p), "", dtype="<U1")
        known = np.isfinite(p).all(axis=1)
        names = np.array([*self.classes, ""])
        return names[np.where(known, np.argmax(np.where(known[:, None], p, -1.0), axis=1), -1)]

    def validate(self) -> None:
        """Check every field (shapes, dtypes, ranges) and convert the arrays to the stored
        dtypes; ModelError naming the first wrong field."""
        check_object_id(self.object_id)
        if type(self.version) is not int or self.version < 0:
            raise ModelError(f"version must be an integer >= 0 (got {one_line(self.version, 40)})")
        _check_time(self.created)
        self.sources = _check_sources(self.sources)
        for key in ("params", "summary"):
            if not isinstance(getattr(self, key), dict):
                raise ModelError(f"{key} must be a dict of JSON values")
            _dumps(getattr(self, key), key)
        self.classes = _check_classes(self.classes)
        n: dict[str, int] = {"C": len(self.classes)}
        for name, (dtype, rows, tail) in ARRAYS.items():
            a = _as_dtype(name, getattr(self, name), dtype)
            _check_shape(name, a.shape, rows, tail, n)
            setattr(self, name, a)
        self._check_values(n)

    def _check_values(self, n: dict[str, int]) -> None:
        for name in FINITE:
            if not np.isfinite(getattr(self, name)).all():
                raise ModelError(f"{name} holds NaN or infinity: every value must be finite")
        _in_range("points_modality", self.points_modality, 0, 1, "0 (OA) or 1 (US)")
        _in_range("points_scan", self.points_scan, 0, len(self.sources) - 1,
                  f"an index into the {len(self.sources)} sources")
        _in_range("points_row", self.points_row, 0, None, "a row index >= 0")
        _in_range("faces", self.faces, 0, n["V"] - 1, f"a vertex index below {n['V']}")
        _in_range("support", self.support, 0, None, "a count >= 0")
        length = np.linalg.norm(self.normals, axis=1)
        if (np.abs(length - 1) > UNIT_TOL).any():
            raise ModelError(f"normals must be unit vectors (a length is "
                             f"{length[np.argmax(np.abs(length - 1))]:.4g})")
        s = self.sigma_mm
        if (np.isinf(s) | (s < 0)).any() or np.isnan(s[self.supported]).any():
            raise ModelError("sigma_mm must be >= 0 mm, NaN only where a vertex is unsupported")
        p = self.material_prob
        nan = np.isnan(p)
        part = p.shape[1] and (nan.any(axis=1) != nan.all(axis=1)).any()  # all([]) is True
        if part or ((p[~nan] < 0) | (p[~nan] > 1)).any():
            raise ModelError("material_prob must hold probabilities in [0, 1], or a whole row "
                             "of NaN for a vertex with no waveform near")


def _dumps(value: object, what: str) -> str:
    try:
        text = json.dumps(value)
    except (TypeError, ValueError, RecursionError) as e:
        raise ModelError(f"{what} must hold JSON values only ({one_line(e, 80)})") from None
    if len(text) > MAX_JSON:
        raise ModelError(f"{what} is {len(text)} characters of JSON, more than {MAX_JSON}")
    return text


def _check_time(text: object) -> None:
    try:
        t = datetime.datetime.fromisoformat(text)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        t = None
    if t is None or t.utcoffset() is None:
        raise ModelError(f"created must be an ISO 8601 time with its offset, e.g. "
                         f"2026-12-03T17:23:59+00:00 (got {one_line(repr(text), 40)})")


def _check_sources(sources: object) -> list[dict]:
    if not isinstance(sources, list) or len(sources) > MAX_SOURCES:
        raise ModelError(f"sources must be a list of at most {MAX_SOURCES} scans")
    for s in sources:
        if not (isinstance(s, dict) and all(isinstance(s.get(k), str) for k in
                                            ("scan_id", "content_hash", "material"))):
            raise ModelError(f"each source must be a dict of text scan_id, content_hash and "
                             f"material (got {one_line(repr(s), 60)})")
    _dumps(sources, "sources")
    return sources


def _check_classes(classes: object) -> list[str]:
    ok = (isinstance(classes, list) and len(classes) <= MAX_CLASSES
          and all(isinstance(c, str) and c and c.isprintable() and len(c) <= 100
                  for c in classes) and len(set(classes)) == len(classes))
    if not ok:
        raise ModelError(f"classes must be at most {MAX_CLASSES} distinct printable names")
    return classes  # type: ignore[return-value]


def _as_dtype(name: str, value: object, dtype: str) -> np.ndarray:
    """`value` as an array of `dtype`: a kind that would lose meaning (floats as indices,
    numbers as flags) or integers out of the type's range are refused."""
    want = np.dtype(dtype)
    try:
        a = np.asarray(value)
    except (ValueError, TypeError) as e:
        raise ModelError(f"{name} must be an array ({one_line(e, 80)})") from None
    kinds = {"f": "fiu", "i": "iu", "u": "iu", "b": "b"}[want.kind]
    if a.dtype.kind not in kinds:
        raise ModelError(f"{name} must hold {want} values (got {a.dtype})")
    if want.kind in "iu" and a.size:
        info = np.iinfo(want)
        if a.min() < info.min or a.max() > info.max:
            raise ModelError(f"{name} holds values outside {want}'s range")
    return np.ascontiguousarray(a, dtype=want)


def _check_shape(name: str, shape: tuple, rows: str, tail: tuple, n: dict[str, int]) -> None:
    want_tail = tuple(n["C"] if d == "C" else d for d in tail)
    if len(shape) != 1 + len(tail) or shape[1:] != want_tail:
        want = "(" + ", ".join((rows, *map(str, want_tail))) + ("," if not tail else "") + ")"
        raise ModelError(f"{name} must have shape {want} (got {shape})")
    if shape[0] > MAX_ROWS:
        raise ModelError(f"{name} has {shape[0]} rows, more than {MAX_ROWS}")
    if n.setdefault(rows, shape[0]) != shape[0]:
        raise ModelError(f"{name} has {shape[0]} rows, but other arrays have {rows} = {n[rows]}")


def _in_range(name: str, a: np.ndarray, lo: int, hi: int | None, what: str) -> None:
    if a.size and (a.min() < lo or (hi is not None and a.max() > hi)):
        raise ModelError(f"every value of {name} must be {what} (got {a.min()} .. {a.max()})")


def check_object_id(object_id: object) -> str:
    """`object_id` if it can name a folder of DB/models: the scan plan's rule (non-empty, no
    spaces, slashes or control characters: scan/plan.py) and a folder name's (printable, not
    "." or ".." or hidden, at most MAX_ID characters); ModelError otherwise."""
    if not isinstance(object_id, str) or not object_id:
        raise ModelError("the object id is empty: give the scan plan's sample.object_id")
    why = ("it holds a control or other unprintable character" if not object_id.isprintable()
           else "it holds a space, a slash or a backslash" if any(c in object_id for c in "/\\ ")
           else "it starts with '.'" if object_id.startswith(".")
           else f"it is longer than {MAX_ID} characters" if len(object_id) > MAX_ID
           or len(object_id.encode()) > 2 * MAX_ID else "")
    if why:
        raise ModelError(f"object id '{one_line(object_id, 60)}' cannot name a model folder: "
                         f"{why}; use letters, digits, '.', '_' and '-'")
    return object_id


def _object_dir(db_dir: Path, object_id: str, create: bool = False) -> Path:
    """DB/models/<object_id>; refused if it is a symbolic link or leads out of DB/models."""
    base = Path(db_dir) / "models"
    folder = base / check_object_id(object_id)
    if create:
        if not Path(db_dir).is_dir():
            raise ModelError(f"{db_dir} is not a scan database folder: give the --db of the scans")
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise ModelError(str(write_failed(folder, e, "--db"))) from None
    if folder.is_symlink() or (folder.exists() and folder.resolve().parent != base.resolve()):
        raise ModelError(f"{folder} is a symbolic link or leads out of {base}: model folders "
                         f"are plain folders; remove it")
    return folder


def _versions(folder: Path) -> dict[int, Path]:
    """The model files of one object's folder by version (v1.h5, v2.h5, ...)."""
    try:
        names = os.listdir(folder)
    except OSError:
        return {}
    return {int(m.group(1)): folder / m.group(0)
            for m in map(VERSION_FILE.fullmatch, names) if m}


def _fsync(path: Path, folder: bool = False) -> None:
    """fsync a file (errors raised) or a folder (some file systems cannot: ignored)."""
    with contextlib.suppress(OSError) if folder else contextlib.nullcontext():
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def write_model(db_dir: Path, model: ObjectModel) -> Path:
    """Write `model` as the next version of its object (DB/models/<object_id>/v<k>.h5) and set
    model.version: a temporary file beside it, fsynced, then hard-linked to the new name, which
    fails if another writer took that version first (then the next one is tried)."""
    model.validate()
    folder = _object_dir(Path(db_dir), model.object_id, create=True)
    tmp = folder / f".v-{secrets.token_hex(6)}-part.h5"
    try:
        os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644))
        version = max(_versions(folder), default=0) + 1
        _write_file(tmp, model, version)
        while True:
            final = folder / f"v{version}.h5"
            _fsync(tmp)
            try:
                os.link(tmp, final)
                break
            except FileExistsError:
                version = max([version, *_versions(folder)]) + 1
                _set_version(tmp, version)
            except OSError as e:  # a file system without hard links: a plain rename
                if e.errno not in (errno.EPERM, errno.ENOTSUP, errno.ENOSYS) or final.exists():
                    raise
                os.rename(tmp, final)
                break
    except OSError as e:
        raise ModelError(str(write_failed(folder, e, "--db"))) from None
    finally:
        with contextlib.suppress(OSError):
            tmp.unlink()
    _fsync(folder, folder=True)
    model.version = version
    return final


def _write_file(path: Path, model: ObjectModel, version: int) -> None:
    import h5py

    with h5py.File(path, "w") as f:
        f.attrs.update(format_name=FORMAT_NAME, format_version=FORMAT_VERSION,
                       object_id=model.object_id, version=version, created=model.created,
                       program="dmdsm", program_version=__version__,
                       **{k: _dumps(getattr(model, k), k) for k in JSON_ATTRS})
        for name in ARRAYS:
            a = getattr(model, name)
            f.create_dataset(name, data=a, **({"compression": "gzip", "compression_opts": 4,
                                               "shuffle": True} if a.size else {}))


def _set_version(path: Path, version: int) -> None:
    import h5py

    with h5py.File(path, "r+") as f:
        f.attrs["version"] = version


def read_model(path: Path) -> ObjectModel:
    """The model in a model file, checked as a hostile file: format, every dataset's shape,
    dtype and size, and the JSON attributes before any array is read, then every value;
    ModelError naming the file otherwise."""
    import h5py

    path = Path(path)
    try:
        kind = os.stat(path).st_mode
    except OSError as e:
        raise ModelError(f"cannot read model {path}: {e.strerror}") from None
    if not stat.S_ISREG(kind):
        raise ModelError(f"{path} is not a model file (not a regular file): name a v<k>.h5 file")
    try:
        with h5py.File(path, "r") as f:
            return _read(f, h5py)
    except ModelError as e:  # a reason that names no fix gets AGAIN
        raise ModelError(f"{path}: {e}" + ("" if ";" in str(e) else f"; {AGAIN}")) from None
    except (OSError, ValueError, KeyError, TypeError, RuntimeError, RecursionError) as e:
        raise ModelError(f"{path} is not a readable model file ({one_line(e, 120)}); "
                         f"{AGAIN}") from None


def _attr(f: object, key: str) -> object:
    """One root attribute, refused unread if it is large."""
    if key not in f.attrs:
        raise ModelError(f"the attribute {key} is missing")
    if f.attrs.get_id(key).get_storage_size() > 4 * MAX_JSON:
        raise ModelError(f"the attribute {key} is larger than {4 * MAX_JSON} bytes")
    v = f.attrs[key]
    if isinstance(v, bytes):
        v = v.decode("utf-8")
    return v.item() if isinstance(v, np.generic) else v


def _read(f: object, h5py: object) -> ObjectModel:
    name = _attr(f, "format_name") if "format_name" in f.attrs else None
    if name != FORMAT_NAME:
        raise ModelError(f"not a dmdsm model file (format_name {one_line(repr(name), 40)}); "
                         f"name a DB/models/OBJECT/vN.h5 file")
    if (v := _attr(f, "format_version")) != FORMAT_VERSION:
        raise ModelError(f"model format {one_line(repr(v), 20)} is not {FORMAT_VERSION}: it "
                         f"was written by another dmdsm version; read it with that version")
    meta = {}
    for key in JSON_ATTRS:
        text = _attr(f, key)
        if not isinstance(text, str) or len(text) > MAX_JSON:
            raise ModelError(f"the attribute {key} is not JSON text of at most {MAX_JSON} chars")
        try:
            meta[key] = json.loads(text)
        except (ValueError, RecursionError):
            raise ModelError(f"the attribute {key} is not valid JSON") from None
    version, created, object_id = (_attr(f, k) for k in ("version", "created", "object_id"))
    n: dict[str, int] = {"C": len(_check_classes(meta["classes"]))}
    for key, (dtype, rows, tail) in ARRAYS.items():
        link = f.get(key, getlink=True)
        d = f.get(key) if isinstance(link, h5py.HardLink) else None
        if not isinstance(d, h5py.Dataset) or d.is_virtual or d.external:
            raise ModelError(f"{key} is missing or not a dataset stored in the file")
        want = np.dtype(dtype)
        if (d.dtype.kind, d.dtype.itemsize) != (want.kind, want.itemsize):
            raise ModelError(f"{key} holds {d.dtype}, not {want}")
        _check_shape(key, d.shape, rows, tail, n)
    m = ObjectModel(object_id=object_id, version=version, created=created,
                    **{k: meta[k] for k in JSON_ATTRS},
                    **{k: f[k][()] for k in ARRAYS})
    m.validate()
    return m


def load_object_model(db_dir: Path, object_id: str, version: int | None = None) -> ObjectModel:
    """One object's model from DB/models (the latest version when None)."""
    folder = _object_dir(Path(db_dir), object_id)
    files = _versions(folder)
    if not files:
        raise ModelError(f"no model of {shown(object_id)} in {db_dir}: build one first")
    if version is None:
        version = max(files)
    if version not in files:
        raise ModelError(f"no version {version} of {shown(object_id)}'s model in {db_dir} "
                         f"(versions: {', '.join(map(str, sorted(files)))})")
    return _db_read(files[version], version)


def _db_read(path: Path, version: int) -> ObjectModel:
    """A model file of the database: a plain file in its object's folder, of its name's
    version and object."""
    if path.is_symlink():
        raise ModelError(f"{path} is a symbolic link: model files are plain files; remove it")
    m = read_model(path)
    if m.version != version or m.object_id != path.parent.name:
        raise ModelError(f"{path} holds version {m.version} of {shown(m.object_id)}, not what "
                         f"its name says: {AGAIN}")
    return m


def _when(text: str) -> datetime.datetime | None:
    """A time from the catalogue or a model (naive: local time), None if it is none."""
    try:
        t = datetime.datetime.fromisoformat(text)
    except (TypeError, ValueError):
        return None
    return t if t.utcoffset() is not None else t.astimezone()


def _stale(db_dir: Path, m: ObjectModel, scans: list[dict], checks: dict[str, str]) -> list[str]:
    """Why `m` no longer describes its object's scans (see staleness), or ["ok"]."""
    rows = {r["scan_id"]: r for r in scans}
    reasons, ends = [], []
    for s in m.sources:
        sid, r = shown(s["scan_id"]), rows.get(s["scan_id"])
        if r is None:
            reasons.append(f"stale: scan {sid} is not in the catalogue")
            continue
        if s["scan_id"] not in checks:
            checks[s["scan_id"]] = verify(r)
        what = {"missing": "'s file is missing", "unfinished": " is unfinished",
                "refused": "'s catalogue path leads out of the database",
                "changed": " changed (its file differs from the catalogue's hash)",
                }.get(checks[s["scan_id"]], "")
        if not what and r["content_hash"] != s["content_hash"]:
            what = " changed (the catalogue holds another content hash)"
        if what:
            reasons.append(f"stale: scan {sid}{what}")
        ends.append(_when(r["finished"]))
    latest = max((t for t in ends if t), default=_when(m.created))
    have = {s["scan_id"] for s in m.sources}
    for r in scans:
        t = _when(r["finished"])
        if (r["object_id"] == m.object_id and r["scan_id"] not in have and r["content_hash"]
                and r["status"] == "complete" and t and latest and t > latest):
            reasons.append(f"stale: scan {shown(r['scan_id'])} is newer")
    return reasons or ["ok"]


def staleness(db_dir: Path, model_or_row: ObjectModel | dict) -> list[str]:
    """["ok"], or why a model (or a list_models row) no longer describes its object's scans:
    a source scan missing from the catalogue, its file missing, its content hash changed (the
    model's against the catalogue's, the catalogue's against the file's), or a finished scan
    of the object that the model leaves out and that finished after its newest source."""
    m = model_or_row
    if isinstance(m, dict):
        m = _db_read(Path(m["path"]), m["version"])
    return _stale(Path(db_dir), m, list_scans(db_dir), {})


def list_models(db_dir: Path, object_id: str | None = None) -> list[dict]:
    """Every model file of DB/models (or one object's), by object and version: object_id,
    version, created, n_vertices, n_points, supported (share of vertices), materials (share of
    vertices per most probable class), material (the largest, "" if none), sources, path and
    status ("ok", "stale: ..." or "damaged: ..."; a damaged file never stops the list).
    CatalogueError if DB is no scan database (the staleness needs its catalogue)."""
    base = Path(db_dir) / "models"
    scans = list_scans(db_dir)
    checks: dict[str, str] = {}
    out = []
    names = sorted(os.listdir(base)) if base.is_dir() else []
    for name in names if object_id is None else [object_id] if object_id in names else []:
        if name.startswith("."):
            continue
        try:
            files = _versions(_object_dir(Path(db_dir), name))
        except ModelError as e:
            out.append(_row(name, 0, base / name, f"damaged: {e}"))
            continue
        for v, path in sorted(files.items()):
            try:
                m = _db_read(path, v)
            except ModelError as e:
                out.append(_row(name, v, path, f"damaged: {e}"))
                continue
            labels, counts = np.unique(m.material[m.material != ""], return_counts=True)
            shares = {str(k): float(c) / len(m.sigma_mm) for k, c in zip(labels, counts)}
            out.append(_row(name, v, path, "; ".join(_stale(Path(db_dir), m, scans, checks)),
                            created=m.created, n_vertices=len(m.vertices_mm),
                            n_points=len(m.points_mm),
                            supported=float(m.supported.mean()) if len(m.supported) else 0.0,
                            materials=shares, material=max(shares, key=shares.get, default=""),
                            sources=m.sources))
    return out


def _row(object_id: str, version: int, path: Path, status: str, **figures: object) -> dict:
    return {"object_id": object_id, "version": version, "created": "", "n_vertices": 0,
            "n_points": 0, "supported": 0.0, "materials": {}, "material": "", "sources": [],
            **figures, "path": str(path), "status": status}
