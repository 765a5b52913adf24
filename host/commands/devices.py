"""`dmdsm ports | info | acquire | stage`: the boards from the terminal, each with --json."""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from dmdsm.marlin_patch import load_machine

from ..files import atomic_output
from ..links.config import load_config, resolve_port
from ..links.link_rate import link_rate
from .errors import check_output
from .options import CONFIG_HELP, SENSOR_HELP, STAGE_HELP, add_waveform_config

ROLES = {  # USB VID:PID -> guessed role
    "0483:374b": "sensor (NUCLEO-H743ZI ST-LINK/V2-1 VCP)",
    "0483:374e": "sensor (NUCLEO-H743ZI2 STLINK-V3 VCP)",
    "0483:374f": "sensor (STLINK-V3 VCP)",
    "0483:3753": "sensor (STLINK-V3 VCP)",
    "0483:3754": "sensor (STLINK-V3 VCP)",
    "0483:5740": "sensor (STM32 USB CDC)",
    "1a86:7523": "stage (CH340, as on the Chiron's Trigorilla)",
    "2341:0042": "stage (Arduino Mega 2560)",
    "2341:0010": "stage (Arduino Mega 2560)",
}


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """Register ports, info, acquire and stage."""
    p = sub.add_parser("ports", help="list serial ports with a guessed role")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.set_defaults(func=cmd_ports)

    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--config", type=Path, default=None, help=CONFIG_HELP)
    common.add_argument("--json", action="store_true", help="machine-readable output")

    p = sub.add_parser("info", parents=[common], help="identify the sensor board")
    p.add_argument("--sensor", help=SENSOR_HELP)
    p.set_defaults(func=cmd_info)

    p = sub.add_parser("acquire", parents=[common], help="record shots into an HDF5 file")
    p.add_argument("--sensor", help=SENSOR_HELP)
    p.add_argument("--shots", type=int, required=True,
                   help="waveforms to record: exactly this many are written (required)")
    add_waveform_config(p)
    p.add_argument("-o", "--output", type=Path, required=True,
                   help="FILE.h5 to write (required; an existing file is kept unless --force)")
    p.add_argument("--force", action="store_true",
                   help="overwrite an existing --output (default: refuse)")
    p.set_defaults(func=cmd_acquire)

    p = sub.add_parser("stage", help="home, move, where, stop")
    # the options are taken before the action too (`dmdsm stage --stage P where`), under
    # their own names, since a subparser's defaults would overwrite them (cmd_stage merges)
    p.add_argument("--stage", dest="stage_first", help=argparse.SUPPRESS)
    p.add_argument("--config", dest="config_first", type=Path, help=argparse.SUPPRESS)
    p.add_argument("--json", dest="json_first", action="store_true", help=argparse.SUPPRESS)
    psub = p.add_subparsers(dest="action", required=True, metavar="ACTION")
    staged = argparse.ArgumentParser(add_help=False, parents=[common])
    staged.add_argument("--stage", help=STAGE_HELP)
    for action, text in (
            ("home", "home X, Y, Z (G28)"),
            ("where", "where the stage is now and whether it moves (M114 R)"),
            ("stop", "stop any move at once (M410), also one another dmdsm runs; return "
                     "once the stage stands")):
        psub.add_parser(action, parents=[staged], help=text)
    q = psub.add_parser("move", parents=[staged],
                        help="move, checked against the envelope and keep-out first")
    for axis, unit in (("x", "mm"), ("y", "mm"), ("z", "mm"), ("a", "deg")):
        q.add_argument(f"-{axis}", f"--{axis}", type=float,
                       help=f"target {axis.upper()} ({unit})")
    q.add_argument("--feed", type=float, default=3000, help="feedrate (mm/min)")
    q.add_argument("--relative", action="store_true", help="move by, not to")
    q.add_argument("--object-radius", type=float, default=0.0,
                   help="keep-out cylinder radius around the table axis (mm)")
    q.add_argument("--object-height", type=float, default=0.0, help="keep-out height (mm)")
    p.set_defaults(func=cmd_stage)


