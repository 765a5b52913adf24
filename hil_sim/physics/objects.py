"""Objects that stand on the turntable: calibration rig, aluminium validation block, household set.

Dimensions in mm, in the turntable frame (origin at the table centre, z up along n). The
household set covers the seven materials of the paper's Fig. 5 with two objects each, all
inside the scanner's 270 x 270 x 430 mm limit; the paper's experiments use these primitives.
The household set made of meshes (handles, necks, labels, lids, liquids) is in household.py
and is mounted by the same scene names.
"""

from __future__ import annotations

import numpy as np

from .scene import Box, Cylinder, SceneObject, Sphere

SIZE_LIMIT_MM = (270.0, 270.0, 430.0)  # width, depth, height the scanner accepts (paper §I)
FILAMENT_DIAMETER_MM = 0.5             # the rig's graphite filament (a rig parameter)
BLOCK_SIZE_MM = (50.0, 30.0, 40.0)     # aluminium validation block: x, y, z


def _axis_to(direction: np.ndarray) -> np.ndarray:
    """Rotation taking local z onto `direction` (a unit vector)."""
    z = np.asarray(direction, float) / np.linalg.norm(direction)
    helper = np.array([1.0, 0, 0]) if abs(z[0]) < 0.9 else np.array([0, 1.0, 0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])


def rig_horizontal(height: float = 20.0, tip_y: float = -10.0, length: float = 40.0,
                   diameter: float = FILAMENT_DIAMETER_MM) -> list[SceneObject]:
    """The filament held horizontally, its tip toward the sensor (-y of the table), Fig. 2(a)."""
    center = np.array([0.0, tip_y + length / 2, height])
    shape = Cylinder(center=center, R=_axis_to(np.array([0.0, 1.0, 0.0])),
                     radius=diameter / 2, half_length=length / 2)
    return [SceneObject("rig_filament_horizontal", "graphite", shape)]


def rig_vertical(offset_x: float = 25.0, offset_y: float = 0.0, bottom: float = 5.0,
                 length: float = 60.0, diameter: float = FILAMENT_DIAMETER_MM
                 ) -> list[SceneObject]:
    """The filament held vertically (along n), off the table centre, Fig. 2(b, c)."""
    shape = Cylinder(center=np.array([offset_x, offset_y, bottom + length / 2]),
                     radius=diameter / 2, half_length=length / 2)
    return [SceneObject("rig_filament_vertical", "graphite", shape)]


def aluminium_block(size: tuple[float, float, float] = BLOCK_SIZE_MM) -> list[SceneObject]:
    """The validation block of §V-A2, centred on the table."""
    half = np.asarray(size, float) / 2
    return [SceneObject("aluminium_block", "aluminium",
                        Box(center=np.array([0.0, 0.0, half[2]]), half=half))]


def _can(r: float, h: float) -> Cylinder:
    return Cylinder(center=np.array([0.0, 0.0, h / 2]), radius=r, half_length=h / 2)


def _box(x: float, y: float, z: float) -> Box:
    return Box(center=np.array([0.0, 0.0, z / 2]), half=np.array([x, y, z]) / 2)


#: the household set: object id -> (material, shape)
HOUSEHOLD = {
    "soda_can": ("aluminium", lambda: _can(33.0, 122.0)),
    "aluminium_bottle": ("aluminium", lambda: _can(36.0, 180.0)),
    "apple_red": ("apple", lambda: Sphere(center=np.array([0.0, 0.0, 40.0]), radius=40.0)),
    "apple_green": ("apple", lambda: Sphere(center=np.array([0.0, 0.0, 36.0]), radius=36.0)),
    "foam_block": ("foam", lambda: _box(100.0, 100.0, 50.0)),
    "foam_cup": ("foam", lambda: _can(45.0, 110.0)),
    "glass_jar": ("glass", lambda: _can(40.0, 100.0)),
    "glass_tumbler": ("glass", lambda: _can(38.0, 120.0)),
    "paper_cup": ("paper", lambda: _can(40.0, 95.0)),
    "tissue_box": ("paper", lambda: _box(120.0, 60.0, 90.0)),
    "plastic_bottle": ("plastic", lambda: _can(35.0, 200.0)),
    "plastic_tub": ("plastic", lambda: _box(110.0, 110.0, 70.0)),
    "steel_can": ("steel", lambda: _can(37.0, 110.0)),
    "steel_mug": ("steel", lambda: _can(42.0, 95.0)),
}


def household(name: str) -> list[SceneObject]:
    """One household object, centred on the table; raises ValueError for unknown names."""
    if name not in HOUSEHOLD:
        raise ValueError(f"unknown object {name!r}; known: {', '.join(HOUSEHOLD)}")
    material, make = HOUSEHOLD[name]
    return [SceneObject(name, material, make())]


def bounding_size(obj: SceneObject) -> tuple[float, float, float]:
    """Width, depth, height (mm) of an object's axis-aligned box in the table frame."""
    s = obj.shape
    if hasattr(s, "bounds"):  # a Mesh (mesh.py; not imported here: trimesh takes 0.5 s)
        w, d, h = np.diff(s.bounds(), axis=0)[0]
    elif isinstance(s, Box):
        w, d, h = 2 * s.half
    elif isinstance(s, Sphere):
        w = d = h = 2 * s.radius
    else:
        ext = np.abs(s.R) @ np.array([s.radius, s.radius, s.half_length]) * 2
        w, d, h = ext
    return float(w), float(d), float(h)


#: the household set made of meshes (household.MESH_HOUSEHOLD, made when mounted; named here
#: so that listing the scenes does not import trimesh)
MESH_SCENES = ("mug", "glass_bottle", "plastic_bottle_neck", "bowl", "jar_with_lid",
               "can_with_label", "glass_jar_labelled", "cereal_box", "tissue_box_slot", "pear",
               "apple_uneven", "paper_cup_thin", "foam_cup_tapered", "foam_packing",
               "soda_can_shaped", "aluminium_bottle_neck", "steel_pot", "wine_glass",
               "plastic_jug", "paper_tube", "steel_bowl")


def mesh_object(name: str) -> list[SceneObject]:
    """One object of the mesh household set, made now (household.py)."""
    from .household import MESH_HOUSEHOLD

    return [MESH_HOUSEHOLD[name]()]


SCENES = {
    "rig_horizontal": rig_horizontal,
    "rig_vertical": rig_vertical,
    "aluminium_block": aluminium_block,
    **{name: (lambda n=name: household(n)) for name in HOUSEHOLD},
    **{name: (lambda n=name: mesh_object(n)) for name in MESH_SCENES},
    "empty": list,  # nothing on the table (for a user's own object: dmdsm sim --object)
}
