"""Scan files: one NeXus-like HDF5 file per scan, written point by point (SWMR) and resumable.

Layout (format_version 1, docs/formats.md):
  /                      format_name="dmdsm-scan", format_version="1"
  /entry       NXentry   scan_id, plan (TOML text), plan_hash, status, start_time, end_time
  /entry/instrument/sensor       NXdetector  identity and configuration of the sensor board
  /entry/instrument/calibration  NXcollection  v, n, X_R (+ std), source file, TOML text
  /entry/instrument/ranging      NXcollection  ranging setup (JSON text), source file
  /entry/sample  NXsample  name (object id), material, notes, bounding cylinder (mm)
  /entry/data    NXdata    one row per finished point: waveforms (n, n_samples) and the
                           per-point datasets in POINT_FIELDS
Rows are appended with every dataset resized, `point_index` last; a reader (or a resume)
takes the shortest dataset as the number of finished points.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..files import one_line

FORMAT_VERSION = "1"
PHASES = ("move", "settle", "acquire", "transfer", "ranging")
#: per-point datasets: name -> (dtype, shape after the point axis)
POINT_FIELDS: dict[str, tuple[str, tuple[int, ...]]] = {
    "stage_position_mm": ("f8", (3,)),   # commanded X, Y, Z in the stage frame {0}
    "theta_deg": ("f8", ()),             # commanded turntable angle A
    "level": ("i4", ()),                 # index of the Z level in the plan
    "column": ("i4", ()),                # index of the in-frame raster position
    "angle_index": ("i4", ()),           # index of the turntable angle in the plan
    "received": ("b1", ()),              # False: the waveform was lost (zeros stored)
    "attempts": ("u1", ()),              # arms it took (a lost waveform is re-armed)
    "n_average": ("u2", ()),             # laser shots averaged on board
    "timestamp": ("u8", ()),             # device ticks of the first averaged laser edge
    "trigger_phase": ("u2", ()),         # device ticks from laser edge to first sample
    "distance_oa_mm": ("f8", ()),        # NaN: no OA arrival
    "distance_us_mm": ("f8", ()),        # NaN: no US echo
    "snr_oa_db": ("f4", ()),
    "snr_us_db": ("f4", ()),
    "phase_time_s": ("f4", (len(PHASES),)),  # wall time per phase, in PHASES order
    "host_time": ("f8", ()),             # Unix time the point was stored (s)
    "point_index": ("i4", ()),           # position in the plan; written last
}


class ScanFileError(ValueError):
    """A scan file that cannot be used as asked; str() says why and what to do."""


@dataclass
class ScanData:
    """A scan read back: metadata dicts and per-point arrays (finished points only)."""

    path: Path
    entry: dict
    sensor: dict
    calibration: dict
    ranging_json: str
    sample: dict
    waveforms: np.ndarray
    points: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def n_points(self) -> int:
        """Finished points."""
        return len(self.waveforms)


def _attrs(obj: object) -> dict:
    out = {}
    for k, v in obj.attrs.items():
        out[k] = v.tolist() if isinstance(v, np.ndarray) else (
            v.item() if isinstance(v, np.generic) else v)
    return out


def _finished(d: object) -> int:
    return min(d[name].shape[0] for name in (*POINT_FIELDS, "waveforms"))


class ScanWriter:
    """Appends points to a scan file; create() starts one, resume() continues one."""

    def __init__(self, f: object, path: Path, lock: int) -> None:
        self.f = f
        self.path = path
        self.lock = lock
        self.data = f["/entry/data"]
        self.n_done = _finished(self.data)

    @classmethod
    def create(cls, path: Path, *, scan_id: str, plan_text: str, plan_hash: str,
               n_samples: int, sensor: dict, calibration: dict, calibration_toml: str,
               ranging_json: str, sample: dict, program_version: str) -> ScanWriter:
        """A new, empty scan file (written to path; fails if it exists)."""
        import h5py

        path = Path(path)
        if path.exists():
            raise ScanFileError(f"{path} already exists")
        path.parent.mkdir(parents=True, exist_ok=True)
        lock = _take_writer_lock(path)
        try:
            f = h5py.File(path, "w-", libver="latest")
        except BaseException:
            _drop_writer_lock(path, lock)
            raise
        f.attrs.update(format_name="dmdsm-scan", format_version=FORMAT_VERSION,
                       default="entry")
        e = f.create_group("entry")
        e.attrs.update(NX_class="NXentry", default="data", scan_id=scan_id, plan=plan_text,
                       plan_hash=plan_hash, status="running",
                       start_time=time.strftime("%Y-%m-%dT%H:%M:%S%z"), end_time="",
                       program="dmdsm", program_version=program_version)
        ins = e.create_group("instrument")
        ins.attrs["NX_class"] = "NXinstrument"
        s = ins.create_group("sensor")
        s.attrs.update(NX_class="NXdetector", **sensor)
        c = ins.create_group("calibration")
        c.attrs.update(NX_class="NXcollection", toml=calibration_toml,
                       **{k: np.asarray(v, float) if isinstance(v, (list, tuple)) else v
                          for k, v in calibration.items()})
        r = ins.create_group("ranging")
        r.attrs.update(NX_class="NXcollection", json=ranging_json)
        smp = e.create_group("sample")
        smp.attrs.update(NX_class="NXsample", **sample)
        d = e.create_group("data")
        d.attrs.update(NX_class="NXdata", signal="waveforms")
        d.create_dataset("waveforms", (0, n_samples), maxshape=(None, n_samples), dtype="u2",
                         chunks=(16, n_samples), compression="gzip", compression_opts=1)
        for name, (dtype, shape) in POINT_FIELDS.items():
            d.create_dataset(name, (0, *shape), maxshape=(None, *shape), dtype=dtype,
                             chunks=(256, *shape))
        f.swmr_mode = True  # readers may open with swmr=True while points arrive
        return cls(f, path, lock)

    @classmethod
    def resume(cls, path: Path, plan_hash: str) -> ScanWriter:
        """Reopen an unfinished scan of the same plan; rows past the last complete point
        (a crash between datasets) are dropped."""
        import h5py

        path = Path(path)
        lock = _take_writer_lock(path)
        try:
            try:
                f = h5py.File(path, "r+", libver="latest")
            except OSError as e:
                if "already open" not in str(e):
                    raise ScanFileError(f"{path}: not a readable scan file ({e})") from None
                _recover(path)  # a crashed writer left the file marked open
                f = h5py.File(path, "r+", libver="latest")
        except BaseException:
            _drop_writer_lock(path, lock)
            raise
        try:
            if f.attrs.get("format_name") != "dmdsm-scan":
                raise ScanFileError(f"{path} is not a dmdsm scan file")
            if f["/entry"].attrs.get("plan_hash") != plan_hash:
                raise ScanFileError(f"{path} was started with a different plan; use a new "
                                    f"output or --scan-id to keep both")
            d = f["/entry/data"]
            n = _finished(d)
            for name in (*POINT_FIELDS, "waveforms"):
                d[name].resize(n, axis=0)
            f["/entry"].attrs["status"] = "running"
            f.flush()
            f.swmr_mode = True
        except BaseException:
            f.close()
            _drop_writer_lock(path, lock)
            raise
        return cls(f, path, lock)

    def append(self, waveform: np.ndarray, **values: object) -> None:
        """Store one finished point (values: every name of POINT_FIELDS) and flush."""
        self.append_many(np.asarray(waveform)[None], **{k: [v] for k, v in values.items()})

    def append_many(self, waveforms: np.ndarray, **values: object) -> None:
        """Store several finished points at once (values: arrays over them for every name
        of POINT_FIELDS), point_index last, and flush once: a fly line lands whole."""
        d = self.data
        i = self.n_done
        k = len(waveforms)
        missing = set(POINT_FIELDS) - set(values)
        if missing:
            raise ValueError(f"points lack {sorted(missing)}")
        order = ["waveforms"] + [n for n in POINT_FIELDS if n != "point_index"] + ["point_index"]
        for name in order:
            ds = d[name]
            ds.resize(i + k, axis=0)
            ds[i:i + k] = waveforms if name == "waveforms" else values[name]
        self.f.flush()
        self.n_done = i + k

    def close(self, status: str, attrs: dict[str, str] | None = None) -> None:
        """Close the file, marking it `complete` or `interrupted` (readable either way);
        attrs: more text attributes of /entry (an auto or sweep scan's coverage, as JSON)."""
        import h5py

        if not self.f.id.valid:
            return
        self.f.close()
        with h5py.File(self.path, "r+") as f:
            f["/entry"].attrs.update(status=status,
                                     end_time=time.strftime("%Y-%m-%dT%H:%M:%S%z"),
                                     **(attrs or {}))
        _drop_writer_lock(self.path, self.lock)


def _lock_path(path: Path) -> Path:
    return Path(path).with_name(Path(path).name + ".writer")


def _take_writer_lock(path: Path) -> int:
    """flock DB/scans/ID.h5.writer for as long as this process writes the scan (the kernel
    drops it when the process dies, so a kill -9 leaves no live-looking writer)."""
    import fcntl
    import os

    fd = os.open(_lock_path(path), os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        pid = os.read(fd, 32).decode(errors="replace").strip() or "?"
        os.close(fd)
        raise ScanFileError(f"{path} is being written by another dmdsm (pid {pid}); wait for "
                            f"it or stop it first") from None
    os.ftruncate(fd, 0)
    os.write(fd, str(os.getpid()).encode())
    return fd


def _drop_writer_lock(path: Path, fd: int) -> None:
    import os

    try:
        _lock_path(path).unlink(missing_ok=True)
    finally:
        os.close(fd)


def writer_alive(path: Path) -> bool:
    """True while a process holds the scan's writer lock (a scan marked running whose writer
    is gone was killed: its finished points are in the file)."""
    import fcntl
    import os

    try:
        fd = os.open(_lock_path(path), os.O_RDONLY)
    except FileNotFoundError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        return False
    except BlockingIOError:
        return True
    finally:
        os.close(fd)


PROBE_S = 20.0  # a damaged file read in SWMR mode can retry for ever: a child gets this long
_PROBE = """
import sys, h5py
with h5py.File(sys.argv[1], "r", swmr=True) as f:
    d = f["/entry/data"]
    for k in d:
        d[k][-1:]
    for k in ("/entry", "/entry/sample", "/entry/instrument/sensor"):
        dict(f[k].attrs)
"""


def _probe_swmr(path: Path) -> None:
    """Read a file marked open for writing (a live or crashed writer) in SWMR mode in a child
    process, bounded in time: HDF5 retries damaged metadata in SWMR mode without end."""
    import subprocess
    import sys

    try:
        r = subprocess.run([sys.executable, "-c", _PROBE, str(path)], capture_output=True,
                           text=True, timeout=PROBE_S)
    except subprocess.TimeoutExpired:
        raise ScanFileError(f"{path} is damaged: reading it did not finish in {PROBE_S:g} s; "
                            f"restore it from a copy or scan again with --scan-id") from None
    if r.returncode:
        last = (r.stderr.strip().splitlines() or ["?"])[-1]
        raise ScanFileError(f"{path} is damaged ({last[:200]}); restore it from a copy or "
                            f"scan again with --scan-id")


def open_scan_file(path: Path) -> object:
    """The HDF5 file for reading: plainly when it was closed properly (a damaged file fails
    at once), in SWMR mode after a bounded probe when a writer holds it or left it open."""
    import h5py

    try:
        return h5py.File(path, "r")
    except FileNotFoundError:
        raise ScanFileError(f"{path}: no such file") from None
    except OSError as e:
        msg = str(e).lower()
        if "unable to lock" not in msg and "already open" not in msg:
            raise ScanFileError(f"{path}: cannot open as HDF5 ({e})") from None
    _probe_swmr(path)
    try:
        return h5py.File(path, "r", swmr=True)
    except OSError as e:
        raise ScanFileError(f"{path}: cannot open as HDF5 ({e})") from None


def _recover(path: Path) -> None:
    """Copy what a crashed writer left (readable in SWMR mode) into a fresh file."""
    import h5py

    tmp = path.with_suffix(".recovering.h5")
    _probe_swmr(path)
    with h5py.File(path, "r", swmr=True) as src, h5py.File(tmp, "w", libver="latest") as dst:
        dst.attrs.update(dict(src.attrs))
        for k in src:
            src.copy(src[k], dst, name=k)
        n = _finished(src["/entry/data"])
        for name in (*POINT_FIELDS, "waveforms"):
            dst["/entry/data"][name].resize(n, axis=0)
    tmp.replace(path)


def read_scan(path: Path, waveforms: bool = True) -> ScanData:
    """A scan file's finished points (also while it is being written)."""

    path = Path(path)
    f = open_scan_file(path)
    try:
        with f:
            return _read(f, path, waveforms)
    except ScanFileError:
        raise
    except (KeyError, ValueError, TypeError, OSError, RuntimeError, IndexError) as e:
        raise ScanFileError(f"{path} is damaged or not a complete dmdsm scan file "
                            f"({type(e).__name__}: {one_line(str(e))})") from None


MAX_POINTS_READ = 5_000_000  # a file declaring more is refused, not read into memory


def _read(f: object, path: Path, waveforms: bool) -> ScanData:
    """The checked contents of an open scan file."""
    if f.attrs.get("format_name") == "dmdsm-shots":
        raise ScanFileError(f"{path} is a recording from `dmdsm acquire`, not a scan: give a "
                            f"file from `dmdsm scan` (DB/scans/*.h5)")
    if f.attrs.get("format_name") != "dmdsm-scan":
        raise ScanFileError(f"{path} is not a dmdsm scan file (no format_name "
                            f"'dmdsm-scan')")
    ver = str(f.attrs.get("format_version"))
    if ver.split(".")[0] != FORMAT_VERSION:
        raise ScanFileError(f"{path} has scan format {ver}; this dmdsm reads "
                            f"{FORMAT_VERSION}.x — upgrade dmdsm")
    d = f["/entry/data"]
    n = _finished(d)
    shape = d["waveforms"].shape
    if n > MAX_POINTS_READ or len(shape) != 2 or shape[1] > 65536:
        raise ScanFileError(f"{path} declares {n} points of {shape[1:]} samples: more than "
                            f"a scan holds; not read")
    for name, (_, shp) in POINT_FIELDS.items():
        if d[name].shape[1:] != shp:
            raise ScanFileError(f"{path}: /entry/data/{name} has shape {d[name].shape}, not "
                                f"(points, {', '.join(map(str, shp))}): not a dmdsm scan file")
    ins = f["/entry/instrument"]
    return ScanData(
        path=path, entry=_attrs(f["/entry"]), sensor=_attrs(ins["sensor"]),
        calibration=_attrs(ins["calibration"]),
        ranging_json=str(ins["ranging"].attrs["json"]), sample=_attrs(f["/entry/sample"]),
        waveforms=d["waveforms"][:n] if waveforms else np.zeros((n, 0), np.uint16),
        points={name: d[name][:n] for name in POINT_FIELDS})


def sample_rate_hz(scan: ScanData) -> float:
    """Samples per second of the scan's waveforms (Hz): the sensor's ADC rate over its
    configured divider, else the ranging setup's rate."""
    s = scan.sensor
    if "adc_rate_hz" in s:
        return float(s["adc_rate_hz"]) / int(s.get("config_sample_rate_div", 1) or 1)
    return float(json.loads(scan.ranging_json)["fs_hz"])


def scan_summary(scan: ScanData) -> dict:
    """What `dmdsm db show` prints: ids, status, counts, modality coverage."""
    p = scan.points
    return {"scan_id": scan.entry.get("scan_id"), "object": scan.sample.get("name"),
            "material": scan.sample.get("material"), "status": scan.entry.get("status"),
            "points": scan.n_points, "received": int(p["received"].sum()),
            "oa_points": int(np.isfinite(p["distance_oa_mm"]).sum()),
            "us_points": int(np.isfinite(p["distance_us_mm"]).sum()),
            "start_time": scan.entry.get("start_time"), "end_time": scan.entry.get("end_time"),
            "sensor": scan.sensor.get("board"), "path": str(scan.path),
            "plan": json.loads(json.dumps(scan.entry.get("plan", "")))}
