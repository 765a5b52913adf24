"""Coverage of the reachable surface (host/scan/coverage.py, hil_sim/physics/visibility.py,
bench/coverage_truth.py): a surface sampled at the spacing covers itself, a removed sector
leaves its share uncovered, the laser's duty is stored shots over fired shots, and the
reachable truth is what a near-horizontal beam can see: a block's four sides, not its top or
floor; a bowl's outside, not its inside; a mug handle's inner face only in part. The
emulator's frames and the host's object frame agree (a beam cast in the Scene lands where
object_points puts it)."""

import importlib.util
import time
from pathlib import Path

import numpy as np
import pytest
import trimesh

from dmdsm.host.scan.coverage import coverage, covered_mask, laser_duty
from dmdsm.host.scan.reconstruct import object_points
from dmdsm.sim.physics.scene import (
    TABLE_I_N,
    TABLE_I_V,
    TABLE_I_XR,
    Scene,
    rodrigues,
    table_frame,
)
from dmdsm.sim.physics.visibility import (
    reachable_surface,
    surface_samples,
    toward_sensor,
    visible_mask,
)
from dmdsm.sim.servers.runner import SimConfig, Simulation

ROOT = Path(__file__).resolve().parents[1]
V, N = TABLE_I_V / np.linalg.norm(TABLE_I_V), TABLE_I_N / np.linalg.norm(TABLE_I_N)


def even(mesh: trimesh.Trimesh, spacing: float, seed: int) -> np.ndarray:
    count = int(np.ceil(mesh.area / spacing ** 2))
    return trimesh.sample.sample_surface_even(mesh, count, seed=seed)[0]


@pytest.fixture(scope="module")
def truths() -> dict:
    out = {}
    for scene in ("aluminium_block", "bowl", "mug"):
        sim = Simulation(SimConfig(scene=scene))
        out[scene] = (sim, sim.truth_objects()[0])
    return out


# ---------------------------------------------------------------- coverage, the laser's duty
@pytest.mark.parametrize("mesh", [trimesh.creation.icosphere(subdivisions=4, radius=30.0),
                                  trimesh.creation.box(extents=(50.0, 30.0, 40.0))],
                         ids=["sphere", "box"])
def test_a_surface_sampled_at_the_spacing_covers_itself(mesh):
    surface, scan = even(mesh, 1.0, seed=0), even(mesh, 1.0, seed=1)
    assert coverage(surface, scan, 1.0) > 0.97
    assert coverage(surface, scan, 3.0) == 1.0
    assert coverage(surface, scan[::50], 1.0) < 0.2  # a sparse scan covers little


@pytest.mark.parametrize("mesh", [trimesh.creation.icosphere(subdivisions=4, radius=30.0),
                                  trimesh.creation.box(extents=(50.0, 50.0, 40.0))],
                         ids=["sphere", "box"])
def test_a_removed_sector_is_missing_in_its_share(mesh):
    surface, scan = even(mesh, 1.0, seed=0), even(mesh, 1.0, seed=1)
    az = np.degrees(np.arctan2(scan[:, 1], scan[:, 0])) % 360
    kept = scan[az >= 90]  # a quarter of the turn never scanned
    c = coverage(surface, kept, 1.0)
    assert 0.75 <= c <= 0.79, c  # 3/4, and a band within 1 mm of the sector's two edges
    mask = covered_mask(surface, kept, 1.0)
    az_s = np.degrees(np.arctan2(surface[:, 1], surface[:, 0])) % 360
    deep = (az_s > 15) & (az_s < 75) & (np.hypot(surface[:, 0], surface[:, 1]) > 5)
    assert not mask[deep].any()  # the holes are where the sector was
    assert mask[(az_s > 95) & (az_s < 355)].mean() > 0.97


def test_coverage_of_nothing():
    surface = np.random.default_rng(0).normal(size=(100, 3))
    assert coverage(surface, np.zeros((0, 3)), 1.0) == 0.0
    assert coverage(surface, np.full((3, 3), np.nan), 1.0) == 0.0
    assert np.isnan(coverage(np.zeros((0, 3)), surface, 1.0))
    assert covered_mask(surface, surface[:10], 1e-9).sum() == 10
    with pytest.raises(ValueError):
        coverage(surface, surface, 0.0)
    with pytest.raises(ValueError):
        coverage(surface, surface[:, :2], 1.0)


