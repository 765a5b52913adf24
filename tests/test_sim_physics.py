"""hil_sim physics: ray-cast distances against analytic ones, arrival times, material rules."""

import numpy as np
import pytest

from dmdsm.sim.physics.objects import (
    HOUSEHOLD,
    SIZE_LIMIT_MM,
    bounding_size,
    household,
    rig_vertical,
)
from dmdsm.sim.physics.scene import Box, Scene, SceneObject, Sphere, rodrigues, table_frame, unit
from dmdsm.sim.physics.signals import (
    MATERIALS,
    SensorModel,
    arrival_times_us,
    speed_of_sound_mm_us,
    synthesize,
)

V = unit(np.array([0.0656, 0.9955, -0.0678]))


def scene_with(shape, material="aluminium", **kw):
    return Scene(objects=[SceneObject("obj", material, shape)], **kw)


def test_box_face_distance_matches_the_plane_intersection():
    sc = scene_with(Box(center=np.array([0.0, 0.0, 20.0]), half=np.array([25.0, 15.0, 20.0])))
    S = np.array([235.0, 265.0, 20.0])
    hit = sc.cast(S, 0.0)
    # the face y = -15 of the table frame, as a plane in {0}
    basis = table_frame(sc.n)
    p0 = sc.X_R + basis @ np.array([0, -15.0, 20.0])
    normal = basis @ np.array([0, -1.0, 0])
    d_plane = np.dot(p0 - S, normal) / np.dot(V, normal)
    assert hit.d == pytest.approx(d_plane, abs=1e-9)
    assert hit.overlap == 1.0 and hit.material == "aluminium"


def test_sphere_distance_on_axis():
    sc = scene_with(Sphere(center=np.array([0.0, 0.0, 40.0]), radius=40.0), spot_radius=1e-6)
    center = sc.X_R + table_frame(sc.n) @ np.array([0, 0, 40.0])
    S = center - 55.0 * V
    assert sc.cast(S, 30.0).d == pytest.approx(15.0, abs=1e-6)  # rotation does not matter


def test_turntable_rotation_moves_objects_by_rodrigues():
    sc = Scene(objects=rig_vertical(offset_x=25.0, offset_y=0.0))
    basis = table_frame(sc.n)
    axis_pt = sc.X_R + basis @ np.array([25.0, 0, 30.0])
    for theta in (0.0, 90.0, 180.0):
        p = sc.X_R + rodrigues(sc.n, np.radians(theta)) @ (axis_pt - sc.X_R)
        S = p - 20.0 * V
        hit = sc.cast(S, theta)
        assert hit.obj == "rig_filament_vertical"
        assert 19.7 < hit.d < 20.0  # the filament's front surface, radius 0.25 mm


def test_filament_response_grows_with_overlap():
    sc = Scene(objects=rig_vertical())
    basis = table_frame(sc.n)
    axis_pt = sc.X_R + basis @ np.array([25.0, 0, 30.0])
    side = unit(np.cross(V, sc.n))
    overlaps = [sc.cast(axis_pt - 20 * V + off * side, 0.0).overlap
                for off in (0.0, 0.3, 0.45, 0.6, 1.0)]
    assert overlaps[0] == 1.0 and overlaps[-1] == 0.0
    assert all(a >= b for a, b in zip(overlaps, overlaps[1:]))


def test_household_objects_fit_the_scanner():
    for name in HOUSEHOLD:
        (obj,) = household(name)
        assert all(s <= lim for s, lim in zip(bounding_size(obj), SIZE_LIMIT_MM)), name
    assert {HOUSEHOLD[n][0] for n in HOUSEHOLD} == {"aluminium", "apple", "foam", "glass",
                                                   "paper", "plastic", "steel"}


def test_speed_of_sound_from_temperature():
    assert speed_of_sound_mm_us(20.0) == pytest.approx(0.3432, abs=2e-4)
    assert speed_of_sound_mm_us(30.0) - speed_of_sound_mm_us(20.0) == pytest.approx(0.0059,
                                                                                   abs=3e-4)


def _peak_time(x, t_us, around, half_width=3.0):
    sel = np.abs(t_us - around) < half_width
    env = np.abs(x[sel])
    return t_us[sel][env.argmax()]


@pytest.mark.parametrize("material", ["aluminium", "plastic", "graphite"])
def test_oa_one_way_and_us_round_trip_arrival_times(material):
    model = SensorModel(noise_counts=0.0, spike_prob=0.0)
    model.materials[material] = MATERIALS[material].__class__(
        **{**MATERIALS[material].__dict__, "roughness_oa_mm": 0.0, "roughness_us_mm": 0.0,
           "variability": 0.0, "ring_gain": 0.0})
    sc = scene_with(Box(center=np.array([0.0, 0.0, 20.0]), half=np.array([25.0, 15.0, 20.0])),
                    material=material)
    hit = sc.cast(np.array([235.0, 263.0, 20.0]), 0.0)
    t_us = np.arange(0, 120, 0.005)
    x = synthesize(hit, model, t_us, np.random.default_rng(0))
    oa, us = arrival_times_us(hit.d, model)
    assert us - model.t0_us_us == pytest.approx(2 * (oa - model.t0_oa_us))
    assert _peak_time(x, t_us, oa) == pytest.approx(oa, abs=0.01)
    assert _peak_time(x, t_us, us) == pytest.approx(us, abs=0.01)


def test_no_oa_on_glass_or_steel_and_no_us_on_foam():
    model = SensorModel(noise_counts=0.0, spike_prob=0.0, bang_amp=0.0)
    t_us = np.arange(0, 150, 0.05)
    box = Box(center=np.array([0.0, 0.0, 20.0]), half=np.array([25.0, 15.0, 20.0]))
    for material, has_oa, has_us in (("glass", False, True), ("steel", False, True),
                                     ("foam", True, False), ("aluminium", True, True)):
        hit = scene_with(box, material=material).cast(np.array([235.0, 263.0, 20.0]), 0.0)
        x = synthesize(hit, model, t_us, np.random.default_rng(1))
        oa, us = arrival_times_us(hit.d, model)
        e_oa = np.abs(x[np.abs(t_us - oa) < 2]).max()
        e_us = np.abs(x[np.abs(t_us - us) < 2]).max()
        assert (e_oa > 100) == has_oa, material
        assert (e_us > 100) == has_us, material


def test_default_noise_gives_the_papers_ranging_error_with_ideal_processing():
    from dmdsm.sim.physics.noise_check import depth_errors, summary

    s = summary(depth_errors(n_points=120, seed=5))
    assert 0.045 < s["oa"][0] < 0.075 and 0.04 < s["oa"][1] < 0.08    # paper 0.06 +/- 0.06
    assert 0.12 < s["us"][0] < 0.18 and 0.08 < s["us"][1] < 0.15      # paper 0.15 +/- 0.11
