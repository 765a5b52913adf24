"""`dmdsm live` against the emulator: records/s, losses, latency, CPU and stamp error.

    python bench/live.py [--minutes 10] [--quick] [--pin] [--rate link|averaging]

The emulator runs in a child process (as `dmdsm sim` would: its physics does not share the
host's interpreter lock; with --pin on a core of its own, as the board's processor is not
the host's), real time, 7 mm in front of the aluminium block. Two rates, each
for --minutes: the link's limit (1024 samples, no averaging: the board skips the laser shots
it has no slot for, ~95 waveforms/s at 2 Mbaud) and on-board averaging (16 shots, 62.5/s).
Each: records/s, lost (shot-id gaps + the board's loss counters), latency p50/p99 from the
laser edge (the emulator's truth) to the record leaving the generator and to its last
message (/dmdsm/distance/us, after the waveform, the ranges and the OA distance) arriving
at a foxglove.websocket.v1 client in its own process (as Foxglove is), beyond the frame's
own time on the wire (at most 2110 bytes at 200 kB/s: `waveform_wire_bytes`), and from
the frame's last byte leaving the board (p50, p99 after the first second of the stream,
and that second's worst: the emulator's start-up); CPU per record (this process: reader,
ranging, encoding, server; not the client's); the host stamps against the truth (RMS z of
error / reported sigma). Beside it, the plain `acquire` path for as many waveforms.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import sys
import time
from contextlib import closing
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

LINK_BYTES_PER_S = 200_000.0
LAST_TOPIC = "/dmdsm/distance/us"  # a record's last message (no model): when it has left
REP_HZ = 1000.0


def emulator_child(conn: object, cpu: int | None = None) -> None:
    """Serve the emulator here until told to stop; send back its truth times. cpu: the one
    core it runs on (--pin), as the board's own processor is not the host's."""
    if cpu is not None:
        os.sched_setaffinity(0, {cpu})
    from live_helpers import EmulatorTimes

    from dmdsm.sim.servers.emulator import Emulator
    from dmdsm.sim.servers.runner import SimConfig

    emu = Emulator(SimConfig(seed=3), speed=1.0)
    times = EmulatorTimes(emu)
    emu.start()
    conn.send((emu.sensor, emu.stage))
    # the truth takes the receive lags of the rate being measured only: the emulator's loop
    # lags its pacing more when it computes every shot (averaging) than when it skips most
    start = 0
    while True:
        ask = conn.recv()
        if ask == "stop":
            break
        if ask == "start":
            start = len(times.lags)
            continue
        conn.send({"wall0": times.wall0, "sim0": times.sim0, "lag": float(np.median(
            times.lags[start:])), "sent": dict(times.sent), "tick_hz": times.tick_hz})
    emu.stop()


def truth(t: dict, ticks: np.ndarray) -> np.ndarray:
    """Host monotonic (s) of the laser edges at these device ticks (EmulatorTimes.laser_s)."""
    return t["wall0"] + (ticks / t["tick_hz"] - t["sim0"]) + t["lag"]


def client_child(url: str, conn: object) -> None:
    """A foxglove.websocket.v1 subscriber in its own process, as Foxglove or a controller
    is (SocketWsClient: one blocking socket, each arrival stamped as its recv returns):
    subscribes, reads until told how many records there were, then sends back the arrival
    times (host monotonic s, a clock shared by every process) of their last messages."""
    from live_helpers import SocketWsClient

    try:
        client = SocketWsClient(url)
    except (OSError, ConnectionError) as e:  # TimeoutError is an OSError
        print(f"the websocket client could not connect to {url}: {e}", file=sys.stderr)
        conn.send(False)
        return
    conn.send(True)
    got: list[float] = []
    n = None
    try:
        while n is None or len(got) < n:
            if n is None and conn.poll():
                n = conn.recv()
            new = client.read(LAST_TOPIC, 0.5)
            if new is None and n is not None:
                break  # the stream has ended short of n: what came is sent back
            got.extend(new or [])
    except ConnectionError:
        pass  # the server went away: what came is sent back
    if n is None:
        n = conn.recv()
    client.close()
    conn.send(got[:n])


def run_live(sensor: str, setup: object, n_average: int, seconds: float) -> dict:
    """One rate: live() into the server, a websocket client reading; the raw figures."""
    from dmdsm.host.links.sensor import SensorClient
    from dmdsm.host.robotics.live import live
    from dmdsm.host.robotics.server import LiveServer

    sc = SensorClient(sensor)
    sc.configure(n_samples=1024, n_average=n_average)
    srv = LiveServer("127.0.0.1", 0, sample_rate_hz=float(sc.identity.adc_rate_hz))
    ctx = mp.get_context("spawn")
    here, there = ctx.Pipe()
    reader = ctx.Process(target=client_child, args=(f"ws://127.0.0.1:{srv.port}", there),
                         daemon=True)
    reader.start()
    if not here.recv():
        raise SystemExit("the websocket client could not subscribe to the live server")
    recs, gen_t = [], []
    cpu0, t0 = time.process_time(), time.monotonic()
    with closing(live(sc, setup)) as g:
        for r in g:
            gen_t.append(time.monotonic())
            srv.publish(r)
            recs.append(r)
            if gen_t[-1] - t0 > seconds:
                break
    cpu, wall = time.process_time() - cpu0, time.monotonic() - t0
    here.send(len(recs))
    arrived = here.recv()
    reader.join(10)
    srv.close()
    sc.close()
    for r in recs:
        r.samples = None  # the figures need no samples
    return {"recs": recs, "gen_t": np.array(gen_t), "ws_t": np.array(arrived),
            "ws_n": len(arrived), "cpu": cpu, "wall": wall}


def run_acquire(sensor: str, n_average: int, n: int) -> dict:
    """The plain acquire path: n waveforms into numpy; rate, lost, CPU per waveform."""
    from dmdsm.host.links.sensor import SensorClient

    with SensorClient(sensor) as sc:
        sc.configure(n_samples=1024, n_average=n_average)
        cpu0, t0 = time.process_time(), time.monotonic()
        shots = sc.acquire(n, timeout_s=n / 20 + 30)
        cpu, wall = time.process_time() - cpu0, time.monotonic() - t0
    got = int(shots.received.sum())
    return {"waveforms": got, "lost": n - got + shots.adc_overruns + shots.integrity_faults,
            "rate_per_s": got / wall, "cpu_ms_per_waveform": cpu / max(got, 1) * 1e3}


def figures(raw: dict, t: dict, n_average: int) -> dict:
    """The figures of one rate from its raw results and the emulator's truth."""
    recs = raw["recs"]
    ticks = np.array([r.device_ticks for r in recs], dtype=float)
    laser = truth(t, ticks)
    last_edge = laser + (n_average - 1) / REP_HZ
    from dmdsm.host.links.link_rate import waveform_wire_bytes

    wire = waveform_wire_bytes(1024) / LINK_BYTES_PER_S  # within 10 B of the frame's own
    sent = np.array([t["sent"].get(r.device_ticks, np.nan) for r in recs])
    err = np.array([r.host_s for r in recs]) - laser
    std = np.array([r.host_std_s for r in recs])
    span = raw["gen_t"][-1] - raw["gen_t"][0]
    ws = raw["ws_t"][:len(recs)]
    steady = raw["gen_t"][:len(ws)] - raw["gen_t"][0] >= 1.0  # the start-up second apart

    def pct(x: np.ndarray) -> tuple[float, float, float]:
        """p50, p99 (ms) after the first second; the first second's worst (ms)."""
        x, first = x[steady[:len(x)]], x[~steady[:len(x)]]
        return (round(float(np.nanpercentile(x, 50)) * 1e3, 2),
                round(float(np.nanpercentile(x, 99)) * 1e3, 2),
                round(float(np.nanmax(first)) * 1e3, 1) if first.size else float("nan"))

    return {"records": len(recs), "rate_per_s": round((len(recs) - 1) / span, 1),
            "lost": sum(r.lost_before for r in recs) + recs[-1].device_lost,
            "triggers_skipped": recs[-1].counters["triggers_skipped"],
            "ws_received": raw["ws_n"],
            "generator_beyond_wire_ms": pct(raw["gen_t"] - last_edge - wire),
            "websocket_beyond_wire_ms": pct(ws - last_edge[:len(ws)] - wire),
            "generator_after_frame_ms": pct(raw["gen_t"] - sent),
            "websocket_after_frame_ms": pct(ws - sent[:len(ws)]),
            "cpu_ms_per_record": round(raw["cpu"] / len(recs) * 1e3, 3),
            "stamp_error_ms": (round(float(err.mean()) * 1e3, 3),
                               round(float(err.std()) * 1e3, 3)),
            "stamp_sigma_ms": round(float(np.median(std)) * 1e3, 3),
            "stamp_rms_z": round(float(np.sqrt(np.mean((err / std) ** 2))), 2)}


