"""Scanning benchmark: step-and-shoot points per second (wall and simulated time) with the
Chiron's motion limits, split by phase, and the aluminium block's reconstruction error per
modality next to the paper's (0.06 +/- 0.06 mm OA, 0.15 +/- 0.11 mm US).

The emulator runs in this process on pseudo-terminals; `--speed 1` ties simulated time to
the wall clock (what hardware would do), larger values run the emulator faster.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from dmdsm.host.commands.cli import main as dmdsm
from dmdsm.host.links.sensor import SensorClient
from dmdsm.host.links.stage import StageClient
from dmdsm.host.ranging.procedure import calibrate_range
from dmdsm.host.scan.plan import ScanPlan
from dmdsm.host.scan.points import scan_points, validate_block
from dmdsm.host.scan.scanfile import read_scan
from dmdsm.sim.servers.pty_server import PtyServer
from dmdsm.sim.servers.runner import SimConfig, Simulation

PAPER = {"oa": (0.06, 0.06), "us": (0.15, 0.11)}


def run(speed: float, levels: str, step: float, out: Path) -> dict:
    """One block scan against a fresh emulator; returns the figures."""
    sim = Simulation(SimConfig(scene="aluminium_block", seed=11))
    server = PtyServer(sim, speed=speed)
    th = threading.Thread(target=server.serve_forever, daemon=True)
    th.start()
    S, T = server.ports["sensor"].name_for_host, server.ports["stage"].name_for_host
    try:
        st, sc = StageClient(T), SensorClient(S)
        st.home()
        st.move(x=235, y=266, z=20, wait=True)
        st.wait()
        setup, _ = calibrate_range(st, sc, {"X": 235, "Y": 266, "Z": 20},
                                   sim.truth()["distance_mm"], steps=11, step_mm=1.0,
                                   shots=2, fit_c=False, lateral=5)
        st.close()
        sc.close()
        setup.save(out / "ranging.json")
        s = sim.scene
        (out / "cal.toml").write_text(
            f"[calibration]\nv = {(s.v / np.linalg.norm(s.v)).tolist()}\n"
            f"n = {(s.n / np.linalg.norm(s.n)).tolist()}\nX_R = {s.X_R.tolist()}\n")
        plan = ScanPlan("aluminium_block", "aluminium", radius_mm=30.0, height_mm=40.0,
                        levels_mm=json.loads(levels), half_width_mm=32.0, step_mm=step)
        (out / "plan.toml").write_text(plan.to_toml())
        sim_t0 = sim.t
        buf = io.StringIO()
        with contextlib.redirect_stdout(buf):
            rc = dmdsm(["scan", "--sensor", S, "--stage", T, "--calibration",
                        str(out / "cal.toml"), "--ranging", str(out / "ranging.json"),
                        "--plan", str(out / "plan.toml"), "--db", str(out / "db"), "--json"])
        sim_dt = sim.t - sim_t0
    finally:
        server.stop()
        th.join(5)
    if rc != 0:
        raise SystemExit(f"scan failed ({rc})")
    summary = json.loads(buf.getvalue().splitlines()[-1])
    scan = read_scan(Path(summary["file"]), waveforms=False)
    fits = validate_block(scan_points(scan), (50.0, 30.0))
    summary["sim_s"] = sim_dt
    summary["fits"] = fits
    return summary


def main() -> int:
    """Print the figures; exit 1 if the reconstruction is worse than the paper."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--speed", type=float, nargs="+", default=[1.0, 5.0])
    ap.add_argument("--levels", default="[12.0, 24.0]")
    ap.add_argument("--step", type=float, default=2.0)
    args = ap.parse_args()
    ok = True
    for speed in args.speed:
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            r = run(speed, args.levels, args.step, Path(tmp))
            wall = time.perf_counter() - t0
        n = r["stored_now"]
        print(f"emulator speed x{speed:g}: {n} points, scan {r['wall_s']:.1f} s wall "
              f"({n / r['wall_s']:.2f} points/s), {r['sim_s']:.1f} s simulated "
              f"({n / r['sim_s']:.2f} points/s of machine time); bench total {wall:.0f} s")
        print("  per point (ms): " + ", ".join(f"{k} {v:.1f}"
                                              for k, v in r["ms_per_point"].items()))
        for m, (pm, ps) in PAPER.items():
            f = r["fits"][m]
            good = f["e_mean_mm"] <= pm + 3 * f["e_std_mm"] / np.sqrt(f["n"])
            ok &= bool(good)
            print(f"  {m.upper()}: e = {f['e_mean_mm']:.3f} +/- {f['e_std_mm']:.3f} mm over "
                  f"{f['n']} points (paper {pm:.2f} +/- {ps:.2f}) {'ok' if good else 'WORSE'}"
                  f"  [true v, n, X_R]")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
