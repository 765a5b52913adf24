"""Aluminium-block scans straight from the physics (no serial link): the host's plan, ranging
and per-point stds against the ray cast's true distances, for Monte Carlo checks of the
reported uncertainties (bench/uncertainty.py, tests/test_uncertainty.py)."""

from __future__ import annotations

import numpy as np

from dmdsm.host.ranging.calibrate import RangingSetup, distance_std_mm
from dmdsm.host.ranging.procedure import calibrate_range
from dmdsm.host.scan.plan import ScanPlan, expand, point_ranger

from ..boards.sensor.core_board import TICK_HZ
from ..physics.objects import aluminium_block
from ..physics.scene import Scene
from .rig_data import DirectRig

START = {"X": 235.0, "Y": 266.0, "Z": 20.0}  # facing the block's face, as the demo


def block_rig(seed: int) -> DirectRig:
    """The block on the table at the paper's Table I pose, stage and sensor in process."""
    return DirectRig(Scene(objects=aluminium_block()), seed)


def ranging_calibration(rig: DirectRig, fit_c: bool = False, steps: int = 21,
                        lateral: int = 5) -> RangingSetup:
    """The demo's ranging calibration on the block's face, gauged with the true distance."""
    rig.move(START["X"], START["Y"], START["Z"])
    d0 = rig.scene.cast(*rig.pose()).d  # the feeler gauge's reading
    setup, _ = calibrate_range(rig, rig, START, d0, steps=steps, step_mm=1.0, shots=2,
                               fit_c=fit_c, lateral=lateral)
    return setup


def scan_block(rig: DirectRig, setup: RangingSetup, levels_mm: list[float],
               step_mm: float = 2.0) -> dict[str, np.ndarray]:
    """The block plan ranged as `dmdsm scan` does; per modality an array of rows
    (d, d_std, true d, Sx, Sy, Sz, theta): distances in mm, theta in deg."""
    s = rig.scene
    v = s.v / np.linalg.norm(s.v)
    plan = ScanPlan("aluminium_block", "aluminium", radius_mm=30.0, height_mm=40.0,
                    levels_mm=list(levels_mm), half_width_mm=32.0, step_mm=step_mm)
    rig.configure(n_samples=plan.samples, n_average=plan.average)
    ranger = point_ranger(plan, setup, plan.samples, TICK_HZ)
    rows: dict[str, list] = {"oa": [], "us": []}
    previous = None
    for p in expand(plan, v, s.X_R):
        rig.move(p.x, p.y, p.z, p.theta_deg)
        S, th = rig.pose()
        truth = s.cast(S, th).d
        got = rig.acquire(1)
        r = ranger(got.samples[0], int(got.trigger_phase[0]), 0,
                   previous if p.column else None)
        found = {m: val for m, val in r.items() if np.isfinite(val[0])}
        previous = (next(iter(found.values()))[0] if found else np.nan,
                    {m: val[1] for m, val in found.items()})
        for m, (d, snr) in found.items():
            rows[m].append((d, float(distance_std_mm(setup, m, snr)), truth, *S, th))
    return {m: np.array(rr).reshape(-1, 7) for m, rr in rows.items()}
