"""hil_sim meshes: tessellated primitives ray-cast like the analytic ones within the tessellation's
own error, materials per region, the echoes of surfaces inside an object, users' mesh files."""

import math

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from dmdsm.sim.physics.mesh import EMBREE, Mesh
from dmdsm.sim.physics.scene import (
    Box,
    Cylinder,
    Scene,
    SceneObject,
    Sphere,
    rodrigues,
    table_frame,
)

SECTIONS = 256          # cylinder: segments around
LAT, LON = 96, 192      # uv sphere: segments pole to pole, around


def cylinder_bound(r: float, sections: int = SECTIONS) -> float:
    """Sagitta of a chord of a regular polygon: how far its sides lie inside the circle (mm)."""
    return r * (1 - math.cos(math.pi / sections))


def sphere_rho(lat: int = LAT, lon: int = LON) -> float:
    """Largest angular circumradius of a uv-sphere triangle (rad): half its longest side,
    the diagonal of a lat x lon cell."""
    return math.hypot(math.pi / lat, 2 * math.pi / lon) / 2


def sphere_bound(r: float) -> float:
    """How far the uv sphere's triangles lie inside the sphere at most (mm): the sagitta of
    the widest triangle's circumcircle, r (1 - cos rho)."""
    return r * (1 - math.cos(sphere_rho()))


def test_embree_casts_the_rays():
    assert EMBREE  # a dependency: without it the fallback caster is 100x slower


def test_the_bounds_hold_for_the_tessellations_themselves():
    """The error bound is the tessellation's: no face plane lies deeper inside than it."""
    cyl = trimesh.creation.cylinder(radius=30.0, height=80.0, sections=SECTIONS)
    side = np.abs(cyl.face_normals[:, 2]) < 0.5
    depth = 30.0 - np.abs(np.einsum("ij,ij->i", cyl.triangles[side, 0], cyl.face_normals[side]))
    assert depth.max() <= cylinder_bound(30.0) + 1e-9
    assert depth.max() > 0.9 * cylinder_bound(30.0)  # and the bound is not loose
    sph = trimesh.creation.uv_sphere(radius=40.0, count=[LAT, LON])
    depth = 40.0 - np.abs(np.einsum("ij,ij->i", sph.triangles[:, 0], sph.face_normals))
    assert depth.max() <= sphere_bound(40.0) + 1e-9


def posed(yaw: float, tilt: float) -> np.ndarray:
    return rodrigues(np.array([0, 0, 1.0]), math.radians(yaw)) @ \
        rodrigues(np.array([1.0, 0, 0]), math.radians(tilt))


def analytic_and_mesh(kind: str, R: np.ndarray):
    """(analytic, mesh, bound mm, normal tolerance rad, rim check) for one kind of primitive."""
    center = np.array([3.0, -2.0, 50.0])
    if kind == "cylinder":
        r, h = 30.0, 80.0
        a = Cylinder(center=center, R=R, radius=r, half_length=h / 2)
        m = trimesh.creation.cylinder(radius=r, height=h, sections=SECTIONS)
        return a, Mesh(center=center, R=R, mesh=m), cylinder_bound(r), 2 * math.pi / SECTIONS
    if kind == "sphere":
        r = 40.0
        a = Sphere(center=center, R=R, radius=r)
        m = trimesh.creation.uv_sphere(radius=r, count=[LAT, LON])
        return a, Mesh(center=center, R=R, mesh=m), sphere_bound(r), 2 * sphere_rho()
    half = np.array([25.0, 15.0, 20.0])
    a = Box(center=center, R=R, half=half)
    m = trimesh.creation.box(extents=2 * half)
    return a, Mesh(center=center, R=R, mesh=m), 1e-9, 1e-9


def near_an_edge(kind: str, a, p: np.ndarray, margin: float) -> bool:
    """Whether the analytic hit point p (local frame) lies within margin of a rim or edge,
    where the inscribed mesh may be passed by a ray that grazes the analytic solid."""
    if kind == "cylinder":
        return abs(abs(p[2]) - a.half_length) < margin
    if kind == "box":
        return bool(np.sum(np.abs(np.abs(p) - a.half) < margin) >= 2)
    return False