def test_laser_duty_is_stored_shots_over_fired_shots():
    assert laser_duty(100, 8, 1000.0, 2.0) == pytest.approx(0.4)  # 800 of 2000 shots
    assert laser_duty(1000, 1, 1000.0, 4.0) == pytest.approx(0.25)
    assert laser_duty(300, 8, 1000.0, 2.0) == 1.0  # capped
    assert laser_duty(0, 1, 1000.0, 2.0) == 0.0
    assert np.isnan(laser_duty(10, 1, 1000.0, 0.0))
    with pytest.raises(ValueError):
        laser_duty(10, 0, 1000.0, 1.0)
    with pytest.raises(ValueError):
        laser_duty(10, 1, 1000.0, -1.0)


# ---------------------------------------------------------------- the reachable truth
def test_the_emulators_frame_is_the_hosts_object_frame(truths):
    """A sample the visibility calls seen at theta is where the emulator's beam, sent at it
    from the sensor's side, lands (150 mm on), and object_points puts that landing back on
    the sample; a sample it calls hidden is hit by something nearer."""
    for scene, theta in (("aluminium_block", 35.0), ("mug", 20.0), ("mug", 200.0)):
        sim, truth = truths[scene]
        s = sim.scene  # its objects and pose, with a point-like spot (one depth per shot)
        scn = Scene(v=s.v, n=s.n, X_R=s.X_R, objects=s.objects, spot_radius=0.0)
        assert np.allclose(scn.X_R, TABLE_I_XR)
        p, nrm = surface_samples(truth, 2.0)
        facing = (nrm @ toward_sensor(V, N, theta) >= 0.5) & (nrm[:, 2] > -0.5)
        seen = visible_mask(truth, p, nrm, V, N, [theta])
        rot = rodrigues(N, np.radians(theta)) @ table_frame(N)
        rng = np.random.default_rng(1)
        for want, sel in ((True, seen), (False, facing & ~seen)):
            idx = rng.choice(np.flatnonzero(sel), size=min(60, sel.sum()), replace=False)
            if not want and len(idx) == 0:
                continue
            assert len(idx) >= 20, (scene, theta, want)
            ok = 0
            for i in idx:
                S = scn.X_R + rot @ p[i] - 150.0 * scn.v / np.linalg.norm(scn.v)
                hit = scn.cast(S, theta)
                X = S + hit.d * scn.v / np.linalg.norm(scn.v)
                if want:
                    back = object_points(X[None], np.array([theta]), scn.n, scn.X_R)[0]
                    ok += abs(hit.d - 150.0) < 1e-3 and np.linalg.norm(back - p[i]) < 1e-3
                else:
                    ok += hit.d < 149.0
            assert ok >= 0.97 * len(idx), (scene, theta, want, ok, len(idx))


def test_the_block_shows_its_four_sides_not_its_top_or_floor(truths):
    _, truth = truths["aluminium_block"]
    p, nrm = surface_samples(truth, 1.0)
    seen = visible_mask(truth, p, nrm, V, N)
    side = np.abs(nrm[:, 2]) < 0.1
    assert seen[side].all()
    assert not seen[nrm[:, 2] > 0.9].any()   # the top: met at ~86 deg incidence
    assert not seen[nrm[:, 2] < -0.9].any()  # the floor
    for axis in (np.eye(3)[0], -np.eye(3)[0], np.eye(3)[1], -np.eye(3)[1]):
        assert (nrm[seen] @ axis > 0.99).sum() > 1000  # each side, 1200-2000 mm^2
    assert seen.mean() == pytest.approx(6400 / 9400, abs=0.01)  # sides' area / all
    # at 87 deg the top is reachable; within levels 10-30 mm only sides are sampled
    assert visible_mask(truth, p, nrm, V, N, max_incidence_deg=87.0)[nrm[:, 2] > 0.9].all()
    q, qn = reachable_surface(truth, V, N, spacing_mm=1.0, z_range_mm=(10.0, 30.0))
    assert q[:, 2].min() >= 10.0 and q[:, 2].max() <= 30.0
    assert len(q) == pytest.approx(160 * 20, rel=0.05) and np.all(np.abs(qn[:, 2]) < 1e-9)


def test_a_bowls_inside_is_not_reachable_its_outside_is(truths):
    _, truth = truths["bowl"]
    p, nrm = surface_samples(truth, 1.0)
    inner = np.linalg.norm(p - [0.0, 0.0, 85.0], axis=1) < 83.0  # r 81 inside, 85 outside
    wall = ~inner & (p[:, 2] > 20.0) & (p[:, 2] < 55.0)  # steep enough (< 60 deg incidence)
    level = np.array([0.0, 1.0, 0.0])  # a level beam: nothing inside
    seen = visible_mask(truth, p, nrm, level, N)
    assert not seen[inner].any() and seen[wall].all()
    seen = visible_mask(truth, p, nrm, V, N)  # Table I: 3.9 deg down
    assert not seen[inner & (p[:, 2] < 45.0)].any()  # the deep inside, never
    assert seen[inner].mean() < 0.25  # only the inner wall under the far rim
    assert seen[wall].all()
    assert not seen[~inner & (p[:, 2] < 8.0)].any()  # the bottom faces down


