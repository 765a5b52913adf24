"""Stage 6 of the demo, beside the campaign: each of its objects swept over the same band (the
table turning under the sensor, a ring at each height), for the coverage and laser-duty
comparison."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..scan.plan import modality_for, plan_for_size
from .session import Demo


def sweep_scans(d: Demo, names: tuple[str, ...], bands: dict[str, list[float]]
                ) -> dict[str, dict]:
    """`dmdsm scan --mode sweep` of each object over its campaign levels (bands: name ->
    levels_mm) into out/db_sweep; per object the scan's file and its `--json` summary."""
    from dmdsm.sim.physics.objects import HOUSEHOLD, bounding_size, household

    out = {}
    for name in names:
        material = HOUSEHOLD[name][0]
        obj = household(name)[0]
        w, dep, h = bounding_size(obj)
        boxy = type(obj.shape).__name__ == "Box"
        plan = plan_for_size(name, (w, dep, h), not boxy, material, "sweep",
                             modality_for(material))
        plan.levels_mm = list(bands[name])
        plan.validate()
        path = d.out / "plans" / f"{name}_sweep.toml"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(plan.to_toml())
        d.mount(name)
        summary = json.loads(d.run(
            "scan", "--plan", str(path), "--db", str(d.out / "db_sweep"), *d.ports,
            "--calibration", str(d.out / "calibration.toml"), "--ranging",
            str(d.out / "ranging.json"), "--json").splitlines()[-1])
        out[name] = {"file": summary["file"], "summary": summary}
    return out


def span_duty(path: str | Path, laser_hz: float = 1000.0) -> float | None:
    """The laser's duty over a scan's waveforms: the shots its stored waveforms averaged over
    the shots fired from its first waveform to its last (the approach before and the return
    after apart; every move, look and reversal between them counted)."""
    from ..scan.scanfile import read_scan

    scan = read_scan(Path(path), waveforms=False)
    p = scan.points
    ts = np.sort(np.asarray(p["timestamp"], np.float64))
    if len(ts) < 2:
        return None
    tick_hz = float(scan.sensor["tick_hz"])
    span_s = (ts[-1] - ts[0]) / tick_hz + float(p["n_average"][-1]) / laser_hz
    return float(np.sum(p["n_average"]) / laser_hz / span_s)


def met_band(path: str | Path, margin_mm: float = 1.0) -> tuple[float, float] | None:
    """The heights (mm, object frame) a scan's points span, widened by margin_mm: where its
    beam met the object (None without a point)."""
    from ..scan.points import scan_points
    from ..scan.scanfile import read_scan

    pts = scan_points(read_scan(Path(path), waveforms=False))
    z = np.concatenate([pts[m]["P"][:, 2] for m in ("oa", "us")])
    if not len(z):
        return None
    return float(z.min()) - margin_mm, float(z.max()) + margin_mm
