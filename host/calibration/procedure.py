"""The calibration procedure of §IV-D with the rig: tip frames, then edge frames, as raw points
for `dmdsm calibrate` (the stage and sensor clients do the I/O; ranging gives d)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..links.interfaces import ShotSensor, StageMotion
from ..links.safety import TABLE_I
from ..ranging.calibrate import RangingSetup, gate_for
from ..ranging.matched_filter import MatchedFilter
from .solver import same_angle


@dataclass
class RigPlan:
    """Where and how to scan (mm, deg); defaults suit the 0.5 mm filament at ~6 mm."""

    tip_start: tuple[float, float, float]   # stage position facing the tip, nearest depth
    tip_depth_steps: tuple[float, ...] = (0.0, 3.0, 6.0, 9.0)  # Y steps back (mm)
    tip_half_mm: float = 0.4                # in-frame X-Z raster half width
    tip_step_mm: float = 0.1
    edge_start: tuple[float, float, float] = (0.0, 0.0, 0.0)  # facing the vertical filament
    edge_angles_deg: tuple[float, ...] = (0.0, 180.0)
    edge_z_levels: tuple[float, ...] = (10.0, 15.0, 20.0, 25.0, 30.0, 35.0, 40.0)
    edge_half_mm: float = 0.6               # X sweep half width
    edge_step_mm: float = 0.1
    shots: int = 1                          # waveforms per raw point
    average: int = 4                        # shots averaged on board per waveform
    modality: str = "oa"
    depth_range_mm: tuple[float, float] = (2.0, 25.0)  # where echoes are searched


class NoEcho(ValueError):
    """A whole tip raster or edge sweep without an echo: the sensor does not face the rig
    where --at put it (raised at once: the rest of the step would be as empty)."""


def check_plan(plan: RigPlan, step: str) -> None:
    """Refuse, before anything moves, a plan whose data could not be solved (ValueError)."""
    if step == "tip":
        if len(set(plan.tip_depth_steps)) < 2:
            raise ValueError("give two or more different --tip-depths (mm): v needs tip "
                             "frames at two or more depths")
        if plan.tip_half_mm <= 0 or plan.tip_step_mm <= 0:
            raise ValueError("--tip-half and --tip-step must be positive (mm)")
        return
    angles = plan.edge_angles_deg
    if all(same_angle(a, angles[0]) for a in angles):
        raise ValueError("give two or more different --angles (deg): n and X_R need the "
                         "filament at two or more turntable angles")
    if np.ptp(plan.edge_z_levels) < 1.0:
        raise ValueError("give --edge-levels (mm) 1 mm or more apart: each edge frame needs "
                         "center points at two or more heights")
    if plan.edge_half_mm <= 0 or plan.edge_step_mm <= 0:
        raise ValueError("--edge-half and --edge-step must be positive (mm)")


def _measure(stage: StageMotion, sensor: ShotSensor, mf: MatchedFilter, setup: RangingSetup,
             plan: RigPlan, gate: tuple[int, int], x: float, y: float, z: float,
             a: float) -> tuple[float, float]:
    """Move, record, range: (d in mm or NaN, amplitude)."""
    stage.move(x=x, y=y, z=z, a=a, feed_mm_min=3000)
    stage.wait()
    got = sensor.acquire(plan.shots)
    if not got.received.any():
        return np.nan, 0.0
    w = got.samples[got.received].astype(float) - 32768.0
    arr = mf(w, gate=gate)
    t = arr.times_s(setup.fs_hz, got.trigger_phase[got.received] / sensor.identity.tick_hz)
    cal = setup.cals[plan.modality]
    k = 1.0 if plan.modality == "oa" else 2.0
    d = cal.c_mm_s * (t - cal.t0_s) / k
    amp = float(np.nanmean(np.where(np.isfinite(arr.index), arr.amplitude, 0.0)))
    return float(np.nanmean(d)) if np.isfinite(d).any() else np.nan, amp


def scan_rig(stage: StageMotion, sensor: ShotSensor, setup: RangingSetup, plan: RigPlan,
             step: str, progress: Callable[[int, int], None] | None = None,
             on_row: Callable[[dict], None] | None = None) -> list[dict]:
    """Raw points of the tip frames (step='tip') or the edge frames (step='edge'); on_row
    gets each one as it is measured (to save it before the next move)."""
    m = plan.modality
    if m not in setup.cals:
        raise ValueError(f"the ranging calibration has no {m.upper()} modality")
    sensor.configure(n_samples=1024, n_average=plan.average, pretrigger=0,
                     trigger_timeout_ms=2000)
    mf = MatchedFilter(setup.templates[m], 1024)
    c, t0 = setup.cals[m].c_mm_s, setup.cals[m].t0_s
    lo, hi = plan.depth_range_mm
    # gated with the calibrated t0: the transmitter's bang must not pass for a near echo
    gate = (gate_for(lo, m, setup.fs_hz, c, 1024, t0)[0],
            min(gate_for(hi, m, setup.fs_hz, c, 1024, t0)[1],
                1024 - len(mf.t.pulse) + int(mf.t.center)))  # no circular wrap
    rows: list[dict] = []
    if step == "tip":
        return _scan_tips(stage, sensor, mf, setup, plan, gate, progress, on_row)
    offs = np.arange(-plan.edge_half_mm, plan.edge_half_mm + 1e-9, plan.edge_step_mm)
    starts = [edge_start_at(plan, th) for th in plan.edge_angles_deg]
    jobs = [(f, li, starts[f][0] + ox, starts[f][1], z, th)
            for f, th in enumerate(plan.edge_angles_deg)
            for li, z in enumerate(plan.edge_z_levels) for ox in offs]
    for i, (frame, line, x, y, z, th) in enumerate(jobs):
        d, amp = _measure(stage, sensor, mf, setup, plan, gate, x, y, z, th)
        rows.append({"step": step, "frame": frame, "line": line, "theta_deg": th,
                     "sx_mm": x, "sy_mm": y, "sz_mm": z, "d_mm": d, "amplitude": amp,
                     "modality": m})
        if on_row is not None:
            on_row(rows[-1])
        if progress is not None:
            progress(i + 1, len(jobs))
        sweep = rows[-len(offs):]
        if len(sweep) == len(offs) and offs.size and sweep[0]["line"] == line == 0 and \
                sweep[0]["frame"] == frame and not any(np.isfinite(r["d_mm"]) for r in sweep):
            raise NoEcho(
                f"no echo across the filament at table angle {th:g} deg (X {x - offs[-1]:.2f} "
                f"± {plan.edge_half_mm:g} mm, Y {y:.2f}, Z {z:g}): the filament is not in front "
                f"of the sensor there; jog to it (docs/calibration.md, \"Finding the tip and the "
                f"filament\") and give that position as --at X Y 0")
    return rows


def _scan_tips(stage: StageMotion, sensor: ShotSensor, mf: MatchedFilter, setup: RangingSetup,
               plan: RigPlan, gate: tuple[int, int],
               progress: Callable[[int, int], None] | None,
               on_row: Callable[[dict], None] | None = None) -> list[dict]:
    """Tip frames, each raster centred where the tip should be: the tip drifts across the
    raster by v_x / v_y, v_z / v_y per mm of Y step, so the second frame's centre follows the
    paper's v and later ones are extrapolated from the centre points of the frames before."""
    offs = np.arange(-plan.tip_half_mm, plan.tip_half_mm + 1e-9, plan.tip_step_mm)
    total = len(plan.tip_depth_steps) * len(offs) ** 2
    rows: list[dict] = []
    centers: list[np.ndarray] = []  # (x, z) of each frame's center point
    x0, y0, z0 = plan.tip_start
    for f, dy in enumerate(plan.tip_depth_steps):
        if len(centers) >= 2:
            step = (centers[-1] - centers[-2]) / (plan.tip_depth_steps[f - 1]
                                                 - plan.tip_depth_steps[f - 2])
            cx, cz = centers[-1] + step * (dy - plan.tip_depth_steps[f - 1])
        elif centers:  # one frame so far: the drift the paper's v predicts
            v = np.asarray(TABLE_I["v"], float)
            dd = plan.tip_depth_steps[f] - plan.tip_depth_steps[f - 1]
            cx, cz = centers[-1] - dd * np.array([v[0], v[2]]) / v[1]
        else:
            cx, cz = x0, z0
        frame_rows = []
        for oz in offs:
            for ox in offs:
                d, amp = _measure(stage, sensor, mf, setup, plan, gate, cx + ox, y0 - dy,
                                  cz + oz, 0.0)
                frame_rows.append({"step": "tip", "frame": f, "line": 0, "theta_deg": 0.0,
                                   "sx_mm": cx + ox, "sy_mm": y0 - dy, "sz_mm": cz + oz,
                                   "d_mm": d, "amplitude": amp, "modality": plan.modality})
                if on_row is not None:
                    on_row(frame_rows[-1])
                if progress is not None:
                    progress(len(rows) + len(frame_rows), total)
        rows += frame_rows
        if not any(np.isfinite(r["d_mm"]) for r in frame_rows):
            raise NoEcho(
                f"no echo in tip frame {f + 1} (X {cx:.2f}, Z {cz:.2f} ± {plan.tip_half_mm:g} mm "
                f"at Y {y0 - dy:.2f}): the filament's tip is not in front of the sensor there; "
                f"jog to it (docs/calibration.md, \"Finding the tip and the filament\") and "
                f"give that position as --at")
        amps = np.array([r["amplitude"] for r in frame_rows])
        keep = amps >= 0.5 * amps.max() if amps.max() > 0 else np.ones(len(amps), bool)
        centers.append(np.array([np.mean([r["sx_mm"] for r, k in zip(frame_rows, keep) if k]),
                                 np.mean([r["sz_mm"] for r, k in zip(frame_rows, keep) if k])]))
    return rows


def edge_start_at(plan: RigPlan, theta_deg: float, nominal_d_mm: float = 6.0
                  ) -> tuple[float, float]:
    """Sensor X, Y facing the vertical filament after the table turned to theta: the filament
    point seen from edge_start, turned about the axis (the paper's n, X_R until calibrated;
    the sweep width covers their error), backed off along v."""
    from .solver import rodrigues

    v, n, xr = (np.asarray(TABLE_I[k], float) for k in ("v", "n", "X_R"))
    v = v / np.linalg.norm(v)
    f0 = np.asarray(plan.edge_start, float) + nominal_d_mm * v
    f = xr + rodrigues(n, np.radians(theta_deg)) @ (f0 - xr)
    s = f - nominal_d_mm * v
    return float(s[0]), float(s[1])
