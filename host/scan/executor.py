"""Step-and-shoot scanning: move, settle, acquire, range and store each planned point, resumable.

The executor knows the two clients, the plan, the calibration and the ranging setup; it writes
through `scanfile.ScanWriter`, so every finished point is on disk before the next move. An
interruption (Ctrl-C, a lost board) closes the file as `interrupted` and quick-stops the stage
(the StageClient context manager); running the same plan again continues after the last
finished point.
"""

from __future__ import annotations

import time
from functools import partial

import numpy as np

from ..links.interfaces import ShotSensor, Stage
from ..ranging.point import PointRanger, surface
from .common import Progress, ScanStats, approach
from .plan import Point, ScanPlan
from .scanfile import PHASES, ScanWriter

RETRIES = 3  # arms per point before a waveform is recorded as lost


def run_scan(stage: Stage, sensor: ShotSensor, plan: ScanPlan, points: list[Point],
             writer: ScanWriter, ranger: PointRanger, progress: Progress | None = None
             ) -> ScanStats:
    """Measure points[writer.n_done:] in order, appending each to the file as it finishes;
    progress(points in the file, planned, phase times s) after each.

    The caller has checked every move (plan.check_plan) and configured the sensor.
    """
    stats = ScanStats()
    t_start = time.monotonic()
    todo = points[writer.n_done:]
    previous = _last_distance(writer, points)
    if todo:  # into the front plane along Y, then to the first point
        approach(stage, todo[0].y, plan.feed_mm_min)
    for p in todo:
        timing = dict.fromkeys(PHASES, 0.0)
        t0 = time.monotonic()
        stage.move(x=p.x, y=p.y, z=p.z, a=p.theta_deg, feed_mm_min=plan.feed_mm_min)
        stage.wait()
        t1 = time.monotonic()
        timing["move"] = t1 - t0
        if plan.settle_s > 0:
            stage.send(f"G4 P{plan.settle_s * 1000:.0f}")
            stage.wait()
        timing["settle"] = time.monotonic() - t1
        got = None
        attempts = 0
        while got is None and attempts < RETRIES:
            attempts += 1
            shots = sensor.acquire(1)
            if shots.received[0]:
                got = shots
            else:
                stats.lost += 1
        t2 = time.monotonic()
        if got is not None and got.first_byte_s and got.done_s:  # bytes on the wire
            timing["transfer"] = got.done_s - got.first_byte_s
        timing["acquire"] = t2 - t1 - timing["settle"] - timing["transfer"]
        if got is not None:
            wave = got.samples[0].astype(np.uint16)
            prev = previous if previous is not None and previous[0] == (p.angle_index,
                                                                         p.level) else None
            window = p.window_mm if np.isfinite(p.window_mm).all() else None  # a lone
            r = ranger(wave, int(got.trigger_phase[0]), int(got.config.get("pretrigger", 0)),
                       prev[1] if prev else None, window)  # pulse read by it, if it is set
            previous = ((p.angle_index, p.level), surface(r))
            ids = dict(n_average=int(got.n_average[0]), timestamp=int(got.timestamp[0]),
                       trigger_phase=int(got.trigger_phase[0]), received=True)
        else:
            wave = np.zeros(writer.data["waveforms"].shape[1], np.uint16)
            r = {}
            ids = dict(n_average=0, timestamp=0, trigger_phase=0, received=False)
        timing["ranging"] = time.monotonic() - t2
        nan = (np.nan, 0.0)
        values = dict(stage_position_mm=[p.x, p.y, p.z], theta_deg=p.theta_deg,
                      level=p.level, column=p.column, angle_index=p.angle_index,
                      distance_oa_mm=r.get("oa", nan)[0], distance_us_mm=r.get("us", nan)[0],
                      snr_oa_db=r.get("oa", nan)[1], snr_us_db=r.get("us", nan)[1],
                      phase_time_s=[timing[k] for k in PHASES], attempts=attempts,
                      point_index=p.index, **ids)
        stats.store(partial(writer.append, wave, host_time=time.time(), **values), 1, timing,
                    writer, len(points), progress)
    stats.wall_s = time.monotonic() - t_start
    return stats


def _last_distance(writer: ScanWriter, points: list[Point]) -> tuple | None:
    """((angle index, level), surface distance mm) of the last stored point, so a resumed
    scan ranges its next point exactly as an uninterrupted one would."""
    i = writer.n_done - 1
    if i < 0:
        return None
    d = writer.data
    r = {m: (float(d[f"distance_{m}_mm"][i]), float(d[f"snr_{m}_db"][i]))
         for m in ("oa", "us")}
    return ((points[i].angle_index, points[i].level), surface(r))