def _out(args: argparse.Namespace, obj: dict, text: str) -> None:
    print(json.dumps(obj) if args.json else text)


def cmd_ports(args: argparse.Namespace) -> int:
    """List serial ports, their USB ids, by-id names and guessed roles."""
    from serial.tools import list_ports

    by_id = {}
    d = Path("/dev/serial/by-id")
    if d.is_dir():
        by_id = {os.path.realpath(p): str(p) for p in d.iterdir()}
    rows = []
    for p in sorted(list_ports.comports(), key=lambda p: p.device):
        vidpid = f"{p.vid:04x}:{p.pid:04x}" if p.vid is not None else ""
        rows.append({"device": p.device, "by_id": by_id.get(os.path.realpath(p.device), ""),
                     "usb": vidpid, "description": p.description or "",
                     "serial_number": p.serial_number or "",
                     "role": ROLES.get(vidpid, "unknown")})
    if args.json:
        print(json.dumps(rows))
    elif not rows:
        print("no serial ports found (is the board plugged in? `dmdsm sim` makes virtual ones)")
    else:
        for r in rows:
            print(f"{r['device']:<16} {r['usb']:<10} {r['role']:<45} "
                  f"{r['by_id'] or r['description']}")
    return 0


def cmd_info(args: argparse.Namespace) -> int:
    """Identity, configuration and counters of the sensor board."""
    from ..links.sensor import SensorClient

    sc = SensorClient(resolve_port("sensor", args.sensor, load_config(args.config)))
    try:
        ident = {k: v for k, v in sc.identity.fields.items()}
        ident["spec_hash"] = f"{ident['spec_hash']:016x}"
        info = {"port": sc.port_name, "identity": ident,
                "config": dict(sc.request("get_config").fields), "status": sc.status()}
    finally:
        sc.close()
    cfg = info["config"]
    rate = link_rate(cfg["n_samples"], cfg["n_average"], cfg["sample_format"])
    info["link"] = {"wire_bytes": rate.wire_bytes, "waveforms_per_s": round(rate.waveforms_hz, 1),
                    "link_waveforms_per_s": round(rate.link_hz, 1), "limit": rate.limit,
                    "skipped_share": round(rate.skipped_share, 3)}
    i = info["identity"]
    _out(args, info, f"{info['port']}: {i['board']}, firmware {i['fw_major']}.{i['fw_minor']}."
         f"{i['fw_patch']}, protocol {i['protocol_version']}, spec {i['spec_hash']}\n"
         f"config: " + " ".join(f"{k}={v}" for k, v in info["config"].items()) + "\n"
         "status: " + " ".join(f"{k}={v}" for k, v in info["status"].items()) + "\n"
         f"link: {rate.text()}")
    return 0


def write_shots(path: Path, shots: object, identity: dict, port: str,
                status: str = "complete", force: bool = True) -> None:
    """HDF5, NeXus-like: /entry/instrument/sensor, /entry/data/waveforms (n, n_samples);
    status "interrupted" keeps only the shots that arrived. Atomic (files.atomic_output): a
    failed write leaves the earlier file, or nothing."""
    import h5py

    with atomic_output(path, force=force) as tmp, h5py.File(tmp, "w") as f:
        f.attrs.update(format_name="dmdsm-shots", format_version="1", default="entry")
        e = f.create_group("entry")
        e.attrs.update(NX_class="NXentry", default="data", created=time.strftime("%FT%T%z"),
                       status=status)
        s = e.create_group("instrument").create_group("sensor")
        s.attrs.update(NX_class="NXdetector", port=port,
                       **{k: v for k, v in identity.items() if k != "spec_hash"},
                       spec_hash=f"{identity['spec_hash']:016x}")
        s.attrs.update({f"config_{k}": v for k, v in shots.config.items()})
        d = e.create_group("data")
        d.attrs.update(NX_class="NXdata", signal="waveforms")
        d.create_dataset("waveforms", data=shots.samples, chunks=(1, shots.samples.shape[1]),
                         compression="gzip", compression_opts=1)
        for name in ("received", "timestamp", "trigger_phase", "n_average"):
            d.create_dataset(name, data=getattr(shots, name))
        d.create_dataset("shot_id", data=np.arange(len(shots.received)))
        d.attrs.update(triggers_skipped=getattr(shots, "triggers_skipped", 0),
                       adc_overruns=getattr(shots, "adc_overruns", 0),
                       integrity_faults=getattr(shots, "integrity_faults", 0),
                       link_rejected=getattr(shots, "link_rejected", 0),
                       lost=len(shots.lost))


