"""Scene geometry: turntable pose (n, X_R), beam X = S + d v (eq. 1), shapes and the ray cast.

All lengths in mm, angles in degrees at the interface. Objects are defined in the turntable
frame (origin at the table centre X_R, z along the normal n) and turn with the table angle
theta about n (eq. 5). The beam is a finite spot sampled by a fixed pattern of parallel rays,
so a thin filament returns a response whose strength grows with the overlap (paper Fig. 2).
"""

from __future__ import annotations

import hashlib
import math
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from statistics import NormalDist

import numpy as np

#: Table I of the paper: beam direction, turntable normal, turntable centre (mm)
TABLE_I_V = np.array([0.0656, 0.9955, -0.0678])
TABLE_I_N = np.array([-0.0007, 0.0022, 0.9999])
TABLE_I_XR = np.array([235.21, 288.17, 0.00])


def unit(x: np.ndarray) -> np.ndarray:
    """x / |x|."""
    x = np.asarray(x, dtype=float)
    return x / np.linalg.norm(x)


def skew(n: np.ndarray) -> np.ndarray:
    """[n]x, the cross-product matrix."""
    return np.array([[0, -n[2], n[1]], [n[2], 0, -n[0]], [-n[1], n[0], 0]])


def rodrigues(n: np.ndarray, theta_rad: float) -> np.ndarray:
    """R_n(theta) = I + sin(theta)[n]x + (1 - cos(theta))[n]x^2 (paper eq. 5)."""
    k = skew(unit(n))
    return np.eye(3) + np.sin(theta_rad) * k + (1 - np.cos(theta_rad)) * (k @ k)


def table_frame(n: np.ndarray) -> np.ndarray:
    """3x3 rotation whose columns are the turntable frame's x, y, z (z = n) in {0}."""
    z = unit(n)
    x = unit(np.cross([0.0, 1.0, 0.0], z))  # table x roughly along world x
    return np.column_stack([x, np.cross(z, x), z])


