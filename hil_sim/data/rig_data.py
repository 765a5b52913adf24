"""Calibration-rig data straight from the physics (no serial link): the host's own procedure
(`scan_rig`) drives an in-process stage and sensor, for Monte Carlo checks of the solver's
reported uncertainties against the truth over many seeds.

`python -m dmdsm.sim.data.rig_data --seed 3 --out rig.csv` writes the raw-point CSV that
`dmdsm calibrate --from-data` reads; the truth (v, n, X_R) is printed as JSON. The physics is
the emulator's (ray cast, waveform synthesis, per-position stage and turntable scatter, shot
averaging); only the links and the firmware are left out.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dmdsm.host.calibration.procedure import RigPlan, scan_rig
from dmdsm.host.calibration.rig_file import append_rows

from ..boards.sensor.core_board import ADC_RATE_HZ, TICK_HZ, averaged_shots
from ..physics.objects import rig_horizontal, rig_vertical
from ..physics.scene import TABLE_I_N, TABLE_I_V, TABLE_I_XR, Scene, hash_noise, table_frame
from ..physics.signals import SensorModel
from .dataset import true_setup


@dataclass
class _Identity:
    tick_hz: int = TICK_HZ
    adc_rate_hz: float = ADC_RATE_HZ


@dataclass
class _Shots:
    samples: np.ndarray
    received: np.ndarray
    trigger_phase: np.ndarray


class DirectRig:
    """Stage + sensor in one object: the host's StageMotion and ShotSensor (links.interfaces),
    what `scan_rig` and `calibrate_range` call."""

    def __init__(self, scene: Scene, seed: int = 0, stage_noise_mm: float = 0.002,
                 angle_noise_deg: float = 0.01) -> None:
        self.scene, self.seed = scene, seed
        self.model = SensorModel()
        self.rng = np.random.default_rng(seed)
        self.identity = _Identity()
        self.stage_noise_mm, self.angle_noise_deg = stage_noise_mm, angle_noise_deg
        self.cmd = np.zeros(4)
        self.cfg = {"n_samples": 1024, "n_average": 1}

    # stage side
    def move(self, x: float, y: float, z: float, a: float = 0.0,
             feed_mm_min: float | None = None, wait: bool = False) -> None:
        """Commanded position (mm, deg; all three axes, A 0 unless given, instantly: the feed
        and wait are ignored); the physical one adds a fixed per-position scatter."""
        self.cmd = np.array([x, y, z, a], float)

    def wait(self) -> None:
        """Moves are instantaneous here."""

    def pose(self) -> tuple[np.ndarray, float]:
        """True S (mm) and theta (deg), scattered per position as the emulator does."""
        S = self.cmd[:3] + hash_noise(f"S{np.round(self.cmd[:3], 3)}", self.stage_noise_mm, 3,
                                       self.seed)
        th = self.cmd[3] + hash_noise(f"A{round(self.cmd[3], 3)}", self.angle_noise_deg, 1,
                                       self.seed)[0]
        return S, float(th)

    # sensor side
    def configure(self, **cfg: int) -> dict:
        """Keep the acquisition settings (samples, on-board averaging)."""
        self.cfg.update(cfg)
        return self.cfg

    def acquire(self, n_shots: int) -> _Shots:
        """n_shots waveforms, each the mean of n_average laser shots, as the board sends."""
        S, th = self.pose()
        hit = self.scene.cast(S, th)
        n, avg = int(self.cfg["n_samples"]), int(self.cfg["n_average"])
        waves, phases = [], []
        for _ in range(n_shots):
            wave, phase = averaged_shots(hit, self.model, n, avg, self.rng, self.seed)
            waves.append(wave)
            phases.append(phase)
        return _Shots(np.array(waves), np.ones(n_shots, bool), np.array(phases))


def record(seed: int, plan_kw: dict | None = None, v: np.ndarray = TABLE_I_V,
           n: np.ndarray = TABLE_I_N, X_R: np.ndarray = TABLE_I_XR
           ) -> tuple[list[dict], dict]:
    """Raw points of the tip and edge steps at the default rig geometry (the e2e test's);
    returns (rows, truth)."""
    scene = Scene(v=np.asarray(v, float), n=np.asarray(n, float), X_R=np.asarray(X_R, float))
    rig = DirectRig(scene, seed)
    setup = true_setup(rig.model)
    vv = scene.v / np.linalg.norm(scene.v)
    frame = table_frame(scene.n)
    # where a user would aim: near the tip and the filament, at an unknown phase of the
    # raster (a start placed on the true centre would hide the raster's quantisation)
    aim = np.random.default_rng([seed, 7]).uniform(-0.05, 0.05, (2, 3))
    tip = scene.X_R + frame @ np.array([0.0, -10.0, 20.0]) - 6 * vv + aim[0]
    fil = scene.X_R + frame @ np.array([25.0, 0.0, 0.0]) - 6.25 * vv + aim[1]
    kw = dict(plan_kw or {})
    plan = RigPlan(tip_start=tuple(np.round(tip, 3)),
                   edge_start=(round(fil[0], 3), round(fil[1], 3), 0.0), **kw)
    scene.objects = rig_horizontal()
    rows = scan_rig(rig, rig, setup, plan, "tip")
    scene.objects = rig_vertical()
    rows += scan_rig(rig, rig, setup, plan, "edge")
    truth = {"v": vv.tolist(), "n": (scene.n / np.linalg.norm(scene.n)).tolist(),
             "X_R": scene.X_R.tolist(), "seed": seed}
    return rows, truth


def main(argv: list[str] | None = None) -> int:
    """Command line: write one seed's raw points and print the truth."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True, help="calibration CSV to write")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    rows, truth = record(args.seed)
    args.out.unlink(missing_ok=True)
    append_rows(args.out, rows)
    print(json.dumps(truth))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
