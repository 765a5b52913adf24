"""`dmdsm calibrate-range` and `dmdsm range`: the stage as a ruler for t0 and c, and ranging of
recorded acquisitions."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from ..files import atomic_output
from ..ranging.calibrate import MODALITIES, RangingSetup, distance_std_mm, range_waveforms
from ..ranging.matched_filter import speed_of_sound_mm_s
from ..ranging.procedure import calibrate_range
from .errors import check_output
from .options import add_ports


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """Register calibrate-range and range."""
    p = sub.add_parser("calibrate-range", help="fit t0 and c with the stage as a ruler")
    add_ports(p)
    p.add_argument("--at", type=float, nargs=3, metavar=("X", "Y", "Z"),
                   help="start position (mm): the sensor facing the block's face, Y closest "
                        "to it (required; as in `dmdsm calibrate --at`)")
    for axis in "xyz":  # the first release's spelling, still read
        p.add_argument(f"-{axis}", type=float, default=None, help=argparse.SUPPRESS)
    p.add_argument("--start-distance", type=float, required=True,
                   help="beam distance to the flat target at the start (mm)")
    p.add_argument("--steps", type=int, default=11, help="depths measured (default 11)")
    p.add_argument("--step-mm", dest="step", type=float, default=0.5,
                   help="Y step away from the target (mm, default 0.5)")
    p.add_argument("--step", dest="step", type=float, default=argparse.SUPPRESS,
                   help=argparse.SUPPRESS)  # the first release's spelling, still read
    p.add_argument("--shots", type=int, default=10, help="waveforms per position")
    p.add_argument("--average", type=int, default=16,
                   help="laser shots averaged on the board per waveform")
    p.add_argument("--temperature", type=float, default=20.0, help="air temperature (degC)")
    p.add_argument("--lateral", type=int, default=1,
                   help="X positions per depth (0.5 mm apart) to average surface roughness")
    p.add_argument("--fixed-c", action="store_true",
                   help="take c from --temperature and fit t0 only (short travel)")
    p.add_argument("-o", "--output", type=Path, default=Path("ranging.json"),
                   help="ranging calibration to write (default ./ranging.json)")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.set_defaults(func=cmd_calibrate_range)
    p = sub.add_parser("range", help="distances from a recorded acquisition (dmdsm acquire)")
    p.add_argument("file", type=Path, help="HDF5 file from `dmdsm acquire`")
    p.add_argument("--ranging", dest="calibration", type=Path, default=Path("ranging.json"),
                   help="ranging calibration (default ./ranging.json; as in `dmdsm scan`)")
    p.add_argument("--calibration", dest="calibration", type=Path,
                   default=argparse.SUPPRESS, help=argparse.SUPPRESS)  # the first spelling
    p.add_argument("--modality", choices=MODALITIES, default="oa",
                   help="which pulse to range (default oa)")
    p.add_argument("--temperature", type=float, default=None,
                   help="use c from this air temperature (degC) instead of the fitted c")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.set_defaults(func=cmd_range)


def cmd_calibrate_range(args: argparse.Namespace) -> int:
    """Run the procedure against the two boards and save the ranging setup."""
    from ..links.config import load_config, resolve_port
    from ..links.sensor import SensorClient
    from ..links.stage import StageClient
    from .errors import CliError

    check_output(args.output)  # before the stage moves
    _check_procedure(args)
    cfg = load_config(args.config)
    sc = SensorClient(resolve_port("sensor", args.sensor, cfg))
    try:
        with StageClient(resolve_port("stage", args.stage, cfg)) as st:
            setup, report = calibrate_range(
                st, sc, {"X": args.x, "Y": args.y, "Z": args.z}, args.start_distance,
                args.steps, args.step, args.shots, args.average, args.temperature,
                fit_c=not args.fixed_c, lateral=args.lateral)
    except ValueError as e:
        raise CliError(str(e)) from None
    finally:
        sc.close()
    out = atomic_output(args.output, keep_previous=True)  # the earlier one is moved aside
    with out as tmp:
        setup.save(tmp)
    previous = out.previous
    if args.json:
        print(json.dumps({"file": str(args.output), **report,
                          "previous": str(previous) if previous else None}))
    else:
        for m, text in report.items():
            print(f"{m.upper()}: {text}")
        print(f"saved {args.output}" + (f" (the earlier one is kept as {previous})"
                                        if previous else ""))
    return 0


def _check_procedure(args: argparse.Namespace) -> None:
    """Refuse, before either board is touched, numbers the procedure cannot use and any
    position it would visit outside the machine envelope."""
    from dmdsm.marlin_patch import load_machine

    from ..links.safety import UnsafeMove, check_target
    from ..ranging.procedure import positions
    from .errors import CliError, check_setting

    if args.at is not None:
        args.x, args.y, args.z = args.at
    elif None in (args.x, args.y, args.z):
        raise CliError("give --at X Y Z: the stage position (mm) where the sensor faces the "
                       "block's face")
    numbers = {"--at X": args.x, "--at Y": args.y, "--at Z": args.z, "--step-mm": args.step,
               "--start-distance": args.start_distance, "--temperature": args.temperature}
    for flag, value in numbers.items():
        if not np.isfinite(value):
            raise CliError(f"{flag} must be a finite number (got {value})")
    if args.start_distance <= 0 or args.step <= 0:
        raise CliError("--start-distance and --step-mm must be positive (mm)")
    fewest = 1 if args.fixed_c else 2  # t0 and c need two depths at least
    if not fewest <= args.steps <= 1000 or not 1 <= args.lateral <= 100 or args.shots < 1:
        raise CliError(f"--steps must be {fewest}..1000, --lateral 1..100 and --shots at "
                       f"least 1")
    check_setting("--average", "n_average", args.average)
    where = positions({"X": args.x, "Y": args.y, "Z": args.z}, args.steps, args.step,
                      args.lateral)
    limits = load_machine()
    for p in (where.min(axis=0), where.max(axis=0)):  # the box the path stays in
        try:
            check_target(dict(zip("XYZ", p.tolist())), limits)
        except UnsafeMove as e:
            raise CliError(f"calibrate-range would leave the machine envelope: {e}; start "
                           f"elsewhere or take fewer or shorter steps") from None


MAX_SHOT_BYTES = 1 << 30  # waveforms read into memory at most (a file's shape is checked first)


def read_acquisition(path: Path) -> tuple[np.ndarray, np.ndarray, int, np.ndarray]:
    """The received shots of a `dmdsm acquire` file: waveforms (centred counts), trigger
    phases (s), pretrigger (samples) and shot ids; any other HDF5 file (another program's, a
    damaged one, one too large to read) is a one-line CliError that says what it is."""
    import h5py

    from .errors import CliError

    def bad(why: str) -> CliError:
        return CliError(f"{path}: not a dmdsm acquisition file ({why}); give a file written "
                        f"by `dmdsm acquire`")

    try:
        with h5py.File(path, "r") as f:
            if f.attrs.get("format_name") not in ("dmdsm-shots", b"dmdsm-shots"):
                raise bad("no format_name 'dmdsm-shots'")
            d, s = f.get("/entry/data"), f.get("/entry/instrument/sensor")
            if not isinstance(d, h5py.Group) or not isinstance(s, h5py.Group):
                raise bad("no /entry/data or /entry/instrument/sensor group")
            sets = {k: d.get(k) for k in ("waveforms", "received", "trigger_phase", "shot_id")}
            for k, ds in sets.items():
                if not isinstance(ds, h5py.Dataset) or ds.dtype.names is not None:
                    raise bad(f"/entry/data/{k} is not a plain dataset")
            w = sets["waveforms"]
            n = w.shape[0] if w.ndim == 2 else -1
            if n < 0 or w.dtype.kind not in "ui" or any(
                    sets[k].shape != (n,) or sets[k].dtype.kind not in "biu"
                    for k in ("received", "trigger_phase", "shot_id")):
                raise bad("waveforms must be (shots, samples) integers with one received, "
                          "trigger_phase and shot_id per shot")
            if w.size * 8 > MAX_SHOT_BYTES:
                raise CliError(f"{path}: {n} waveforms of {w.shape[1]} samples is more than "
                               f"this command reads at once ({MAX_SHOT_BYTES >> 30} GiB as "
                               f"numbers): split the acquisition")
            tick_hz = float(s.attrs.get("tick_hz", np.nan))
            if not (np.isfinite(tick_hz) and tick_hz > 0):
                raise bad("no positive tick_hz on /entry/instrument/sensor")
            ok = sets["received"][:].astype(bool)
            x = w[:][ok].astype(float) - 32768.0
            phase = sets["trigger_phase"][:][ok] / tick_hz
            pre = int(s.attrs.get("config_pretrigger", 0))
            ids = sets["shot_id"][:][ok]
    except OSError as e:
        raise CliError(f"{path}: cannot read it as HDF5 ({e}); give a file written by "
                       f"`dmdsm acquire`") from None
    except (TypeError, ValueError) as e:
        raise bad(str(e)) from None
    return x, phase, pre, ids


def cmd_range(args: argparse.Namespace) -> int:
    """Range every received shot of an HDF5 acquisition."""

    from .errors import CliError

    try:
        setup = RangingSetup.load(args.calibration)
    except ValueError as e:
        raise CliError(f"{e}; run `dmdsm calibrate-range` first") from None
    if args.modality not in setup.cals:
        raise CliError(f"{args.calibration} has no {args.modality.upper()} calibration")
    if args.temperature is not None:
        setup.cals[args.modality].c_mm_s = speed_of_sound_mm_s(args.temperature)
    x, phase, pre, ids = read_acquisition(args.file)
    dist, snr = range_waveforms(x, phase, setup, args.modality, pre)
    std = np.where(np.isfinite(dist), distance_std_mm(setup, args.modality, snr), np.nan)
    if args.json:
        print(json.dumps({"shot_id": ids.tolist(), "distance_mm": [
            None if np.isnan(v) else v for v in dist.tolist()], "distance_std_mm": [
            None if np.isnan(v) else v for v in std.tolist()], "snr_db": snr.tolist()}))
    else:
        for i, v, sd, s in zip(ids, dist, std, snr):
            print(f"{i:6d} {'no reading' if np.isnan(v) else f'{v:10.4f} ± {sd:.4f} mm'}  "
                  f"SNR {s:5.1f} dB")
        good = dist[np.isfinite(dist)]
        if good.size:
            print(f"{good.size} of {len(dist)} shots: mean {good.mean():.4f} mm, "
                  f"std {good.std():.4f} mm")
    return 0
