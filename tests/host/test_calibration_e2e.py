"""The whole calibration chain in hil_sim: ranging calibration on the block, tip frames on the
horizontal filament, edge frames on the vertical one at 0 and 180 deg, then the solver."""

import numpy as np

from dmdsm.host.calibrate_proc import RigPlan, scan_rig
from dmdsm.host.calibration import solve
from dmdsm.host.calibration_io import COLUMNS, center_points
from dmdsm.host.range_cmd import calibrate_range
from dmdsm.host.sensor import SensorClient
from dmdsm.host.stage import StageClient
from dmdsm.sim.objects import rig_horizontal, rig_vertical
from dmdsm.sim.scene import table_frame


def test_calibration_procedure_recovers_table_i_end_to_end(emulator):
    emu = emulator(speed=5.0, scene="aluminium_block", seed=3)
    sim = emu.sim
    st, sc = StageClient(emu.stage), SensorClient(emu.sensor)
    st.home()
    st.move(x=235, y=266, z=20, wait=True)
    st.wait()
    setup, _ = calibrate_range(st, sc, {"X": 235, "Y": 266, "Z": 20},
                               sim.truth()["distance_mm"], steps=21, step_mm=1.0, shots=4)

    def mount(objects):  # the user re-mounts the rig between the two steps
        with emu.server.lock:
            sim.scene.objects = objects
            sim.sensor._hit_cache = None

    v = sim.scene.v / np.linalg.norm(sim.scene.v)
    frame = table_frame(sim.scene.n)
    mount(rig_horizontal())
    tip = sim.scene.X_R + frame @ np.array([0.0, -10.0, 20.0])  # jogged to by hand
    plan = RigPlan(tip_start=tuple(tip - 6 * v))
    rows = scan_rig(st, sc, setup, plan, "tip")
    mount(rig_vertical())
    fil = sim.scene.X_R + frame @ np.array([25.0, 0.0, 0.0]) - 6.25 * v
    plan = RigPlan(tip_start=plan.tip_start, edge_start=(fil[0], fil[1], 0.0))
    rows += scan_rig(st, sc, setup, plan, "edge")
    raw = {c: np.array([r[c] for r in rows]) for c in COLUMNS}
    r = solve(center_points(raw, "oa", 0.5, 0.25))
    n_true = sim.scene.n / np.linalg.norm(sim.scene.n)
    assert np.degrees(np.arccos(np.clip(r.v @ v, -1, 1))) < 2.0
    assert np.degrees(np.arccos(np.clip(r.n @ n_true, -1, 1))) < 0.5
    assert np.linalg.norm(r.X_R[:2] - sim.scene.X_R[:2]) < 0.3
    st.close()
    sc.close()
