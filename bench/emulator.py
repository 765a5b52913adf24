"""Emulator cost: CPU seconds per simulated second while a fly line streams, and while idle.

The SIL emulator must keep up with the wall clock at `--speed 1` for the fly figures of
bench/scan.py to be the stage's and not the emulator's: one core per simulated second is the
limit, and the host needs the other. Runs the Simulation in this process (no ptys): home,
move to the block, arm continuously (1 kHz, 1024 samples, average 12) and run X at 83 mm/s,
the block plan's fly speed. Then the same line on the same block made of a mesh of 131 072
triangles (issue 31: objects from meshes, cast by Embree), and on the filled glass bottle of the
mesh household set (a mesh cast through to the surfaces inside it).
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np
import trimesh

from dmdsm.protocol import Message, encode_frame
from dmdsm.sim.physics.mesh import Mesh
from dmdsm.sim.physics.objects import BLOCK_SIZE_MM
from dmdsm.sim.physics.scene import SceneObject
from dmdsm.sim.servers.runner import SimConfig, Simulation


def cpu_per_sim_s(sim: Simulation, seconds: float, chunk_s: float) -> float:
    """Advance `seconds` of simulated time in chunks (as the pty server does); CPU s per s."""
    t0, s0 = time.process_time(), sim.t
    for _ in range(round(seconds / chunk_s)):
        sim.advance(chunk_s)
        sim.read("stage")
        sim.read("sensor")
    return (time.process_time() - t0) / (sim.t - s0)


def mesh_block(max_edge_mm: float = 0.7) -> SceneObject:
    """The aluminium block as a mesh: its faces cut into triangles of edges up to max_edge_mm
    (0.7 mm: 131 072 triangles)."""
    box = trimesh.creation.box(extents=BLOCK_SIZE_MM)
    v, f = trimesh.remesh.subdivide_to_size(box.vertices, box.faces, max_edge=max_edge_mm)
    mesh = trimesh.Trimesh(v, f)
    return SceneObject("aluminium_block_mesh", "aluminium",
                       Mesh(center=np.array([0.0, 0.0, BLOCK_SIZE_MM[2] / 2]), mesh=mesh))


def fly_line(cfg: SimConfig, seconds: float, y: float = 266.0, z: float = 32.0
             ) -> tuple[float, float, int]:
    """(idle, fly) CPU s per simulated s and the shots of one fly line on cfg's scene, the
    sensor at y, z (mm): 7-8 mm in front of the block's face by default."""
    sim = Simulation(cfg)
    sim.write("stage", b"G28\n")
    cpu_per_sim_s(sim, 12.0, 0.005)
    sim.write("stage", f"G1 X60 Y{y:g} Z{z:g} F12000\n".encode())
    idle = cpu_per_sim_s(sim, 3.0, 0.005)
    sim.write("sensor", encode_frame(Message(
        "set_config", seq=1, n_samples=1024, sample_rate_div=1, n_average=12, pretrigger=64,
        trigger_edge=0, modality=0, sample_format=0, trigger_timeout_ms=0)))
    sim.write("sensor", encode_frame(Message("arm", seq=2, n_shots=0)))
    length = 83.3 * seconds
    sim.write("stage", f"G1 X{60 + length:.1f} F5000\n".encode())
    shots0 = sim.sensor.shots
    fly = cpu_per_sim_s(sim, seconds, 0.005)
    return idle, fly, sim.sensor.shots - shots0


def main() -> int:
    """Print the figures; exit 1 if a fly line costs a core or more per simulated second."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=3.0, help="simulated seconds of line")
    args = ap.parse_args()
    idle, fly, shots = fly_line(SimConfig(scene="aluminium_block", seed=3), args.seconds)
    print(f"idle stage moving, core not armed: {idle:.3f} CPU s per simulated s")
    worst = fly
    runs = [("aluminium_block (analytic box)", fly, shots)]
    block = mesh_block()
    _, fly_m, shots_m = fly_line(SimConfig(scene="empty", seed=3, objects=[block]),
                                 args.seconds)
    runs.append((f"the block as a mesh of {len(block.shape.mesh.faces)} triangles", fly_m,
                 shots_m))
    _, fly_b, shots_b = fly_line(SimConfig(scene="glass_bottle", seed=3), args.seconds,
                                 y=245.0, z=80.0)  # 8 mm in front of the bottle
    runs.append(("glass_bottle (mesh, water inside, cast through)", fly_b, shots_b))
    for name, cost, n in runs:
        worst = max(worst, cost)
        per_shot = cost / max(n, 1) * args.seconds * 1e3
        print(f"fly line on {name} ({n} shots at 1 kHz over {args.seconds:g} s, X at 83 "
              f"mm/s): {cost:.3f} CPU s per simulated s ({per_shot:.3f} ms per shot); real "
              "time needs < 1")
    return 0 if worst < 1.0 else 1


if __name__ == "__main__":
    sys.exit(main())
