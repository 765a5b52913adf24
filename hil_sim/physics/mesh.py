"""Objects from closed triangle meshes: the ray cast (Embree through trimesh), regions, interiors.

A `Mesh` is a `Shape` like `Box`, `Cylinder` and `Sphere`: posed on the turntable by `center`
and `R`, it answers `local_hit(o, d)` with the entry distance (mm) and outward normal per ray.
It also gives the face each ray hit (`local_hit_faces`), so a scene object can take its material
per region of faces (a label on a can, a lid on a jar), and the surfaces behind the first one
along each ray (`layers`), so the ultrasound can see a wall's inner side or a liquid inside.
The rays are cast by Intel Embree (`embreex`) through trimesh's intersector, which finds the
triangle; the distance is then computed again in float64 from that triangle's plane (Embree
works in float32). Without embreex, trimesh's own numpy intersector finds the triangles.
"""

from __future__ import annotations

import io
import os
from dataclasses import dataclass, field

import numpy as np
import trimesh

from .scene import Box, Cylinder, SceneObject, Shape, Sphere

try:  # Embree when installed (a pyproject dependency); trimesh's numpy caster otherwise
    from trimesh.ray.ray_pyembree import RayMeshIntersector as _Intersector
    EMBREE = True
except ImportError:  # pragma: no cover - exercised only without embreex
    from trimesh.ray.ray_triangle import RayMeshIntersector as _Intersector
    EMBREE = False

MAX_LAYERS = 4      # surfaces cast behind the first along one ray (an object's interior)
STEP_PAST_MM = 1e-4  # how far past a surface the next cast starts (mm; Embree is float32)