@settings(max_examples=60, deadline=None)
@given(kind=st.sampled_from(["cylinder", "sphere", "box"]),
       yaw=st.floats(-180, 180), tilt=st.floats(-30, 30),
       az=st.floats(0, 2 * math.pi), el=st.floats(-1.2, 1.2),
       seed=st.integers(0, 2**31 - 1))
def test_tessellated_primitives_cast_like_the_analytic_ones(kind, yaw, tilt, az, el, seed):
    """Rays from all around at random offsets: the mesh hits only where the analytic solid
    is hit (it is inscribed), it hits wherever the analytic one is hit squarely enough away
    from a rim, and there its distance is within bound / cos(incidence + facet tilt) and its
    normal within the facets' angular size of the analytic one."""
    R = posed(yaw, tilt)
    a, m, bound, normal_tol = analytic_and_mesh(kind, R)
    rng = np.random.default_rng(seed)
    toward = -np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    d = np.tile(R.T @ toward, (400, 1))  # in the local frame (the shapes share R, center)
    e1 = np.cross(d[0], [0.3, 0.1, 0.9])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(d[0], e1)
    off = rng.uniform(-50, 50, (400, 2))
    o = -120.0 * d + off[:, :1] * e1 + off[:, 1:] * e2
    with np.errstate(all="ignore"):  # the analytic cylinder with a beam (nearly) level
        ta, na = a.local_hit(o, d)
    tm, nm, face = m.local_hit_faces(o, d)
    hit_a, hit_m = np.isfinite(ta), np.isfinite(tm)
    assert not (hit_m & ~hit_a).any()  # inscribed: never a hit where the solid is missed
    cos_a = np.abs(np.einsum("ij,ij->i", na, d))
    p = o + np.where(hit_a, ta, 0)[:, None] * d
    square = hit_a & (cos_a > 0.5) & ~np.array(
        [near_an_edge(kind, a, q, 0.5) for q in p])
    assert hit_m[square].all()
    both = square & hit_m
    assert (face[both] >= 0).all()
    tol = bound / np.cos(np.minimum(np.arccos(cos_a[both]) + normal_tol, 1.5)) + 1e-6
    assert (np.abs(tm[both] - ta[both]) <= tol).all()
    assert (tm[both] >= ta[both] - 1e-6).all()  # the inscribed surface is never nearer
    angle = np.arccos(np.clip(np.einsum("ij,ij->i", nm[both], na[both]), -1, 1))
    assert (angle <= normal_tol + 1e-6).all()


@settings(max_examples=25, deadline=None)
@given(kind=st.sampled_from(["cylinder", "sphere", "box"]),
       theta=st.floats(0, 360), dx=st.floats(-10, 10), dz=st.floats(-10, 10),
       yaw=st.floats(-180, 180), tilt=st.floats(-20, 20))
def test_a_scene_of_the_mesh_gives_the_same_shots(kind, theta, dx, dz, yaw, tilt):
    """The 19-ray spot on the turntable: distance, overlap, incidence and material of each
    shot as the analytic shape's, within the tessellation's bound."""
    R = posed(yaw, tilt)
    a, m, bound, normal_tol = analytic_and_mesh(kind, R)
    sa = Scene(objects=[SceneObject("o", "plastic", a)])
    sm = Scene(objects=[SceneObject("o", "plastic", m)])
    v = sa.v / np.linalg.norm(sa.v)
    centre = sa.X_R + rodrigues(sa.n, math.radians(theta)) @ table_frame(sa.n) @ a.center
    e1 = np.cross(v, [0, 0, 1.0])
    e1 /= np.linalg.norm(e1)
    S = centre - 100 * v + dx * e1 + dz * np.cross(v, e1)
    ha, hm = sa.cast(S, theta), sm.cast(S, theta)
    assert np.isfinite(ha.d) and np.isfinite(hm.d)  # aimed within the object's outline
    if ha.overlap < 1 or ha.cos_incidence < 0.5 or ha.later:
        return  # a spot on a rim or at a grazing angle: covered ray by ray above
    assert hm.overlap == ha.overlap and hm.material == "plastic" and hm.obj == "o"
    assert hm.d == pytest.approx(ha.d, abs=bound / 0.3 + 1e-6)
    assert hm.cos_incidence == pytest.approx(ha.cos_incidence, abs=math.sin(normal_tol) + 1e-6)
