"""Coverage per modality of the truth surface the sensor can reach (for the bench's figures).

The reference is the union of every mounted object's reachable surface samples
(hil_sim/physics/visibility.py: seen from some table angle at a usable incidence, within the
scanner's levels), in the turntable frame at theta = 0, the host's object frame; each
modality's points (object frame, mm) cover a sample when one lies within the spacing
(host/scan/coverage.py). Objects are judged one at a time: one standing in front of another
is not taken as hiding it.
"""

from __future__ import annotations

import numpy as np

from dmdsm.host.scan.coverage import coverage
from dmdsm.sim.physics.visibility import reachable_surface


def reachable_truth(sim_truth_objects, v, n, spacing_mm=2.0, z_range_mm=None,
                    max_incidence_deg=60.0) -> np.ndarray:
    """The union of all objects' reachable surface samples (m, 3, mm, object frame): seen
    from some table angle within max_incidence_deg (deg) of head on."""
    parts = [reachable_surface(t, np.asarray(v, float), np.asarray(n, float),
                               spacing_mm=spacing_mm, z_range_mm=z_range_mm,
                               max_incidence_deg=max_incidence_deg)[0]
             for t in sim_truth_objects]
    return np.concatenate(parts) if parts else np.zeros((0, 3))


def truth_coverage(sim_truth_objects, points_object_frame_by_modality, v, n, spacing_mm=2.0,
                   z_range_mm=None) -> dict[str, float]:
    """Coverage (0..1) per modality of the reachable truth surface: the share of its samples
    (about spacing_mm apart) with one of the modality's points (object frame, mm) within
    spacing_mm; NaN per modality when nothing is reachable. sim_truth_objects:
    Simulation.truth_objects(); v, n: the beam and the table's axis (world frame);
    z_range_mm: the scanned heights (object frame z, mm), None for all."""
    surface = reachable_truth(sim_truth_objects, v, n, spacing_mm, z_range_mm)
    return {name: coverage(surface, np.asarray(pts, float).reshape(-1, 3), spacing_mm)
            for name, pts in points_object_frame_by_modality.items()}
