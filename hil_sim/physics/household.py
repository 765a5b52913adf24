"""The household set made of meshes: objects with handles, necks, concave insides, labels, lids.

Every object is generated when its scene is mounted, procedurally with trimesh's creation tools
(revolved profiles, boxes, tori) and manifold3d's booleans, so the repository holds no mesh
files and the same code gives the same triangles every time. Dimensions in mm, in the object's
own frame with its bottom at z = 0 on the table's axis. Materials are the paper's seven
(aluminium, apple, foam, glass, paper, plastic, steel); a region of faces may have another
(label, lid), and a container may be filled (`fill`, a liquid the ultrasound crosses).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import trimesh

from .mesh import Mesh
from .scene import SceneObject

SECTIONS = 96  # segments around a revolved profile


def _revolve(profile: list[tuple[float, float]], sections: int = SECTIONS,
             step: float | None = None) -> trimesh.Trimesh:
    """A solid of revolution about z from an (r, z) profile that starts and ends on the axis
    (mm), its normals out; with `step`, no profile segment longer than that (mm)."""
    pts = _densify(profile, step) if step else np.asarray(profile, float)
    m = trimesh.creation.revolve(pts, sections=sections)
    if m.volume < 0:
        m.invert()
    return m


def _densify(profile: list[tuple[float, float]], step: float) -> np.ndarray:
    """The profile with points added so no segment is longer than `step` mm: faces short
    enough that a region (label, lid) can be told by where their centres lie."""
    pts = np.asarray(profile, float)
    out = [pts[0]]
    for a, b in zip(pts[:-1], pts[1:]):
        k = max(int(np.ceil(np.linalg.norm(b - a) / step)), 1)
        out += [a + (b - a) * i / k for i in range(1, k + 1)]
    return np.array(out)


def _cup_profile(r_bottom: float, r_top: float, height: float, wall: float, base: float,
                 cuts: tuple[float, ...] = ()) -> list[tuple[float, float]]:
    """An open container's profile: outside up (through the heights `cuts`, where a region
    begins or ends), over the rim, inside down to the base."""
    side = [(r_bottom + (r_top - r_bottom) * z / height, z) for z in sorted(cuts)]
    rim = [(r_bottom, 0.0), *side, (r_top, height), (r_top - wall, height)]
    inner_bottom = r_bottom - wall + (r_top - r_bottom) * base / height
    return [(0.0, 0.0), *rim, (inner_bottom, base), (0.0, base)]


def _regions_by(mesh: trimesh.Trimesh, rule: Callable[[np.ndarray, np.ndarray], np.ndarray]
                ) -> np.ndarray:
    """Region number per face from a rule on face centroids and normals (N x 3 each)."""
    return np.asarray(rule(mesh.triangles_center, mesh.face_normals), int)


def _obj(name: str, material: str, mesh: trimesh.Trimesh, regions: dict[int, str] | None = None,
         face_region: np.ndarray | None = None, fill: str | None = None,
         interior: bool = False, names: tuple[str, ...] = (),
         fill_level: float = np.inf) -> SceneObject:
    """A SceneObject of a mesh standing centred on the table (its origin at the table's)."""
    shape = Mesh(center=np.zeros(3), mesh=mesh, face_region=face_region, region_names=names,
                 interior=interior)
    return SceneObject(name, material, shape, regions=dict(regions or {}), fill=fill,
                       fill_level=fill_level)


def _bumpy(mesh: trimesh.Trimesh, amp: float, seed: int, centre_z: float) -> trimesh.Trimesh:
    """Uneven skin: each vertex moved along its direction from (0, 0, centre_z) by a smooth
    sum of low-order waves (amp mm peak); the topology is kept, so the mesh stays closed."""
    m = mesh.copy()
    rng = np.random.default_rng(seed)
    p = m.vertices - [0, 0, centre_z]
    r = np.linalg.norm(p, axis=1)
    u = p / np.maximum(r, 1e-9)[:, None]
    bump = np.zeros(len(p))
    for _ in range(6):
        k = rng.normal(size=3) * 2.5
        bump += np.sin(u @ k + rng.uniform(0, 2 * np.pi))
    m.vertices = m.vertices + (amp / 6 * bump)[:, None] * u
    return m


# ---------------------------------------------------------------- the objects
def mug() -> SceneObject:
    """Steel mug, 80 mm across, 95 mm tall, 3 mm wall, with a ring handle: hollow."""
    body = _revolve(_cup_profile(40.0, 40.0, 95.0, 3.0, 5.0))
    handle = trimesh.creation.torus(28.0, 5.5, major_sections=48, minor_sections=16)
    handle.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    handle.apply_translation([40.0, 0.0, 50.0])
    cavity = trimesh.creation.cylinder(radius=37.0, height=95.0, sections=SECTIONS)
    cavity.apply_translation([0, 0, 5.0 + 95.0 / 2 + 0.5])
    m = trimesh.boolean.difference([trimesh.boolean.union([body, handle]), cavity])
    return _obj("mug", "steel", m, interior=True)


def glass_bottle() -> SceneObject:
    """Glass bottle with shoulder and neck, 70 mm across, 250 mm tall, 2.5 mm wall, water up
    to 150 mm."""
    outer = [(0, 0), (35, 0), (35, 160), (30, 180), (16, 200), (13, 215), (13, 250),
             (11, 250), (11, 215), (14, 200), (28, 180), (32.5, 160), (32.5, 4), (0, 4)]
    return _obj("glass_bottle", "glass", _revolve(outer), fill="water", interior=True,
                fill_level=150.0)


def plastic_bottle_neck() -> SceneObject:
    """Plastic water bottle, 66 mm across, 215 mm: waisted body, shoulder, open neck, 1 mm
    wall; water inside."""
    outer = [(0, 0), (33, 0), (33, 70), (29, 85), (33, 100), (33, 160), (20, 185),
             (14, 195), (14, 215), (12.5, 215), (12.5, 196), (19, 185), (32, 160), (32, 100),
             (28, 85), (32, 70), (32, 1.5), (0, 1.5)]
    return _obj("plastic_bottle_neck", "plastic", _revolve(outer), fill="water",
                interior=True)


def bowl() -> SceneObject:
    """Plastic bowl: 164 mm across, 64 mm tall, 4 mm wall, concave inside (a spherical cap
    shell)."""
    a = np.linspace(0.0, np.radians(75), 24)
    r_out, r_in, zc = 85.0, 81.0, 85.0
    outer = [(r_out * np.sin(t), zc - r_out * np.cos(t)) for t in a]
    inner = [(r_in * np.sin(t), zc - r_in * np.cos(t)) for t in a[::-1]]
    profile = [(0.0, 0.0), *outer[1:], *inner[:-1], (0.0, zc - r_in)]
    return _obj("bowl", "plastic", _revolve(profile), interior=True)


def jar_with_lid() -> SceneObject:
    """Glass jar (80 mm across, 110 mm body) closed by a steel lid 12 mm tall: region 1."""
    outer = _revolve([(0, 0), (40, 0), (40, 100), (36, 104), (36, 110), (38, 110),
                      (38, 122), (0, 122)], 64)
    cavity = _revolve([(0, 4), (36.5, 4), (36.5, 99), (33, 103), (33, 119), (0, 119)])
    m = trimesh.boolean.difference([outer, cavity])
    lid = _regions_by(m, lambda c, n: c[:, 2] > 109.9)
    return _obj("jar_with_lid", "glass", m, regions={1: "steel"}, face_region=lid,
                interior=True, names=("jar", "lid"))


def can_with_label() -> SceneObject:
    """Steel food can (74 mm across, 110 mm) with a paper label around 15..95 mm: region 1."""
    outer = _revolve([(0, 1), (34, 0), (37, 2), (37, 15), (37, 95), (37, 108), (34, 110),
                      (0, 109)])
    label = _regions_by(outer, lambda c, n: (np.hypot(c[:, 0], c[:, 1]) > 36.5)
                        & (c[:, 2] > 15) & (c[:, 2] < 95))
    return _obj("can_with_label", "steel", outer, regions={1: "paper"}, face_region=label,
                names=("can", "label"))


def glass_jar_labelled() -> SceneObject:
    """Glass jar with a paper label band (30..80 mm), hollow, 3 mm wall: OA only on the label."""
    m = _revolve(_cup_profile(38.0, 38.0, 105.0, 3.0, 5.0, cuts=(30.0, 80.0)))  # label edges
    label = _regions_by(m, lambda c, n: (np.hypot(c[:, 0], c[:, 1]) > 37.5)
                        & (c[:, 2] > 30) & (c[:, 2] < 80))
    return _obj("glass_jar_labelled", "glass", m, regions={1: "paper"}, face_region=label,
                interior=True, names=("glass", "label"))


def cereal_box() -> SceneObject:
    """Paper cereal box, 190 x 70 x 280 mm."""
    m = trimesh.creation.box(extents=[190.0, 70.0, 280.0])
    m.apply_translation([0, 0, 140.0])
    return _obj("cereal_box", "paper", m)


def tissue_box_slot() -> SceneObject:
    """Paper tissue box with the slot in its top, 240 x 120 x 90 mm, 1.5 mm card: hollow."""
    outer = trimesh.creation.box(extents=[240.0, 120.0, 90.0])
    inner = trimesh.creation.box(extents=[237.0, 117.0, 87.0])
    slot = trimesh.creation.box(extents=[150.0, 30.0, 10.0])
    slot.apply_translation([0, 0, 45.0])
    m = trimesh.boolean.difference([outer, inner, slot])
    m.apply_translation([0, 0, 45.0])
    return _obj("tissue_box_slot", "paper", m, interior=True)


def pear() -> SceneObject:
    """A pear (apple material): revolved pear profile, uneven skin, 70 mm across, 105 mm."""
    z = np.linspace(0, 100, 40)
    r = 35 * np.sin(np.pi * np.clip(z / 100, 0, 1)) ** 0.7 * (1 - 0.45 * (z / 100) ** 1.5)
    r = r * (1 + 0.25 * np.exp(-((z - 30) / 20) ** 2))
    prof = [(0.0, 0.0), *zip(r[1:-1], z[1:-1]), (0.0, 100.0)]
    body = _bumpy(_revolve(prof, 64), 1.5, 11, 40.0)
    stem = trimesh.creation.cylinder(radius=2.0, height=12.0, sections=12)
    stem.apply_translation([0, 0, 104.0])
    m = trimesh.boolean.union([body, stem])
    m.apply_translation([0, 0, -m.bounds[0, 2]])
    return _obj("pear", "apple", m)


def apple_uneven() -> SceneObject:
    """An apple, 78 mm across: a dimpled sphere with an uneven skin."""
    m = trimesh.creation.icosphere(subdivisions=4, radius=39.0)
    top = np.clip((m.vertices[:, 2] / 39.0 - 0.7) / 0.3, 0, 1)
    bottom = np.clip((-m.vertices[:, 2] / 39.0 - 0.8) / 0.2, 0, 1)
    m.vertices[:, 2] -= 8.0 * top ** 2 - 4.0 * bottom ** 2
    m = _bumpy(m, 1.2, 7, 0.0)
    m.apply_translation([0, 0, -m.bounds[0, 2]])
    return _obj("apple_uneven", "apple", m)


def paper_cup_thin() -> SceneObject:
    """Paper cup, tapered 56 -> 80 mm across, 95 mm, 0.6 mm wall: the thin-walled cup."""
    return _obj("paper_cup_thin", "paper", _revolve(_cup_profile(28.0, 40.0, 95.0, 0.6, 2.0)),
                interior=True)


def foam_cup_tapered() -> SceneObject:
    """Foam cup, tapered 60 -> 90 mm across, 110 mm, 3 mm wall."""
    return _obj("foam_cup_tapered", "foam",
                _revolve(_cup_profile(30.0, 45.0, 110.0, 3.0, 4.0)))


def foam_packing() -> SceneObject:
    """Foam packing insert, 150 x 100 x 60 mm with a round 70 mm pocket 40 mm deep."""
    block = trimesh.creation.box(extents=[150.0, 100.0, 60.0])
    pocket = trimesh.creation.cylinder(radius=35.0, height=41.0, sections=SECTIONS)
    pocket.apply_translation([0, 0, 30.0 - 20.0 + 0.5])
    m = trimesh.boolean.difference([block, pocket])
    m.apply_translation([0, 0, 30.0])
    return _obj("foam_packing", "foam", m)


def soda_can_shaped() -> SceneObject:
    """Aluminium drinks can with its necked top and domed bottom, 66 mm across, 122 mm."""
    prof = [(0, 8), (20, 1), (27, 0), (33, 6), (33, 108), (27, 118), (27, 122), (0, 121)]
    return _obj("soda_can_shaped", "aluminium", _revolve(prof))


def aluminium_bottle_neck() -> SceneObject:
    """Aluminium bottle with a shoulder and a screw neck, 72 mm across, 230 mm: hollow."""
    prof = [(0, 0), (36, 0), (36, 170), (18, 200), (15, 205), (15, 230), (13.5, 230),
            (13.5, 205), (16.5, 200), (35, 170), (35, 1), (0, 1)]
    return _obj("aluminium_bottle_neck", "aluminium", _revolve(prof), interior=True)


def steel_pot() -> SceneObject:
    """Steel cooking pot, 180 mm across, 110 mm, two side handles, 1.5 mm wall."""
    body = _revolve(_cup_profile(90.0, 90.0, 110.0, 1.5, 3.0))
    parts = [body]
    for side in (-1, 1):
        h = trimesh.creation.box(extents=[30.0, 40.0, 8.0])
        h.apply_translation([side * 103.0, 0.0, 95.0])
        parts.append(h)
    return _obj("steel_pot", "steel", trimesh.boolean.union(parts), interior=True)


def wine_glass() -> SceneObject:
    """Glass wine glass: foot, stem and bowl, 80 mm across, 200 mm."""
    prof = [(0, 0), (38, 0), (38, 2), (5, 6), (4, 110), (20, 120), (35, 150), (38, 175),
            (36, 200), (34.5, 200), (36.5, 175), (33.5, 150), (19, 122), (0, 115)]
    return _obj("wine_glass", "glass", _revolve(prof), interior=True)


def plastic_jug() -> SceneObject:
    """Plastic jug with a handle: 110 mm across, 200 mm, 2 mm wall."""
    body = _revolve(_cup_profile(55.0, 48.0, 200.0, 2.0, 3.0))
    handle = trimesh.creation.torus(55.0, 8.0, major_sections=48, minor_sections=16)
    handle.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    handle.apply_translation([50.0, 0.0, 110.0])
    cavity = _revolve([(0, 3), (52.9, 3), (45.9, 200.5), (0, 200.5)])
    return _obj("plastic_jug", "plastic",
                trimesh.boolean.difference([trimesh.boolean.union([body, handle]), cavity]),
                interior=True)


def paper_tube() -> SceneObject:
    """Paper tube (a kitchen roll core), 45 mm across, 2 mm wall, 250 mm, open both ends."""
    m = trimesh.creation.annulus(r_min=20.5, r_max=22.5, height=250.0, sections=SECTIONS)
    m.apply_translation([0, 0, 125.0])
    return _obj("paper_tube", "paper", m, interior=True)


def steel_bowl() -> SceneObject:
    """Steel mixing bowl, 220 mm across, 1 mm wall (a hemispherical shell on a flat ring)."""
    a = np.linspace(0.0, np.pi / 2, 28)
    r_out, r_in = 110.0, 109.0
    outer = [(r_out * np.sin(t), r_out - r_out * np.cos(t)) for t in a]
    inner = [(r_in * np.sin(t), r_out - r_in * np.cos(t)) for t in a[::-1]]
    return _obj("steel_bowl", "steel", _revolve([*outer, *inner]), interior=True)


#: the mesh household set: scene name -> its object, made when mounted
MESH_HOUSEHOLD: dict[str, Callable[[], SceneObject]] = {
    f.__name__: f for f in (
        mug, glass_bottle, plastic_bottle_neck, bowl, jar_with_lid, can_with_label,
        glass_jar_labelled, cereal_box, tissue_box_slot, pear, apple_uneven, paper_cup_thin,
        foam_cup_tapered, foam_packing, soda_can_shaped, aluminium_bottle_neck, steel_pot,
        wine_glass, plastic_jug, paper_tube, steel_bowl)}
