"""Link benchmark: shots/s and MB/s from the emulated sensor into numpy, host CPU per shot,
and G-code commands/s through the stage client. The emulator runs as its own process
(`dmdsm sim`), so this process's CPU time is the host side alone.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time

from dmdsm.host.links.sensor import SensorClient
from dmdsm.host.links.stage import StageClient


def start_sim(*args: str) -> tuple[subprocess.Popen, dict]:
    """`dmdsm sim --json ARGS` in a child process; returns it and its ports."""
    p = subprocess.Popen([sys.executable, "-m", "dmdsm.host", "sim", "--json", *args],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    return p, json.loads(p.stdout.readline())


def stop(p: subprocess.Popen) -> None:
    """Ctrl-C the emulator."""
    p.send_signal(signal.SIGINT)
    p.communicate(timeout=10)


def sensor_rate(n_samples: int, rep_rate: float, shots: int) -> None:
    """Stream `shots` un-averaged waveforms over a fast link and time the host side."""
    p, ports = start_sim("--rep-rate", str(rep_rate), "--sensor-link", "40000000")
    try:
        sc = SensorClient(ports["sensor"])
        sc.configure(n_samples=n_samples, n_average=1)
        t0, c0 = time.perf_counter(), time.process_time()
        got = sc.acquire(shots, timeout_s=120)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        n = int(got.received.sum())
        mb = n * (2 * n_samples + 41) / wall / 1e6
        print(f"sensor {n_samples:5d} samples: {n / wall:8.1f} shots/s delivered, "
              f"{mb:6.2f} MB/s, host CPU {cpu / max(n, 1) * 1e6:7.1f} us/shot "
              f"({100 * cpu / wall:4.1f} % of one core); lost {len(got.lost)} "
              f"(board skipped {got.triggers_skipped} triggers); emulator laser {rep_rate:g}/s")
        sc.close()
    finally:
        stop(p)


def stage_rate(n: int) -> None:
    """G-code lines/s: tiny relative moves (windowed) and M105 round trips (one at a time)."""
    p, ports = start_sim("--speed", "100")
    try:
        st = StageClient(ports["stage"])
        st.send("G91")
        t0 = time.perf_counter()
        for i in range(n):
            st.send(f"G1 X{0.01 * ((i % 7) - 3):.4f} F6000", wait=False)
        st.drain()
        moves = n / (time.perf_counter() - t0)
        t0 = time.perf_counter()
        for _ in range(n // 4):
            st.send("M105")
        rtt = (n // 4) / (time.perf_counter() - t0)
        print(f"stage: {moves:8.1f} G1 lines/s windowed (emulator at 100x), "
              f"{rtt:8.1f} M105 round trips/s; resends {st.stats.resent}, "
              f"probes {st.stats.probes}")
        st.close()
    finally:
        stop(p)


def main() -> int:
    """Print the figures."""
    sensor_rate(1024, 2000, 4000)
    sensor_rate(8192, 300, 600)
    stage_rate(4000)
    return 0


if __name__ == "__main__":
    sys.exit(main())
