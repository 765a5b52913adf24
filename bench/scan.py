"""Scanning benchmark: step and shoot against fly scanning, side by side on one plan and seed.

For each mode: points/s and wall time of the block scan, time per phase, the block's contour
error per modality next to the paper's (0.06 +/- 0.06 mm OA, 0.15 +/- 0.11 mm US), and the
error of every stored stage position along the line against the emulator's truth (the mean
X of the waveform's laser shots). The emulator runs in this process on pseudo-terminals with
`--speed 1` tying simulated time to the wall clock (what hardware does); the scans run as
`dmdsm scan` subprocesses, as a user runs them, so the two share no interpreter.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from dmdsm.host.links.sensor import SensorClient
from dmdsm.host.links.stage import StageClient
from dmdsm.host.ranging.procedure import calibrate_range
from dmdsm.host.scan.plan import ScanPlan
from dmdsm.host.scan.points import scan_points, validate_block
from dmdsm.host.scan.scanfile import read_scan
from dmdsm.sim.boards.sensor.core_board import TICK_HZ
from dmdsm.sim.servers.emulator import Emulator
from dmdsm.sim.servers.runner import SimConfig, Simulation

PAPER = {"oa": (0.06, 0.06), "us": (0.15, 0.11)}


def run(mode: str, speed: float, plan: ScanPlan, seed: int, out: Path) -> dict:
    """One block scan in `mode` against a fresh emulator; returns the figures."""
    sim = Simulation(SimConfig(scene="aluminium_block", seed=seed))
    shots: list[tuple[int, float]] = []
    pose = sim.pose

    def recording(t: float) -> tuple[np.ndarray, float]:
        S, theta = pose(t)
        shots.append((round(t * TICK_HZ), float(S[0])))
        return S, theta

    sim.sensor.pose = recording
    emu = Emulator(sim=sim, speed=speed).start()
    S, T = emu.sensor, emu.stage
    try:
        with StageClient(T) as st:
            st.home()
            st.move(x=235, y=266, z=20, wait=True)
            st.wait()
            sc = SensorClient(S)
            try:
                setup, _ = calibrate_range(st, sc, {"X": 235, "Y": 266, "Z": 20},
                                           sim.truth()["distance_mm"], steps=11, step_mm=1.0,
                                           shots=2, fit_c=False, lateral=5)
            finally:
                sc.close()
            st.home()  # away from the object: the scan's approach starts outside its keep-out
        setup.save(out / "ranging.json")
        s = sim.scene
        (out / "cal.toml").write_text(
            f"[calibration]\nv = {(s.v / np.linalg.norm(s.v)).tolist()}\n"
            f"n = {(s.n / np.linalg.norm(s.n)).tolist()}\nX_R = {s.X_R.tolist()}\n")
        (out / "plan.toml").write_text(replace(plan, mode=mode).to_toml())
        sim_t0 = sim.t
        r = subprocess.run([sys.executable, "-m", "dmdsm.host", "scan", "--sensor", S,
                            "--stage", T, "--no-home", "--calibration", str(out / "cal.toml"),
                            "--ranging", str(out / "ranging.json"), "--plan",
                            str(out / "plan.toml"), "--db", str(out / "db"), "--json"],
                           capture_output=True, text=True, timeout=3600)
        sim_dt = sim.t - sim_t0
    finally:
        emu.stop()
    if r.returncode != 0:
        raise SystemExit(f"{mode} scan failed: {r.stderr.strip()[-300:]}")
    summary = json.loads(r.stdout.splitlines()[-1])
    scan = read_scan(Path(summary["file"]), waveforms=False)
    summary["fits"] = validate_block(scan_points(scan), (50.0, 30.0))
    summary["sim_s"] = sim_dt
    summary["position_error_mm"] = along_line_error(scan.points, np.array(shots))
    return summary


def along_line_error(points: dict, shots: np.ndarray) -> np.ndarray:
    """Stored X minus the true mean X of the waveform's shots (mm), per point."""
    shots = shots[np.argsort(shots[:, 0], kind="stable")]
    out = []
    for ts, n, x in zip(points["timestamp"], points["n_average"],
                        points["stage_position_mm"][:, 0]):
        i = int(np.searchsorted(shots[:, 0], int(ts)))
        out.append(x - shots[i:i + int(n), 1].mean())
    return np.asarray(out)