@dataclass(eq=False)
class Mesh(Shape):
    """A closed triangle mesh (mm, in its own frame; `center`, `R` place it on the table).

    `face_region` gives each face a region number (0 where absent): the scene object's
    `regions` maps region numbers to materials. `region_names` names them (for the truth and
    the docs). `interior`: cast on through the object to the surfaces inside it (a wall's inner
    side, a liquid's surface) for the deeper US echoes; off for solid objects (it costs a
    second cast per ray)."""

    mesh: trimesh.Trimesh = field(default_factory=trimesh.Trimesh)
    face_region: np.ndarray | None = None
    region_names: tuple[str, ...] = ()
    interior: bool = False
    MAX_LAYERS = MAX_LAYERS

    def __post_init__(self) -> None:
        tris = np.asarray(self.mesh.triangles, float)
        self._v0 = tris[:, 0]
        self._normals = np.asarray(self.mesh.face_normals, float)
        self._ray = _Intersector(self.mesh)
        if self.face_region is None:
            self.face_region = np.zeros(len(self.mesh.faces), int)
        self.face_region = np.asarray(self.face_region, int)
        if self.face_region.shape != (len(self.mesh.faces),):
            raise ValueError("face_region needs one region number per face")

    def local_hit(self, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Entry distance (mm, inf for a miss) and outward normal per ray, local frame."""
        t, normal, _ = self.local_hit_faces(o, d)
        return t, normal

    def local_hit_faces(self, o: np.ndarray, d: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Entry distance (mm, inf for a miss), outward normal and face index (-1 for a miss)
        per ray (o, d: N x 3 in the local frame, d unit)."""
        face = np.asarray(self._ray.intersects_first(o, d), int)
        return self._distance(o, d, face), self.face_normals(face), face

    def _distance(self, o: np.ndarray, d: np.ndarray, face: np.ndarray) -> np.ndarray:
        """Distance (mm) along each ray to the plane of its face, in float64 (inf if none)."""
        t = np.full(len(o), np.inf)
        hit = face >= 0
        if hit.any():
            f = face[hit]
            n = self._normals[f]
            den = np.einsum("ij,ij->i", d[hit], n)
            with np.errstate(divide="ignore", invalid="ignore"):
                th = np.einsum("ij,ij->i", self._v0[f] - o[hit], n) / den
            t[hit] = np.where(np.isfinite(th) & (th > 0), th, np.inf)
        return t

    def face_normals(self, face: np.ndarray) -> np.ndarray:
        """Outward unit normals of faces (any shape of indices; zero for -1), local frame."""
        f = np.asarray(face, int)
        return np.where((f >= 0)[..., None], self._normals[np.maximum(f, 0)], 0.0)

    def regions(self, face: np.ndarray) -> np.ndarray:
        """Region number of each face index (-1 for a miss)."""
        return np.where(face >= 0, self.face_region[np.maximum(face, 0)], -1)

    def layers(self, o: np.ndarray, d: np.ndarray, t: np.ndarray, face: np.ndarray,
               n: int = MAX_LAYERS) -> tuple[np.ndarray, np.ndarray]:
        """The next `n` surfaces behind the first hit (distance t, face) along each ray:
        distances (N x n, mm from o, inf where the ray has left the object) and faces
        (N x n, -1 where none)."""
        ts = np.full((len(o), n), np.inf)
        fs = np.full((len(o), n), -1)
        cur_t, cur_f = t.copy(), face.copy()
        for k in range(n):
            live = np.isfinite(cur_t) & (cur_f >= 0)
            if not live.any():
                break
            start = o[live] + (cur_t[live] + STEP_PAST_MM)[:, None] * d[live]
            f = np.asarray(self._ray.intersects_first(start, d[live]), int)
            dt = self._distance(start, d[live], f)
            nt = np.full(len(o), np.inf)
            nf = np.full(len(o), -1)
            nt[live] = cur_t[live] + STEP_PAST_MM + dt
            nf[live] = np.where(np.isfinite(dt), f, -1)
            ts[:, k], fs[:, k] = nt, nf
            cur_t, cur_f = nt, nf
        return ts, fs

    def bounds(self) -> np.ndarray:
        """2 x 3 min/max corner (mm) of the posed mesh in the turntable frame."""
        pts = np.asarray(self.mesh.vertices, float) @ self.R.T + self.center
        return np.array([pts.min(axis=0), pts.max(axis=0)])

    def signed_distance(self, points: np.ndarray) -> np.ndarray:
        """Signed distance (mm) of points in the object's own frame to its surface: positive
        inside, negative outside (trimesh's convention)."""
        return np.asarray(trimesh.proximity.signed_distance(
            self.mesh, np.asarray(points, float).reshape(-1, 3)), float)


# ---------------------------------------------------------------- the truth for judging scans
TRUTH_SECTIONS = 512  # segments around a primitive's tessellation for the truth


def surface_mesh(shape: Shape) -> trimesh.Trimesh:
    """The shape's surface as a closed mesh in its own frame (mm): a mesh as it is; a box
    exactly; a cylinder or sphere finely tessellated (within r (1 - cos(pi / 512)) inside:
    5e-4 mm at r = 30)."""
    if isinstance(shape, Mesh):
        return shape.mesh
    if isinstance(shape, Box):
        return trimesh.creation.box(extents=2 * np.asarray(shape.half, float))
    if isinstance(shape, Cylinder):
        return trimesh.creation.cylinder(radius=shape.radius, height=2 * shape.half_length,
                                         sections=TRUTH_SECTIONS)
    if isinstance(shape, Sphere):
        return trimesh.creation.uv_sphere(radius=shape.radius,
                                          count=[TRUTH_SECTIONS // 2, TRUTH_SECTIONS])
    raise TypeError(f"no surface for a {type(shape).__name__}")


@dataclass(eq=False)
class ObjectTruth:
    """One mounted object's true surface, for scoring a scan or a model against it: the mesh
    in the object's own frame (mm), the pose that puts it in the turntable frame
    (p_table = R p_object + center, before the table turns), the material of every face, and
    what fills it and how high."""

    name: str
    material: str
    mesh: trimesh.Trimesh
    center: np.ndarray
    R: np.ndarray
    face_material: np.ndarray  # one material name per face
    fill: str | None = None
    fill_level: float = np.inf  # mm, height in the object's frame the fill reaches

    def to_object(self, points_table: np.ndarray) -> np.ndarray:
        """Turntable-frame points (N x 3, mm, table at angle 0) in the object's frame."""
        return (np.asarray(points_table, float).reshape(-1, 3) - self.center) @ self.R

    def signed_distance(self, points_table: np.ndarray) -> np.ndarray:
        """Signed distance (mm) of turntable-frame points to the surface: positive inside."""
        return np.asarray(trimesh.proximity.signed_distance(
            self.mesh, self.to_object(points_table)), float)

    def material_at(self, points_table: np.ndarray) -> list[str]:
        """The material of the surface nearest each turntable-frame point."""
        _, _, face = trimesh.proximity.closest_point(self.mesh, self.to_object(points_table))
        return [str(self.face_material[f]) for f in face]


def object_truth(obj: SceneObject) -> ObjectTruth:
    """The truth of one scene object (its surface, pose, materials per face, fill)."""
    mesh = surface_mesh(obj.shape)
    if isinstance(obj.shape, Mesh):
        face_mat = np.array([obj.material_of(r) for r in obj.shape.face_region], dtype=object)
    else:
        face_mat = np.full(len(mesh.faces), obj.material, dtype=object)
    return ObjectTruth(obj.name, obj.material, mesh, np.asarray(obj.shape.center, float),
                       np.asarray(obj.shape.R, float), face_mat, obj.fill, obj.fill_level)


# ---------------------------------------------------------------- users' mesh files
MESH_FORMATS = ("stl", "obj", "ply", "off")
MAX_FACES = 2_000_000         # faces a user's mesh may have
MAX_FILE_BYTES = 200 * 2**20  # bytes a user's mesh file may have (memory and load time)


class MeshFileError(ValueError):
    """A user's mesh file the emulator cannot mount; the message says what to fix."""


def _count_faces(data: bytes, kind: str) -> int | None:
    """Faces the file declares, read before parsing it (None when the format hides it)."""
    if kind == "stl" and not data[:5].lower().startswith(b"solid") and len(data) >= 84:
        return int.from_bytes(data[80:84], "little")
    if kind == "stl":
        return data.count(b"facet normal") or data.count(b"endfacet")
    if kind == "ply":
        head = data[:4096].split(b"end_header")[0]
        for line in head.splitlines():
            parts = line.split()
            if parts[:2] == [b"element", b"face"] and len(parts) == 3 and parts[2].isdigit():
                return int(parts[2])
        return None
    if kind == "obj":
        return data.count(b"\nf ") + data.startswith(b"f ")
    if kind == "off":
        lines = [x for x in data[:4096].splitlines() if x.strip() and not x.startswith(b"#")]
        if len(lines) > 1 and lines[0].strip().upper().endswith(b"OFF"):
            parts = lines[1].split()
            return int(parts[1]) if len(parts) > 1 and parts[1].isdigit() else None
    return None


def load_mesh_file(path: str | os.PathLike, max_faces: int = MAX_FACES,
                   limit_mm: tuple[float, float, float] = (270.0, 270.0, 430.0)
                   ) -> trimesh.Trimesh:
    """A user's closed mesh (STL, OBJ, PLY or OFF; units mm), checked: a regular file of at
    most MAX_FILE_BYTES, at most `max_faces` faces (counted before it is parsed where the
    format declares them), one closed (watertight) surface, within `limit_mm` (width, depth,
    height). The file's bytes are parsed from memory, so nothing it names (an OBJ's material
    library, textures) is opened. Raises MeshFileError with one line saying what to fix."""
    p = os.fspath(path)
    kind = os.path.splitext(p)[1].lower().lstrip(".")
    if kind not in MESH_FORMATS:
        raise MeshFileError(f"{p}: not a mesh file this emulator reads (use "
                            f"{', '.join('.' + k for k in MESH_FORMATS)})")
    if not os.path.isfile(p):
        raise MeshFileError(f"{p}: no such file")
    if os.path.getsize(p) > MAX_FILE_BYTES:
        raise MeshFileError(f"{p}: {os.path.getsize(p) / 2**20:.0f} MiB; meshes of at most "
                            f"{MAX_FILE_BYTES // 2**20} MiB are mounted (simplify it)")
    with open(p, "rb") as fh:
        data = fh.read()
    declared = _count_faces(data, kind)
    if declared is not None and declared > max_faces:
        raise MeshFileError(f"{p}: {declared} faces; at most {max_faces} are mounted "
                            "(decimate it)")
    try:
        mesh = trimesh.load(io.BytesIO(data), file_type=kind, force="mesh", process=True)
    except Exception as e:  # noqa: BLE001 - any parser failure is the file's fault
        raise MeshFileError(f"{p}: not a readable {kind.upper()} mesh "
                            f"({type(e).__name__}: {str(e)[:80]})") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise MeshFileError(f"{p}: holds no triangles (is it really a {kind.upper()} file?)")
    if len(mesh.faces) > max_faces:
        raise MeshFileError(f"{p}: {len(mesh.faces)} faces; at most {max_faces} are mounted "
                            "(decimate it)")
    if not np.isfinite(mesh.vertices).all():
        raise MeshFileError(f"{p}: has vertices that are not finite numbers")
    if not mesh.is_watertight:
        raise MeshFileError(f"{p}: not closed (watertight): fill its holes so it bounds a "
                            "solid")
    if mesh.volume < 0:
        mesh.invert()  # faces wound inward: the normals must point out
    ext = mesh.extents
    if any(e > lim for e, lim in zip(ext, limit_mm)):
        raise MeshFileError(f"{p}: {ext[0]:.1f} x {ext[1]:.1f} x {ext[2]:.1f} mm does not fit "
                            f"the scanner's {limit_mm[0]:g} x {limit_mm[1]:g} x "
                            f"{limit_mm[2]:g} mm (units must be mm; scale it)")
    return mesh


def standing(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """A copy moved so its footprint is centred on the table's axis and its bottom at z = 0."""
    m = mesh.copy()
    lo, hi = m.bounds
    m.apply_translation([-(lo[0] + hi[0]) / 2, -(lo[1] + hi[1]) / 2, -lo[2]])
    return m


MAX_REGION_MAP_BYTES = 64 * 2**20  # a region map's JSON (face lists of a 2M-face mesh fit)


def load_region_map(path: str | os.PathLike, n_faces: int, known: set[str]
                    ) -> tuple[np.ndarray, dict[int, str]]:
    """A region map: a JSON object {material: [face index, ...], ...} (faces numbered from 0
    in the mesh file's order); faces not listed keep the object's material. Returns the face
    regions (1, 2, ... in the order given; 0 elsewhere) and region -> material. Raises
    MeshFileError with one line saying what to fix."""
    import json

    p = os.fspath(path)
    if not os.path.isfile(p):
        raise MeshFileError(f"{p}: no such region map")
    if os.path.getsize(p) > MAX_REGION_MAP_BYTES:
        raise MeshFileError(f"{p}: a region map of at most {MAX_REGION_MAP_BYTES // 2**20} MiB "
                            "is read")
    try:
        with open(p, "rb") as fh:
            doc = json.loads(fh.read())
    except (ValueError, UnicodeDecodeError) as e:
        raise MeshFileError(f"{p}: not JSON ({str(e)[:60]})") from None
    if not isinstance(doc, dict) or not doc:
        raise MeshFileError(f'{p}: a region map is a JSON object such as {{"paper": [0, 1, 2]}}')
    face_region = np.zeros(n_faces, int)
    regions: dict[int, str] = {}
    for k, (material, faces) in enumerate(doc.items(), start=1):
        if material not in known:
            raise MeshFileError(f"{p}: {material!r} is not a material of the emulator; use "
                                f"one of {', '.join(sorted(known))}")
        if not isinstance(faces, list) or not all(
                isinstance(f, int) and not isinstance(f, bool) for f in faces):
            raise MeshFileError(f"{p}: {material!r} must list face numbers (integers)")
        idx = np.asarray(faces, int)
        if len(idx) and (idx.min() < 0 or idx.max() >= n_faces):
            raise MeshFileError(f"{p}: {material!r} names faces outside 0..{n_faces - 1}")
        face_region[idx] = k
        regions[k] = material
    return face_region, regions


def user_object(path: str | os.PathLike, material: str, yaw_deg: float = 0.0,
                tilt_deg: float = 0.0, region_map: str | os.PathLike | None = None,
                limit_mm: tuple[float, float, float] = (270.0, 270.0, 430.0),
                interior: bool = False, fill: str | None = None,
                offset_mm: tuple[float, float] = (0.0, 0.0)) -> SceneObject:
    """A user's mesh file (load_mesh_file) as a SceneObject standing on the table's centre:
    turned by yaw about the table's normal after tilting it by tilt about the table's x axis
    (deg), its lowest point on the table; a region map (load_region_map) gives parts other
    materials; `interior` casts on to the surfaces inside it (a hollow object's inner wall),
    `fill` fills its cavities (a material, e.g. water); `offset_mm` (x, y) places its centre
    off the table's axis. Raises MeshFileError with one line saying what to fix."""
    from .scene import rodrigues
    from .signals import MATERIALS

    known = {m for m in MATERIALS if m != "water"}  # water only fills containers
    if material not in known:
        raise MeshFileError(f"material {material!r} is not one of the emulator's; use one of "
                            f"{', '.join(sorted(known))}")
    if not (np.isfinite(yaw_deg) and np.isfinite(tilt_deg) and abs(tilt_deg) <= 180):
        raise MeshFileError("yaw and tilt are angles in degrees (tilt within -180..180)")
    if fill is not None and fill not in MATERIALS:
        raise MeshFileError(f"fill {fill!r} is not a material of the emulator; use one of "
                            f"{', '.join(sorted(MATERIALS))}")
    mesh = standing(load_mesh_file(path, limit_mm=limit_mm))
    face_region, regions = (None, {}) if region_map is None else load_region_map(
        region_map, len(mesh.faces), known)
    R = rodrigues(np.array([0, 0, 1.0]), np.radians(yaw_deg)) @ rodrigues(
        np.array([1.0, 0, 0]), np.radians(tilt_deg))
    centroid = mesh.bounds.mean(axis=0)
    turned = (mesh.vertices - centroid) @ R.T
    ext = np.ptp(turned, axis=0)
    if any(e > lim for e, lim in zip(ext, limit_mm)):
        raise MeshFileError(f"{os.fspath(path)}: tilted by {tilt_deg:g} deg it is "
                            f"{ext[0]:.1f} x {ext[1]:.1f} x {ext[2]:.1f} mm, more than the "
                            f"scanner's {limit_mm[0]:g} x {limit_mm[1]:g} x {limit_mm[2]:g} mm")
    # p_table = R (p - centroid) + center: centred on the axis, lowest point at z = 0
    lo, hi = turned.min(axis=0), turned.max(axis=0)
    center = -np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])
    off = np.asarray(offset_mm, float)
    if not (off.shape == (2,) and np.isfinite(off).all()):
        raise MeshFileError("the offset is two numbers in mm (x, y from the table's axis)")
    reach = np.abs(off) + ext[:2] / 2  # the footprint's farthest extent from the axis
    if any(r > lim / 2 for r, lim in zip(reach, limit_mm[:2])):
        raise MeshFileError(f"{os.fspath(path)} placed {off[0]:g}, {off[1]:g} mm off the axis "
                            f"reaches {reach[0]:.1f}, {reach[1]:.1f} mm from it, beyond the "
                            f"scanner's ±{limit_mm[0] / 2:g} x ±{limit_mm[1] / 2:g} mm: place "
                            f"it nearer the axis")
    center[:2] += off
    mesh = mesh.copy()
    mesh.apply_translation(-centroid)
    shape = Mesh(center=center, R=R, mesh=mesh, face_region=face_region,
                 region_names=("object", *(regions[k] for k in sorted(regions))),
                 interior=interior or fill is not None)
    return SceneObject(os.path.basename(os.fspath(path)), material, shape, regions=regions,
                       fill=fill)