def cmd_acquire(args: argparse.Namespace) -> int:
    """Arm for N shots with a progress bar, then write them and report losses."""
    from tqdm import tqdm

    from ..links.sensor import AcquisitionInterrupted, AcquisitionLost, SensorClient
    from .errors import CliError, check_setting

    if args.shots <= 0:
        raise CliError("--shots must be positive")
    check_setting("--samples", "n_samples", args.samples)
    check_setting("--average", "n_average", args.average)
    check_output(args.output, keep_existing=not args.force)  # before anything is measured
    sc = SensorClient(resolve_port("sensor", args.sensor, load_config(args.config)))
    try:
        cfg = {k: v for k, v in (("n_average", args.average), ("n_samples", args.samples))
               if v is not None}
        if cfg:
            sc.configure(**cfg)
        with tqdm(total=args.shots, unit="shot", disable=args.json) as bar:
            def progress(n: int) -> None:
                bar.update(n - bar.n)
            try:
                shots = sc.acquire(args.shots, progress=progress)
            except AcquisitionInterrupted as e:  # the board is disarmed: keep what arrived
                got = int(e.shots.received.sum())
                write_shots(args.output, e.shots, dict(sc.identity.fields), sc.port_name,
                            status="interrupted", force=args.force)
                print(f"\ndmdsm: acquisition stopped after {got} of {args.shots} shots; they "
                      f"are saved in {args.output}", file=sys.stderr)
                raise
            except AcquisitionLost as e:  # the cable, not the user: keep what arrived too
                write_shots(args.output, e.shots, dict(sc.identity.fields), sc.port_name,
                            status="interrupted", force=args.force)
                raise CliError(f"{e}; they are saved in {args.output}") from None
        write_shots(args.output, shots, dict(sc.identity.fields), sc.port_name,
                    force=args.force)
    finally:
        sc.close()
    got = int(shots.received.sum())
    rate = link_rate(shots.config["n_samples"], shots.config["n_average"],
                     shots.config["sample_format"])
    summary = {"file": str(args.output), "shots": args.shots, "received": got,
               "lost": int(len(shots.lost)), "link_rejected": shots.link_rejected,
               "adc_overruns": shots.adc_overruns, "integrity_faults": shots.integrity_faults,
               "triggers_skipped": shots.triggers_skipped,
               "waveforms_per_s": round(rate.waveforms_hz, 1)}
    text = (f"wrote {args.output}: {got} of {args.shots} shots; lost {len(shots.lost)} (link "
            f"rejected {shots.link_rejected} frames, ADC overruns {shots.adc_overruns}, "
            f"integrity faults {shots.integrity_faults})")
    if shots.triggers_skipped:  # by design: the laser outpaces the link at these settings
        summary["hint"] = rate.text()
        text += (f"\nthe board skipped {shots.triggers_skipped} laser shots while the link was "
                 f"busy; {summary['hint']}")
    _out(args, summary, text)
    return 0