def main() -> None:
    """Run both rates and the acquire path; print the figures."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=10.0, help="per rate (default 10)")
    ap.add_argument("--quick", action="store_true", help="~30 s in all")
    ap.add_argument("--pin", action="store_true",
                    help="run the emulator on the last core alone, the host and the client "
                         "on the others (as the board's processor is not the host's)")
    ap.add_argument("--rate", choices=("link", "averaging"), action="append",
                    help="measure only this rate (repeatable; default both)")
    args = ap.parse_args()
    seconds = 10.0 if args.quick else args.minutes * 60
    from dmdsm.host.links.stage import StageClient
    from dmdsm.sim.data.dataset import true_setup
    from dmdsm.sim.physics.signals import SensorModel

    ctx = mp.get_context("spawn")
    here, there = ctx.Pipe()
    cores = sorted(os.sched_getaffinity(0))
    pin = cores[-1] if args.pin and len(cores) > 1 else None
    child = ctx.Process(target=emulator_child, args=(there, pin), daemon=True)
    child.start()
    sensor, stage = here.recv()
    if pin is not None:  # the host (and the client it starts) off the emulator's core
        os.sched_setaffinity(0, set(cores) - {pin})
    try:
        with StageClient(stage) as st:
            st.home()
            st.move(x=235, y=266, z=20, wait=True)
            st.wait()
        setup = true_setup(SensorModel())
        where = f"alone on core {pin}, the host on {sorted(set(cores) - {pin})}" \
            if pin is not None else "sharing the host's cores"
        print(f"dmdsm live bench: emulator in a child process ({where}), real time; "
              f"{seconds:.0f} s per rate")
        rates = {"link": ("link limit (1024 samples, no averaging)", 1),
                 "averaging": ("on-board averaging (16 shots)", 16)}
        for name, n_avg in (rates[r] for r in args.rate or rates):
            here.send("start")
            raw = run_live(sensor, setup, n_avg, seconds)
            here.send("times")
            f = figures(raw, here.recv(), n_avg)
            acq = run_acquire(sensor, n_avg, f["records"])
            print(f"\n{name}:")
            for k, v in f.items():
                print(f"  live {k:28s} {v}")
            for k, v in acq.items():
                print(f"  acquire {k:25s} {v:.3f}" if isinstance(v, float) else
                      f"  acquire {k:25s} {v}")
    finally:
        here.send("stop")
        child.join(10)


if __name__ == "__main__":
    main()