def fly_motion_s(plan: ScanPlan) -> float:
    """Seconds the emulated Marlin needs for a fly scan's moves alone, from the homed stage
    (the approach along Y, every line with its ramps, the moves between lines, and the
    100 ms hold of each lone block)."""
    from dmdsm.host.scan.fly_executor import fly_lines, fly_speed, line_ends
    from dmdsm.host.scan.plan import expand
    from dmdsm.marlin_patch import load_machine
    from dmdsm.sim.boards.stage.motion import BLOCK_DELAY_FOR_1ST_MOVE, Planner
    from dmdsm.sim.physics.scene import TABLE_I_V, TABLE_I_XR

    machine = load_machine()
    plan = replace(plan, mode="fly")
    v, _ = fly_speed(plan, machine)
    lines = fly_lines(expand(plan, TABLE_I_V, TABLE_I_XR))
    total, here = 0.0, (0.0, 0.0, 0.0, 0.0)  # after G28
    moves = [((0.0, lines[0].points[0].y, 0.0, 0.0), plan.feed_mm_min / 60)]
    for line in lines:
        p = line.points[0]
        xs, xe = line_ends(line, plan, machine)
        moves += [((xs, p.y, p.z, p.theta_deg), plan.feed_mm_min / 60),
                  ((xe, p.y, p.z, p.theta_deg), v)]
    for target, feed in moves:
        pl = Planner(machine)
        total += pl.add(0.0, pl.to_steps(here), pl.to_steps(target), feed).duration
        total += BLOCK_DELAY_FOR_1ST_MOVE
        here = target
    return total


def main() -> int:
    """Print the figures side by side; exit 1 if fly misses the paper or the 10x target."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--speed", type=float, default=1.0, help="emulator speed (1: real time)")
    ap.add_argument("--levels", default="[12.0, 24.0]")
    ap.add_argument("--angles", default="[0.0, 90.0, 180.0, 270.0]")
    ap.add_argument("--step", type=float, default=1.0, help="point spacing (mm)")
    ap.add_argument("--half-width", type=float, default=32.0,
                    help="lines run -half..+half about the table axis (mm)")
    ap.add_argument("--average", type=int, default=12, help="laser shots per waveform")
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--feed", type=float, default=12000.0,
                    help="travel feed between points and lines (mm/min; 12000 = the "
                         "Chiron's X/Y maximum, 200 mm/s)")
    ap.add_argument("--modes", nargs="+", default=["step", "fly"], choices=["step", "fly"])
    args = ap.parse_args()
    plan = ScanPlan("aluminium_block", "aluminium", radius_mm=30.0, height_mm=40.0,
                    angles_deg=json.loads(args.angles),
                    levels_mm=json.loads(args.levels), half_width_mm=args.half_width,
                    step_mm=args.step, average=args.average, feed_mm_min=args.feed)
    print(f"plan: {len(plan.levels_mm)} levels x {len(plan.angles_deg)} angles, "
          f"{2 * plan.half_width_mm:g} mm lines, step {plan.step_mm:g} mm, average "
          f"{plan.average}, {plan.samples} samples, travel feed {plan.feed_mm_min:g} mm/min; "
          f"emulator x{args.speed:g}, seed {args.seed}")
    res = {}
    ok = True
    for mode in args.modes:
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            r = res[mode] = run(mode, args.speed, plan, args.seed, Path(tmp))
            total = time.perf_counter() - t0
        n = r["stored_now"]
        err = r["position_error_mm"]
        print(f"{mode}: {n} points in {r['wall_s']:.1f} s ({r['points_per_s']:.2f} points/s), "
              f"{r['sim_s']:.1f} s of emulator time ({n / r['sim_s']:.2f} points/s); "
              f"bench total {total:.0f} s")
        print("  per point (ms): " + ", ".join(f"{k} {v:.1f}"
                                              for k, v in r["ms_per_point"].items()))
        if "clock_sync" in r:
            print(f"  clock sync: {r['clock_sync']}")
        print(f"  stage X against the truth: mean {err.mean() * 1e3:+.2f} um, RMS "
              f"{np.sqrt(np.mean(err ** 2)) * 1e3:.2f} um, max |e| "
              f"{np.abs(err).max() * 1e3:.2f} um over {len(err)} points")
        for m, (pm, ps) in PAPER.items():
            f = r["fits"][m]
            good = f["e_mean_mm"] <= pm + 3 * f["e_mean_se_mm"] and f["e_std_mm"] <= 1.5 * ps
            ok &= bool(good) or mode == "step"
            print(f"  {m.upper()}: e = {f['e_mean_mm']:.3f} +/- {f['e_std_mm']:.3f} mm over "
                  f"{f['n']} points (paper {pm:.2f} +/- {ps:.2f}), RMS e/std "
                  f"{f['e_over_std_rms']:.2f} {'ok' if good else 'WORSE'}")
    if len(res) == 2:
        ratio = res["fly"]["points_per_s"] / res["step"]["points_per_s"]
        ratio_sim = (res["fly"]["stored_now"] / res["fly"]["sim_s"]) / (
            res["step"]["stored_now"] / res["step"]["sim_s"])
        print(f"fly / step: {ratio:.1f}x the points per second of wall time "
              f"({ratio_sim:.1f}x of emulator time); target >= 10x")
        floor = fly_motion_s(plan)
        print(f"  the stage's motion alone (the approach from home, lines, ramps, moves between "
              f"lines, Marlin's 100 ms holds) takes {floor:.1f} s in fly: at most "
              f"{n / floor:.1f} points/s, "
              f"{n / floor / res['step']['points_per_s']:.1f}x step and shoot")
        ok &= ratio >= 10
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
