"""Emulator cost: CPU seconds per simulated second while a fly line streams, and while idle.

The SIL emulator must keep up with the wall clock at `--speed 1` for the fly figures of
bench/scan.py to be the stage's and not the emulator's: one core per simulated second is the
limit, and the host needs the other. Runs the Simulation in this process (no ptys): home,
move to the block, arm continuously (1 kHz, 1024 samples, average 12) and run X at 83 mm/s,
the block plan's fly speed.
"""

from __future__ import annotations

import argparse
import sys
import time

from dmdsm.protocol import Message, encode_frame
from dmdsm.sim.servers.runner import SimConfig, Simulation


def cpu_per_sim_s(sim: Simulation, seconds: float, chunk_s: float) -> float:
    """Advance `seconds` of simulated time in chunks (as the pty server does); CPU s per s."""
    t0, s0 = time.process_time(), sim.t
    for _ in range(round(seconds / chunk_s)):
        sim.advance(chunk_s)
        sim.read("stage")
        sim.read("sensor")
    return (time.process_time() - t0) / (sim.t - s0)


def main() -> int:
    """Print the figures; exit 1 if a fly line costs a core or more per simulated second."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=3.0, help="simulated seconds of line")
    args = ap.parse_args()
    sim = Simulation(SimConfig(scene="aluminium_block", seed=3))
    sim.write("stage", b"G28\n")
    cpu_per_sim_s(sim, 12.0, 0.005)
    sim.write("stage", b"G1 X60 Y266 Z32 F12000\n")
    idle = cpu_per_sim_s(sim, 3.0, 0.005)
    sim.write("sensor", encode_frame(Message(
        "set_config", seq=1, n_samples=1024, sample_rate_div=1, n_average=12, pretrigger=64,
        trigger_edge=0, modality=0, sample_format=0, trigger_timeout_ms=0)))
    sim.write("sensor", encode_frame(Message("arm", seq=2, n_shots=0)))
    length = 83.3 * args.seconds
    sim.write("stage", f"G1 X{60 + length:.1f} F5000\n".encode())
    shots0 = sim.sensor.shots
    fly = cpu_per_sim_s(sim, args.seconds, 0.005)
    shots = sim.sensor.shots - shots0
    print(f"idle stage moving, core not armed: {idle:.3f} CPU s per simulated s")
    print(f"fly line ({shots} shots at 1 kHz over {args.seconds:g} s, X at 83 mm/s): "
          f"{fly:.3f} CPU s per simulated s ({fly / max(shots, 1) * args.seconds * 1e3:.3f} "
          f"ms per shot); real time needs < 1")
    return 0 if fly < 1.0 else 1


if __name__ == "__main__":
    sys.exit(main())