# ---------------------------------------------------------------- shapes (local frames)
@dataclass
class Shape(ABC):
    """A solid in its own frame: `center` and rotation `R` place it in the turntable frame."""

    center: np.ndarray
    R: np.ndarray = field(default_factory=lambda: np.eye(3))

    @abstractmethod
    def local_hit(self, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Entry distance (inf for a miss) and outward normal per ray, in the local frame."""


@dataclass
class Box(Shape):
    """Axis-aligned box in its frame, half sizes `half` (mm)."""

    half: np.ndarray = field(default_factory=lambda: np.ones(3))

    def local_hit(self, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / d
            t1 = (-self.half - o) * inv
            t2 = (self.half - o) * inv
        tmin = np.nan_to_num(np.minimum(t1, t2), nan=-np.inf)
        tmax = np.nan_to_num(np.maximum(t1, t2), nan=np.inf)
        t_enter = tmin.max(axis=1)
        t_exit = tmax.min(axis=1)
        hit = (t_enter <= t_exit) & (t_enter > 0)
        axis = tmin.argmax(axis=1)
        normal = np.zeros_like(o)
        normal[np.arange(len(o)), axis] = -np.sign(d[np.arange(len(o)), axis])
        return np.where(hit, t_enter, np.inf), normal


@dataclass
class Cylinder(Shape):
    """Capped cylinder along its local z: radius and half length (mm)."""

    radius: float = 1.0
    half_length: float = 1.0

    def local_hit(self, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        a = d[:, 0] ** 2 + d[:, 1] ** 2
        b = 2 * (o[:, 0] * d[:, 0] + o[:, 1] * d[:, 1])
        c = o[:, 0] ** 2 + o[:, 1] ** 2 - self.radius ** 2
        disc = b * b - 4 * a * c
        with np.errstate(divide="ignore", invalid="ignore"):
            t_side = (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a)
        z_side = o[:, 2] + t_side * d[:, 2]
        side_ok = (disc >= 0) & (a > 1e-15) & (t_side > 0) & (np.abs(z_side) <= self.half_length)
        t_side = np.where(side_ok, t_side, np.inf)
        with np.errstate(divide="ignore", invalid="ignore"):
            t_cap = (-np.sign(d[:, 2]) * self.half_length - o[:, 2]) / d[:, 2]
        p = o + t_cap[:, None] * d
        cap_ok = (t_cap > 0) & (p[:, 0] ** 2 + p[:, 1] ** 2 <= self.radius ** 2)
        t_cap = np.where(cap_ok, t_cap, np.inf)
        t = np.minimum(t_side, t_cap)
        p = o + np.where(np.isfinite(t), t, 0)[:, None] * d
        normal = np.column_stack([p[:, 0], p[:, 1], np.zeros(len(o))])
        normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
        cap_n = np.column_stack([np.zeros(len(o)), np.zeros(len(o)), -np.sign(d[:, 2])])
        normal = np.where((t_cap <= t_side)[:, None], cap_n, normal)
        return t, normal


@dataclass
class Sphere(Shape):
    """Sphere of `radius` (mm) about its centre."""

    radius: float = 1.0

    def local_hit(self, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        b = np.einsum("ij,ij->i", o, d)
        c = np.einsum("ij,ij->i", o, o) - self.radius ** 2
        disc = b * b - c
        t = -b - np.sqrt(np.maximum(disc, 0))
        ok = (disc >= 0) & (t > 0)
        t = np.where(ok, t, np.inf)
        p = o + np.where(ok, t, 0)[:, None] * d
        return t, p / self.radius


@dataclass
class SceneObject:
    """A shape standing on the turntable; `name` identifies it. `material` is its surface's;
    a mesh's regions may have others (`regions`: region number -> material, e.g. a paper
    label on a glass jar), and `fill` is what fills its cavities (a liquid; None: air) up to
    `fill_level` (mm, height in the shape's own frame; above it, air)."""

    name: str
    material: str
    shape: Shape
    regions: dict[int, str] = field(default_factory=dict)
    fill: str | None = None
    fill_level: float = math.inf

    def material_of(self, region: int) -> str:
        """The material of a region of the shape's faces (the object's own where unnamed)."""
        return self.regions.get(int(region), self.material)


@dataclass
class Hit:
    """What one laser shot sees, nearest return first: mean distance of its rays (mm), their
    share of the spot 0..1, cos of the incidence angle, the material hit (or None); deeper
    returns of the same object in `later`."""

    d: float
    overlap: float
    cos_incidence: float
    material: str | None
    obj: str | None
    local: np.ndarray | None = None  # mean hit point in the object's own frame (mm)
    later: list[Hit] = field(default_factory=list)  # returns from deeper in the spot
    # an interface inside the object (a wall's inner side, a liquid): the media the sound
    # crossed inside it to get there, (material, mm) each; () for a surface facing the air
    path: tuple[tuple[str, float], ...] = ()


RETURN_MM = 0.3  # depth spread within the spot that still arrives as one pulse (mm)
SPOT = np.array([[0.0, 0.0]] + [[np.cos(a), np.sin(a)] for a in np.arange(6) * np.pi / 3]
                + [[2 * np.cos(a), 2 * np.sin(a)] for a in (np.arange(12) + 0.5) * np.pi / 6]) / 2


@dataclass
class Scene:
    """Turntable pose, beam direction and the objects on the table."""

    v: np.ndarray = field(default_factory=lambda: TABLE_I_V.copy())
    n: np.ndarray = field(default_factory=lambda: TABLE_I_N.copy())
    X_R: np.ndarray = field(default_factory=lambda: TABLE_I_XR.copy())
    objects: list[SceneObject] = field(default_factory=list)
    spot_radius: float = 0.25  # mm, laser spot radius at the target

    def _frames(self, theta_deg: float) -> tuple[np.ndarray, np.ndarray, list]:
        """What a cast needs that depends only on the table angle (cached for the last
        angle: a fly line casts a thousand times a second at one angle): the beam, the spot's
        ray offsets (mm) and each object's local->world rotation, centre and local beam."""
        key = (float(theta_deg), id(self.objects), len(self.objects),
               tuple(self.v), tuple(self.n), tuple(self.X_R))
        cached = getattr(self, "_frame_cache", None)
        if cached is not None and cached[0] == key:
            return cached[1]
        v = unit(self.v)
        basis = table_frame(self.n)
        rot = rodrigues(self.n, np.radians(theta_deg)) @ basis  # table frame after turning
        e1 = unit(np.cross(v, [0.0, 0.0, 1.0]) if abs(v[2]) < 0.9 else np.cross(v, [1, 0, 0]))
        e2 = np.cross(v, e1)
        spot = self.spot_radius * (SPOT[:, :1] * e1 + SPOT[:, 1:] * e2)
        frames = []
        for obj in self.objects:
            to_local = rot @ obj.shape.R  # local -> world rotation
            center = self.X_R + rot @ obj.shape.center
            frames.append((to_local, center, np.tile(v @ to_local, (len(SPOT), 1))))
        self._frame_cache = (key, (v, spot, frames))
        return v, spot, frames

    def cast(self, S: np.ndarray, theta_deg: float, max_d: float = 200.0) -> Hit:
        """Ray-cast the beam from sensor position S (mm) with the table at theta (deg)."""
        return self.cast_many(np.asarray(S, float)[None], theta_deg, max_d)[0]

    def cast_many(self, S: np.ndarray, theta_deg: float, max_d: float = 200.0) -> list[Hit]:
        """cast() from each of K sensor positions (K x 3, mm) at one table angle, in one
        numpy pass over all K x 19 rays: a fly line casts a thousand times a second."""
        v, spot, frames = self._frames(theta_deg)
        S = np.asarray(S, float).reshape(-1, 3)
        K, m = len(S), len(spot)
        origins = (S[:, None, :] + spot[None]).reshape(-1, 3)
        best = np.full(len(origins), np.inf)
        normals = np.zeros((len(origins), 3))
        owner = np.full(len(origins), -1)
        local = np.zeros((len(origins), 3))
        face = None  # per ray: the mesh face hit (-1: none or a primitive), meshes only
        rays = {}  # interior meshes: object index -> its local ray origins and directions
        for k, (obj, (to_local, center, d)) in enumerate(zip(self.objects, frames)):
            d = np.tile(d, (K, 1)) if K > 1 else d
            o = (origins - center) @ to_local
            by_face = getattr(obj.shape, "local_hit_faces", None)
            if by_face is None:
                t, nl = obj.shape.local_hit(o, d)
            else:
                t, nl, f = by_face(o, d)
            closer = t < best
            best = np.where(closer, t, best)
            normals = np.where(closer[:, None], nl @ to_local.T, normals)
            owner = np.where(closer, k, owner)
            local = np.where(closer[:, None], o + np.where(np.isfinite(t), t, 0)[:, None] * d,
                             local)
            if by_face is not None or face is not None:
                face = np.full(len(origins), -1) if face is None else face
                face = np.where(closer, f if by_face is not None else -1, face)
                if getattr(obj.shape, "interior", False):
                    rays[k] = (o, d)
        deeper = self._interiors(rays, best, owner, face) if rays else None
        return [self._returns(best[i * m:(i + 1) * m], normals[i * m:(i + 1) * m],
                              owner[i * m:(i + 1) * m], local[i * m:(i + 1) * m], v, max_d,
                              None if face is None else face[i * m:(i + 1) * m],
                              None if deeper is None else
                              tuple(x[i * m:(i + 1) * m] for x in deeper))
                for i in range(K)]

    def _interiors(self, rays: dict, best: np.ndarray, owner: np.ndarray, face: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The surfaces behind each ray's first hit on an interior mesh: distances (mm), faces
        and the cosine between the beam and the face's outward normal (negative where the
        ray passes into the solid) per ray and layer (inf, -1, 0 where none), and the height
        (mm, object frame) of the first hit and of each layer's."""
        n_layers = max(self.objects[k].shape.MAX_LAYERS for k in rays)
        lt = np.full((len(best), n_layers), np.inf)
        lf = np.full((len(best), n_layers), -1)
        lc = np.zeros((len(best), n_layers))
        lz = np.zeros((len(best), n_layers + 1))
        for k, (o, d) in rays.items():
            mine = (owner == k) & np.isfinite(best)
            if not mine.any():
                continue
            shape = self.objects[k].shape
            t, f = shape.layers(o[mine], d[mine], best[mine], face[mine], n_layers)
            lt[mine], lf[mine] = t, f
            lc[mine] = np.einsum("ijk,ik->ij", shape.face_normals(f), d[mine])
            ts = np.column_stack([best[mine], np.where(np.isfinite(t), t, 0)])
            lz[mine] = o[mine, 2:3] + ts * d[mine, 2:3]  # heights in the object's frame
        return lt, lf, lc, lz

    def _returns(self, best: np.ndarray, normals: np.ndarray, owner: np.ndarray,
                 local: np.ndarray, v: np.ndarray, max_d: float,
                 face: np.ndarray | None = None, deeper: tuple | None = None) -> Hit:
        """One shot's Hit from its rays' distances (mm), normals, objects and local points
        (and, on meshes, the faces hit and the surfaces behind them)."""
        hit = np.isfinite(best) & (best < max_d)
        if not hit.any():
            return Hit(np.inf, 0.0, 0.0, None, None)
        k = np.bincount(owner[hit]).argmax()
        sel = hit & (owner == k)
        obj = self.objects[k]
        # rays whose distances lie within RETURN_MM of each other make one return at their
        # mean distance; a spot spread over depth (a tip seen with its grazing side, a face
        # and the one behind it) makes separate returns, nearest first
        near = best[sel].min()
        if best[sel].max() - near < RETURN_MM:  # the common case: one return
            groups = [sel]
        else:
            rank = np.floor((best - near) / RETURN_MM)
            groups = [sel & (rank == b) for b in np.unique(rank[sel])]
        returns = []
        for r in groups:
            cos_i = float(np.clip(np.mean(np.abs(normals[r] @ v)), 0, 1))
            material = obj.material if face is None else self._material(obj, face[r])
            returns.append(Hit(float(best[r].mean()), float(r.mean()), cos_i,
                               material, obj.name, local[r].mean(axis=0)))
        if deeper is not None:
            returns += self._inside(obj, sel, best, face, deeper, max_d)
        returns[0].later = returns[1:]
        return returns[0]

    @staticmethod
    def _material(obj: SceneObject, faces: np.ndarray) -> str:
        """The material most of these rays' faces have (their regions' materials)."""
        regions = getattr(obj.shape, "regions", None)
        if regions is None or not obj.regions:
            return obj.material
        r = regions(faces)
        r = r[r >= 0]
        return obj.material_of(np.bincount(r).argmax()) if len(r) else obj.material

    def _inside(self, obj: SceneObject, sel: np.ndarray, best: np.ndarray, face: np.ndarray,
                deeper: tuple, max_d: float) -> list[Hit]:
        """One return per surface behind the first along the rays of `sel` (a wall's inner
        side, the far wall, a liquid), with the media the sound crossed inside the object:
        past a face it entered, the face's region's material; past one it left, the fill
        (below the fill level; air above it)."""
        lt, lf, lc, lz = deeper
        out: list[Hit] = []
        prev_t, prev_f = best, face
        entered = np.ones(len(best), bool)  # the first surface is entered from the air
        path: list[tuple[str, float]] = []
        for j in range(lt.shape[1]):
            r = sel & np.isfinite(lt[:, j]) & (lt[:, j] < max_d)
            if not r.any():
                break
            inside = np.mean(entered[r]) >= 0.5
            wet = np.mean(lz[r, j]) < obj.fill_level  # where the ray left the solid
            medium = self._material(obj, prev_f[r]) if inside else (obj.fill if wet else None)
            if medium is not None:
                path = path + [(medium, float(np.mean(lt[r, j] - prev_t[r])))]
            out.append(Hit(float(lt[r, j].mean()), float(r.mean()),
                           float(np.clip(np.abs(lc[r, j]).mean(), 0, 1)),
                           self._material(obj, lf[r, j]), obj.name, None, path=tuple(path)))
            prev_t, prev_f, entered = lt[:, j], lf[:, j], lc[:, j] < 0
        return out


_STANDARD_NORMAL = NormalDist()


def keyed_uniforms(key: bytes, size: int) -> list[float]:
    """`size` (at most 8) uniforms in (0, 1) fixed by a key: its blake2b digest read as 64-bit
    integers. Seeding a numpy Generator per key costs 40 us; this costs 2, and the emulator
    draws several per laser shot."""
    d = hashlib.blake2b(key, digest_size=8 * size).digest()
    return [(int.from_bytes(d[8 * i:8 * i + 8], "little") + 0.5) * 2.0 ** -64
            for i in range(size)]


def keyed_normal(key: bytes, sigma: float) -> float:
    """One N(0, sigma) value fixed by a key."""
    return sigma * _STANDARD_NORMAL.inv_cdf(keyed_uniforms(key, 1)[0])


def keyed_laplace(key: bytes, scale: float) -> float:
    """One Laplace(0, scale) value fixed by a key (inverse CDF)."""
    u = keyed_uniforms(key, 1)[0]
    return scale * (math.log(2 * u) if u < 0.5 else -math.log(2 - 2 * u))


def hash_noise(key: str, sigma: float, size: int, seed: int) -> np.ndarray:
    """A fixed pseudo-random offset (`size` at most 8) for a key: repeatable per position, not
    per read."""
    if sigma == 0:
        return np.zeros(size)
    u = keyed_uniforms(f"{seed}:{key}".encode(), size)
    return sigma * np.array([_STANDARD_NORMAL.inv_cdf(x) for x in u])
