"""`dmdsm live`: every waveform as ROS 2 messages, served over Foxglove's WebSocket and/or
recorded to MCAP, until Ctrl-C, --duration or --count; then a short summary."""

from __future__ import annotations

import argparse
import contextlib
import json
import signal
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import closing
from pathlib import Path

import numpy as np

from ..links.config import load_config, resolve_port
from .errors import CliError, Terminated, check_setting
from .options import CONFIG_HELP, SENSOR_HELP, add_waveform_config


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register `dmdsm live`."""
    p = sub.add_parser("live", help="stream distances, materials and waveforms as ROS 2 "
                                    "messages (Foxglove WebSocket, MCAP)")
    p.add_argument("--sensor", help=SENSOR_HELP)
    p.add_argument("--config", type=Path, default=None, help=CONFIG_HELP)
    p.add_argument("--ranging", type=Path, default=None,
                   help="ranging calibration (from `dmdsm calibrate-range`): distances per "
                        "modality with sigma and SNR (default: waveforms only)")
    p.add_argument("--model", type=Path, default=None,
                   help="material model (from `dmdsm model train`; needs --ranging)")
    p.add_argument("--serve", metavar="HOST:PORT", default=None,
                   help="serve the Foxglove WebSocket protocol here (e.g. 127.0.0.1:8765; "
                        "loopback only unless --allow-remote)")
    p.add_argument("--allow-remote", action="store_true",
                   help="let --serve listen on an address other machines can reach")
    p.add_argument("--mcap", type=Path, default=None,
                   help="also record the messages to this MCAP file (replaced if it exists)")
    p.add_argument("--bag", type=Path, metavar="DIR", default=None,
                   help="record instead as a ROS 2 bag folder `ros2 bag` (Humble) opens: "
                        "DIR/DIR_0.mcap, and DIR/metadata.yaml at the end")
    add_waveform_config(p)
    end = p.add_mutually_exclusive_group()
    end.add_argument("--duration", type=float, default=None, help="stop after S seconds")
    end.add_argument("--count", type=int, default=None, help="stop after N waveforms")
    p.add_argument("--json", action="store_true", help="the summary as JSON")
    p.set_defaults(func=cmd_live)


def summary(recs: int, lost: int, skipped: int, span_s: float, latency_s: list[float],
            stamp_std_s: list[float], server: object | None) -> dict:
    """The run in figures: records, lost, rate (/s over span_s, first to last record),
    laser edge to record on the host's clock and stamp sigma (ms)."""
    lat = np.array(latency_s) * 1e3
    out = {"records": recs, "lost": lost, "triggers_skipped": skipped,
           "rate_per_s": round((recs - 1) / span_s, 2) if span_s > 0 else 0.0,
           "latency_ms_p50": round(float(np.percentile(lat, 50)), 2) if recs else None,
           "latency_ms_p99": round(float(np.percentile(lat, 99)), 2) if recs else None,
           "stamp_std_ms": round(float(np.median(stamp_std_s)) * 1e3, 3) if recs else None}
    if server is not None and server.recording_stopped:
        out["recording_stopped"] = server.recording_stopped
    return out


@contextlib.contextmanager
def ctrl_c_between_records() -> Iterator[list[bool]]:
    """Ctrl-C that lands while a record is being published (and recorded) is held until
    that record is whole, so the MCAP always ends with its summary: yields a flag list; set
    flag[0] while publishing; a Ctrl-C then sets flag[1] and the caller stops after the
    record. A Ctrl-C anywhere else (waiting on the board) raises at once."""
    state = [False, False]  # publishing, Ctrl-C held
    if threading.current_thread() is not threading.main_thread():
        yield state
        return

    def on_int(signum: int, frame: object) -> None:
        if state[0] and not state[1]:
            state[1] = True
            return
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGINT, on_int)
    try:
        yield state
    finally:
        signal.signal(signal.SIGINT, previous)


