"""A 3D model in the files users' tools open: PLY with sigma, support and material per vertex;
glTF binary (GLB) and OBJ through trimesh, coloured by material. Each written atomically."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from ..files import atomic_output
from .store import ObjectModel

GREY = (150, 150, 150)  # unsupported or unknown-material vertices
PALETTE = ((31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189),
           (140, 86, 75), (227, 119, 194), (188, 189, 34), (23, 190, 207))
FORMATS = ("ply", "glb", "obj")


def vertex_colors(model: ObjectModel) -> np.ndarray:
    """RGBA (V, 4) uint8 per vertex: the material's colour (classes in order), grey where
    the vertex is unsupported or has no material."""
    out = np.tile(np.array([*GREY, 255], np.uint8), (len(model.vertices_mm), 1))
    if model.classes and len(model.material_prob):
        prob = np.nan_to_num(model.material_prob, nan=-1.0)
        best = prob.argmax(axis=1)
        known = model.supported & np.isfinite(model.material_prob).all(axis=1)
        for k in range(len(model.classes)):
            out[known & (best == k), :3] = PALETTE[k % len(PALETTE)]
    return out


def ply_bytes(model: ObjectModel) -> bytes:
    """Binary little-endian PLY: vertices (x, y, z mm, normal, sigma_mm (NaN: unsupported),
    support, supported, material index (-1: none), colour) and triangles; the material
    names in comments, in class order."""
    V = len(model.vertices_mm)
    best = np.full(V, -1, np.int16)
    if model.classes and len(model.material_prob):
        ok = np.isfinite(model.material_prob).all(axis=1)
        best[ok] = np.nan_to_num(model.material_prob[ok]).argmax(axis=1)
    rgba = vertex_colors(model)
    vert = np.empty(V, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("nx", "<f4"),
                              ("ny", "<f4"), ("nz", "<f4"), ("sigma_mm", "<f4"),
                              ("support", "<i4"), ("supported", "u1"), ("material", "<i2"),
                              ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    for k, name in enumerate(("x", "y", "z")):
        vert[name] = model.vertices_mm[:, k]
        vert["n" + name] = model.normals[:, k]
    vert["sigma_mm"] = model.sigma_mm
    vert["support"] = model.support
    vert["supported"] = model.supported
    vert["material"] = best
    vert["red"], vert["green"], vert["blue"] = rgba[:, 0], rgba[:, 1], rgba[:, 2]
    face = np.empty(len(model.faces), dtype=[("n", "u1"), ("v", "<i4", (3,))])
    face["n"] = 3
    face["v"] = model.faces
    names = "".join(f"comment material {k} {_plain(c)}\n" for k, c in enumerate(model.classes))
    props = "".join(f"property {t} {n}\n" for n, t in (
        ("x", "float"), ("y", "float"), ("z", "float"), ("nx", "float"), ("ny", "float"),
        ("nz", "float"), ("sigma_mm", "float"), ("support", "int"), ("supported", "uchar"),
        ("material", "short"), ("red", "uchar"), ("green", "uchar"), ("blue", "uchar")))
    header = ("ply\nformat binary_little_endian 1.0\n"
              f"comment dmdsm model of {_plain(model.object_id)} version {model.version}, mm\n"
              f"{names}element vertex {V}\n{props}element face {len(model.faces)}\n"
              "property list uchar int vertex_indices\nend_header\n")
    return header.encode() + vert.tobytes() + face.tobytes()


def _plain(text: str) -> str:
    """Text for a PLY header line: printable ASCII, no line breaks."""
    return "".join(c if 32 <= ord(c) < 127 else "?" for c in str(text))


def to_trimesh(model: ObjectModel) -> trimesh.Trimesh:
    """The model's surface as a trimesh (mm) coloured by material."""
    return trimesh.Trimesh(vertices=model.vertices_mm, faces=model.faces,
                           vertex_normals=model.normals, vertex_colors=vertex_colors(model),
                           process=False)


def export_model(model: ObjectModel, path: Path, fmt: str | None = None, force: bool = True,
                 flag: str = "-o") -> str:
    """Write the model to path as ply, glb or obj (from the suffix unless fmt is given);
    returns the format. Atomic: an earlier file stays whole on any failure."""
    fmt = (fmt or Path(path).suffix.lstrip(".")).lower()
    if fmt not in FORMATS:
        raise ValueError(f"{path}: unknown model format {fmt!r}; use .ply, .glb or .obj")
    if fmt == "ply":
        data = ply_bytes(model)
    else:
        data = to_trimesh(model).export(file_type=fmt)
        data = data.encode() if isinstance(data, str) else data
    with atomic_output(Path(path), force=force, flag=flag) as tmp:
        Path(tmp).write_bytes(data)
    return fmt