def test_a_mug_handles_inner_face_is_reachable_only_in_part(truths):
    _, truth = truths["mug"]
    p, nrm = surface_samples(truth, 1.0)
    seen = visible_mask(truth, p, nrm, V, N)
    # the handle: a torus of radii 28 and 5.5 about (40, 0, 50) in the xz plane
    rho = np.hypot(p[:, 0] - 40.0, p[:, 2] - 50.0)
    on_handle = (np.abs(np.hypot(rho - 28.0, p[:, 1]) - 5.5) < 0.3) & (p[:, 0] > 41.0)
    to_hole = np.column_stack([40.0 - p[:, 0], np.zeros(len(p)), 50.0 - p[:, 2]])
    to_hole /= np.linalg.norm(to_hole, axis=1, keepdims=True)
    inner_face = on_handle & (rho < 28.0) & (np.einsum("ij,ij->i", nrm, to_hole) > 0.7)
    assert inner_face.sum() > 300
    assert 0.5 < seen[inner_face].mean() < 0.95
    assert seen[inner_face & (p[:, 0] < 48.0)].mean() < 0.7   # beside the body: hidden
    assert seen[inner_face & (p[:, 0] > 56.0)].all()          # across the hole: seen
    cavity = (np.hypot(p[:, 0], p[:, 1]) < 36.5) & (p[:, 2] > 6.0) & (p[:, 2] < 80.0)
    assert not seen[cavity].any()  # the mug's inside below the rim's sight line


def test_reachable_surface_is_bounded_and_fast(truths):
    _, truth = truths["bowl"]
    t = time.process_time()  # CPU seconds: a loaded machine stretches the wall clock
    q, qn = reachable_surface(truth, V, N, spacing_mm=1.0)
    assert time.process_time() - t < 10.0
    assert q.shape == qn.shape and q.shape[1] == 3
    assert np.allclose(np.linalg.norm(qn, axis=1), 1.0)
    all_p, _ = surface_samples(truth, 1.0)
    assert 0.3 < len(q) / len(all_p) < 0.6


# ---------------------------------------------------------------- the bench's figure
def test_truth_coverage_per_modality(truths):
    spec = importlib.util.spec_from_file_location("coverage_truth",
                                                  ROOT / "bench" / "coverage_truth.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    _, truth = truths["aluminium_block"]
    reach, _ = reachable_surface(truth, V, N, spacing_mm=1.0, seed=3)
    front = reach[reach[:, 1] < -14.0]  # the side facing -y only: 2000 of 6400 mm^2
    got = mod.truth_coverage([truth], {"OA": reach, "US": front, "none": np.zeros((0, 3))},
                             V, N, spacing_mm=2.0)
    assert got["OA"] == 1.0
    # the side facing -y and the 2 mm of its neighbours next to it: (2000 + 160) / 6400
    assert got["US"] == pytest.approx(2160 / 6400, abs=0.02)
    assert got["none"] == 0.0
    levels = mod.truth_coverage([truth], {"OA": reach[reach[:, 2] < 20.0]}, V, N,
                                spacing_mm=2.0, z_range_mm=(0.0, 20.0))
    assert levels["OA"] > 0.97


def test_the_us_reference_is_the_surface_within_its_incidence(truths):
    """bench/scan_coverage.py holds each modality to what it can reach: US (echoes within ~15
    deg of head on) to the block's faces alone, met square by some table angle; OA (60 deg)
    to the same; a surface that faces the table more than 15 deg from a level beam
    drops out of US's reference only (a bowl's foot)."""
    spec = importlib.util.spec_from_file_location("coverage_truth",
                                                  ROOT / "bench" / "coverage_truth.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    _, block = truths["aluminium_block"]
    oa = mod.reachable_truth([block], V, N, 2.0, (2.0, 38.0), 60.0)
    us = mod.reachable_truth([block], V, N, 2.0, (2.0, 38.0), 15.0)
    assert len(oa) > 0 and len(us) == pytest.approx(len(oa), rel=0.05)
    low = (3.5, 13.5)  # the bowl's foot: its normals point 57-74 deg below level
    _, bowl = truths["bowl"]
    assert len(mod.reachable_truth([bowl], V, N, 2.0, low, 60.0)) > 10
    assert len(mod.reachable_truth([bowl], V, N, 2.0, low, 15.0)) == 0