def cmd_stage(args: argparse.Namespace) -> int:
    """Home, move (checked against the envelope and keep-out first), where, stop."""
    from ..links.stage import StageClient

    args.stage = args.stage or args.stage_first
    args.config = args.config or args.config_first
    args.json = args.json or args.json_first
    config = load_config(args.config)
    port = resolve_port("stage", args.stage, config)
    if args.action == "stop":
        return _stop(args, port)
    st = StageClient(port)
    try:
        if args.action == "home":
            pos = st.home()
        elif args.action == "where":
            return _where(args, st)
        else:
            pos = _move(st, args, config)
    except KeyboardInterrupt:
        st.stop()  # Ctrl-C during motion: quick-stop, port stays usable
        raise
    finally:
        st.close()
    _out(args, pos, " ".join(f"{k}:{v:.3f}" for k, v in pos.items()))
    return 0


def _where(args: argparse.Namespace, st: object) -> int:
    """Where the steppers are now and whether the stage moves (M114 R)."""
    if st.busy_at_connect:  # Marlin reads nothing new until an earlier client's moves end
        _out(args, {"moving": True, "earlier_client": True},
             "moving: the stage is still running moves an earlier connection queued; "
             "`dmdsm stage stop` stops them, `dmdsm stage where` says where once they end")
        return 0
    pos, moving = st.live()
    _out(args, {**pos, "moving": moving},
         " ".join(f"{k}:{v:.3f}" for k, v in pos.items()) +
         (" moving" if moving else " standing"))
    return 0


def _stop(args: argparse.Namespace, port: str) -> int:
    """Stop the stage whoever holds its port: this process opens it and quick-stops before
    anything else (a killed client's moves keep running), or asks the dmdsm process that
    holds it (stage_control) to stop and waits for its proof that the stage stands."""
    from ..links import stage_control
    from ..links.stage import StageClient
    from ..links.transport import LinkError
    from .errors import CliError

    t0 = time.monotonic()
    try:
        st = StageClient(port, stop_first=True)
    except LinkError as e:
        if "in use by another program" not in str(e):
            raise
        try:
            pid, where = stage_control.request_stop(port)
        except stage_control.NoOwner:
            raise CliError(f"{port} is held by a program that is not dmdsm (OctoPrint, a "
                           f"terminal?): stop the stage there") from None
        except RuntimeError as e2:
            raise CliError(str(e2)) from None
        pos = {k: float(v) for k, v in (w.split(":") for w in where.split())}
        _out(args, {**pos, "moving": False, "stopped_in_pid": pid,
                    "seconds": round(time.monotonic() - t0, 3)},
             f"stopped (the move of dmdsm pid {pid}); standing at {where}")
        return 0
    try:
        pos = st.stop()
    finally:
        st.close()
    _out(args, {**pos, "moving": False, "seconds": round(time.monotonic() - t0, 3)},
         "stopped; standing at " + " ".join(f"{k}:{v:.3f}" for k, v in pos.items()))
    return 0


MAX_TURNS = 100  # the turntable axis A: |A| beyond this many turns is a typing error


def _move(st: object, args: argparse.Namespace, config: dict) -> dict:
    """Check the move against the envelope and the keep-out, then move and wait."""
    from ..links.safety import TABLE_I, KeepOut, check_move

    here = st.where()
    target = dict(here)
    for axis in "XYZA":
        v = getattr(args, axis.lower())
        if v is not None:
            target[axis] = here[axis] + v if args.relative else v
    if abs(target["A"]) > MAX_TURNS * 360.0:  # A has no endstop and no soft limit
        from .errors import CliError

        raise CliError(f"A {target['A']:g} deg is more than {MAX_TURNS} turns from the "
                       f"turntable's zero: move it less (or `G92 A0` to re-zero it)")
    cal = config.get("calibration", {})
    keep = KeepOut(np.asarray(cal.get("X_R", TABLE_I["X_R"]), float),
                   np.asarray(cal.get("n", TABLE_I["n"]), float),
                   args.object_radius, args.object_height)
    check_move(np.array([here[a] for a in "XYZ"]), np.array([target[a] for a in "XYZ"]),
               load_machine(), keep)
    st.move(x=target["X"], y=target["Y"], z=target["Z"], a=target["A"],
            feed_mm_min=args.feed)
    st.wait()
    return st.where()