def cmd_live(args: argparse.Namespace) -> int:
    """Arm the board continuously; publish every record until the end condition or Ctrl-C
    (which ends the run normally: the board disarmed, the MCAP closed, the summary)."""
    from ..files import check_output
    from ..ranging.calibrate import RangingSetup
    from ..robotics import bag_metadata as bags
    from ..robotics.live import live
    from ..robotics.mcap_file import McapRecorder
    from ..robotics.server import LiveServer, ServeError, parse_serve

    check_setting("--samples", "n_samples", args.samples)
    check_setting("--average", "n_average", args.average)
    if args.count is not None and args.count <= 0:
        raise CliError("--count must be positive")
    if args.duration is not None and not args.duration > 0:
        raise CliError("--duration must be positive (seconds)")
    if args.model is not None and args.ranging is None:
        raise CliError("--model needs --ranging (the material is read where the pulses are)")
    try:
        host, port = parse_serve(args.serve, args.allow_remote) if args.serve else (None, 0)
        setup = RangingSetup.load(args.ranging) if args.ranging else None
    except ServeError as e:
        raise CliError(str(e)) from None
    except ValueError as e:
        raise CliError(f"{e}; run `dmdsm calibrate-range` first") from None
    if args.mcap is not None and args.bag is not None:
        raise CliError("--mcap FILE and --bag DIR both record the messages: give one")
    if args.mcap is not None:
        check_output(args.mcap, True, "--mcap")
    if args.bag is not None:
        args.mcap = bags.bag_file(args.bag)  # checked here; the folder is made below
    from ..links.sensor import SensorClient

    sc = SensorClient(resolve_port("sensor", args.sensor, load_config(args.config)))
    server = recorder = bag_error = None
    try:
        cfg = {k: v for k, v in (("n_average", args.average), ("n_samples", args.samples))
               if v is not None}
        if cfg:
            sc.configure(**cfg)
        fs = float(sc.identity.adc_rate_hz) / sc.request("get_config").sample_rate_div
        if args.bag is not None:
            bags.make_bag_dir(args.bag)
            bags.drop_metadata(args.bag)  # it described the file about to be replaced
        if args.mcap is not None:
            recorder = McapRecorder(args.mcap, force=True, flag="--bag" if args.bag else "--mcap",
                                    metadata={"source": "dmdsm live", "sensor": sc.port_name})
        try:
            server = LiveServer(host, port, allow_remote=args.allow_remote, sample_rate_hz=fs,
                                model_name=args.model.name if args.model else "",
                                recorder=recorder)
        except ServeError as e:
            raise CliError(str(e)) from None
        if host is not None:
            print(f"dmdsm live: serving ws://{host}:{server.port} (Foxglove: open "
                  f"connection, Foxglove WebSocket)", file=sys.stderr)
        n = gaps = 0
        last, first_s = None, 0.0
        latency, stds = [], []
        t0 = time.monotonic()
        end = t0 + args.duration if args.duration else None
        try:
            with ctrl_c_between_records() as held, closing(live(sc, setup, args.model)) \
                    as records:
                for rec in records:
                    n, gaps, last = n + 1, gaps + rec.lost_before, rec
                    first_s = rec.received_s if n == 1 else first_s
                    held[0] = True
                    server.publish(rec)
                    held[0] = False
                    latency.append(time.monotonic() - rec.host_s)
                    stds.append(rec.host_std_s)
                    if held[1]:  # Ctrl-C came while publishing: the record is whole
                        print("", file=sys.stderr)
                        break
                    if (args.count and n >= args.count) or (end and rec.received_s >= end):
                        break
                    if server.recording_stopped and host is None:
                        break  # recording was all this run did
        except KeyboardInterrupt as e:
            if isinstance(e, Terminated):
                raise
            print("", file=sys.stderr)  # after the ^C
        lost = gaps + (last.device_lost if last else 0)
        skipped = last.counters.get("triggers_skipped", 0) if last else 0
        span = last.received_s - first_s if last is not None and n > 1 else 0.0
        out = summary(n, lost, skipped, span, latency, stds, server)
    finally:
        if server is not None:
            server.close()
        if recorder is not None:
            recorder.finish()
            bag_error = _bag_metadata(args.bag, args.mcap) if args.bag is not None else None
        sc.close()
    if args.mcap is not None:
        out["mcap"] = str(args.mcap)
    if args.bag is not None:
        out["bag"] = str(args.bag)
        if bag_error:
            out["bag_error"] = bag_error
            print(f"dmdsm live: {bag_error}", file=sys.stderr)
    if args.json:
        print(json.dumps(out))
    else:
        print(f"{out['records']} records, {out['lost']} lost, {out['rate_per_s']:.1f}/s; "
              f"first laser edge to record (averaging and wire included) p50 "
              f"{out['latency_ms_p50']} ms, p99 {out['latency_ms_p99']} "
              f"ms; stamp sigma {out['stamp_std_ms']} ms"
              + (f"; recorded to {args.mcap}" if args.mcap else "")
              + (f" (ROS 2 bag {args.bag})" if args.bag else ""))
        if out.get("recording_stopped"):
            print(f"dmdsm live: {out['recording_stopped']}", file=sys.stderr)
    return 0


def _bag_metadata(bag: Path, mcap: Path) -> str | None:
    """Write the bag's metadata.yaml for its finished MCAP file; None, or the one line saying
    why it could not be (the MCAP stays readable: `ros2 bag reindex` makes one)."""
    from ..files import OutputError
    from ..robotics.bag_metadata import write_bag_metadata

    try:
        write_bag_metadata(bag, mcap)
    except OutputError as e:
        return str(e)
    return None
