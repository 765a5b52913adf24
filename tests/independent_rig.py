"""An independent generator of calibration-rig raw points (issue 30, item 3): the rig CSV that
`dmdsm calibrate --from-data` reads, made WITHOUT the emulator's physics (hil_sim) or the
host's forward model, so the calibration's reported stds can be checked on data they were
not tuned to.

Its own model, in the sensor frame {0} (mm, deg):

- the beam leaves the *actual* stage position along v; the file holds the commanded one
  (stage repeatability `stage_mm`, Gaussian per raw point and axis);
- the laser spot is a circular Gaussian (1/e^2 radius `spot_w_mm`), sampled by a fixed set of
  rays: the amplitude is the spot's share on the target times cos(incidence) (a cylinder's
  side; the tip's flat end face is met head on), the depth the amplitude-weighted mean
  distance of the rays that hit (plus noise);
- the tip is the flat end of a cylinder of radius `radius_mm`, its axis a few degrees off
  -v (a hand-mounted holder); the edge is a cylinder of that radius along a direction a
  little off n, standing off the table's centre and turned about (n, X_R) with the table;
- noise: per raw point depth noise `depth_mm` (Student-t with 5 degrees of freedom scaled
  to that std: rough surfaces are heavy-tailed), a common depth error per frame (tips: the
  ranging's offset at that distance) or per sweep (edges: the surface patch) `common_mm`,
  relative amplitude noise `amp_rel` and additive amplitude noise `amp_add` (a weak or
  empty reading can be negative), the table's actual angle off its reading by `table_deg`
  (per frame); no echo (d empty) where the amplitude is below `detect`;
- the rasters are centred on the target by a user jogging by eye: at a random phase within
  one step plus `aim_mm`.

`python tests/independent_rig.py --out rig.csv --seed 3` writes one set and prints its truth.
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

PAPER = {"v": (0.0656, 0.9955, -0.0678), "n": (-0.0007, 0.0022, 0.9999),
         "X_R": (235.21, 288.17, 0.0)}  # Table I of the paper
COLUMNS = ("step", "frame", "line", "theta_deg", "sx_mm", "sy_mm", "sz_mm", "d_mm",
           "amplitude", "modality")


def _unit(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, float)
    return x / np.linalg.norm(x)


def _perp_basis(u: np.ndarray) -> np.ndarray:
    """3 x 2 orthonormal basis across u (own construction: Gram-Schmidt on the least
    aligned axis)."""
    e = np.eye(3)[int(np.argmin(np.abs(u)))]
    a = _unit(e - (e @ u) * u)
    return np.column_stack([a, np.cross(u, a)])


def _turn(axis: np.ndarray, deg: float) -> np.ndarray:
    """Rotation matrix about a unit axis by deg (the matrix exponential of the cross
    matrix, here via scipy for independence from the host's Rodrigues code)."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(np.radians(deg) * _unit(axis)).as_matrix()


@dataclass
class Noise:
    """Noise levels (mm, deg, relative)."""

    stage_mm: float = 0.005
    depth_mm: float = 0.02
    common_mm: float = 0.01
    amp_rel: float = 0.05
    amp_add: float = 0.01     # in units of the full-on amplitude
    table_deg: float = 0.01
    detect: float = 0.03      # no echo below this amplitude (full-on = 1)


NOISE_LEVELS = {  # from nearly none to large
    "none": Noise(1e-5, 1e-5, 0.0, 1e-4, 1e-4, 1e-5),
    "low": Noise(0.002, 0.005, 0.002, 0.02, 0.005, 0.003),
    "paper": Noise(0.005, 0.02, 0.01, 0.05, 0.01, 0.01),
    "large": Noise(0.02, 0.06, 0.03, 0.15, 0.03, 0.05),
}


@dataclass
class Raster:
    """The procedure's rasters (mm, deg)."""

    tip_depths: tuple[float, ...] = (0.0, 3.0, 6.0, 9.0)  # Y steps back from the first
    tip_half: float = 0.4
    tip_step: float = 0.1
    edge_levels: tuple[float, ...] = (10.0, 15.0, 20.0, 25.0, 30.0, 35.0, 40.0)
    edge_half: float = 0.6
    edge_step: float = 0.1
    angles: tuple[float, ...] = (0.0, 180.0)


RASTERS = {
    "default": Raster(),
    "coarse": Raster((0.0, 4.0, 8.0), 0.45, 0.15, (10.0, 20.0, 30.0, 40.0, 50.0), 0.75, 0.15,
                     (0.0, 120.0, 240.0)),
    "fine": Raster((0.0, 2.0, 4.0, 6.0, 8.0), 0.3, 0.05, (12.0, 22.0, 32.0, 42.0), 0.5, 0.05,
                   (0.0, 90.0, 180.0, 270.0)),
}


@dataclass
class Rig:
    """The filament and the spot (mm)."""

    radius_mm: float = 0.25
    spot_w_mm: float = 0.25        # 1/e^2 radius of the Gaussian spot
    tip_tilt_deg: float = 3.0      # the tip's axis off -v, at most
    edge_tilt_deg: float = 0.5     # the vertical filament off n, at most
    edge_offset_mm: tuple[float, float] = (25.0, 0.0)  # from X_R in the table plane
    standoff_mm: float = 6.0
    aim_mm: float = 0.05
    spot_rays: np.ndarray = field(default_factory=lambda: np.random.default_rng(
        12345).standard_normal((256, 2)) / 2.0)  # unit-w Gaussian (sigma = w / 2)


def random_truth(rng: np.random.Generator) -> dict[str, np.ndarray]:
    """A rig unlike Table I: v up to ~5 deg off it, n up to ~1 deg, X_R within ~10 mm."""
    v = _unit(np.array(PAPER["v"]) + rng.normal(0, 0.05, 3))
    n = _unit(np.array(PAPER["n"]) + rng.normal(0, 0.01, 3))
    xr = np.array(PAPER["X_R"]) + np.array([*rng.normal(0, 5.0, 2), 0.0])
    return {"v": v, "n": n, "X_R": xr}


def paper_truth() -> dict[str, np.ndarray]:
    """Table I, v and n normalised."""
    return {"v": _unit(PAPER["v"]), "n": _unit(PAPER["n"]), "X_R": np.array(PAPER["X_R"])}


def _amp_and_depth(hit_t: np.ndarray, weight: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per raw point (rows) from its spot rays (columns, drawn from the spot's intensity):
    amplitude (the rays' weights: share of the spot on the target, by incidence) and the
    mean hit distance of the rays that hit (NaN: nothing hit)."""
    amp = weight.mean(axis=1)
    hit = weight > 0
    with np.errstate(invalid="ignore", divide="ignore"):
        d = np.where(hit.any(axis=1), np.where(hit, hit_t, 0).sum(axis=1)
                     / np.maximum(hit.sum(axis=1), 1), np.nan)
    return amp, d


def _noisy(amp: np.ndarray, d: np.ndarray, nz: Noise, rng: np.random.Generator,
           common: float) -> tuple[np.ndarray, np.ndarray]:
    """Amplitude and depth noise; no echo where the amplitude is below detection."""
    a = amp * (1 + nz.amp_rel * rng.standard_normal(amp.shape)) + \
        nz.amp_add * rng.standard_normal(amp.shape)
    t5 = rng.standard_t(5, amp.shape) / np.sqrt(5 / 3)  # unit variance
    dd = d + common + nz.depth_mm * t5
    dd = np.where((a >= nz.detect) & np.isfinite(d), dd, np.nan)
    return a, dd


def _tip_rows(truth: dict, rig: Rig, ras: Raster, nz: Noise, rng: np.random.Generator,
              hidden: dict) -> list[dict]:
    v = truth["v"]
    axis = _unit(-v + np.tan(np.radians(rig.tip_tilt_deg)) * (_perp_basis(v) @ rng.uniform(
        -1, 1, 2)) / np.sqrt(2))  # toward the sensor
    # the tip stands 20 mm above the table, 10 mm toward the sensor from X_R
    T = truth["X_R"] + np.array([0.0, -10.0, 20.0])
    hidden["tip"], hidden["tip_axis"] = T, axis
    B = _perp_basis(v)
    rays = rig.spot_rays * rig.spot_w_mm
    offs = np.arange(-ras.tip_half, ras.tip_half + 1e-9, ras.tip_step)
    rows = []
    y0 = None
    for f, dy in enumerate(ras.tip_depths):
        S_face = T - (rig.standoff_mm + dy) * v  # where the sensor faces the tip
        if y0 is None:
            y0 = S_face[1]
        y = y0 - dy
        # centre of the raster in X, Z where the beam along v meets the tip, by eye
        lam = (y - T[1]) / v[1]
        cx, cz = T[0] + lam * v[0], T[2] + lam * v[2]
        cx += rng.uniform(-0.5, 0.5) * ras.tip_step + rng.normal(0, rig.aim_mm)
        cz += rng.uniform(-0.5, 0.5) * ras.tip_step + rng.normal(0, rig.aim_mm)
        X, Z = np.meshgrid(cx + offs, cz + offs)
        cmd = np.column_stack([X.ravel(), np.full(X.size, y), Z.ravel()])
        act = cmd + nz.stage_mm * rng.standard_normal(cmd.shape)
        # spot rays: origins across the beam, along v
        orig = act[:, None, :] + np.einsum("ij,kj->ki", B, rays)[None]  # (pts, rays, 3)
        t = ((T - orig) @ axis) / (v @ axis)   # the end face's plane
        H = orig + t[..., None] * v
        on = np.linalg.norm(H - T, axis=2) < rig.radius_mm
        amp, d = _amp_and_depth(t, on.astype(float))
        a, dd = _noisy(amp, d, nz, rng, nz.common_mm * rng.standard_normal())
        for i in range(len(cmd)):
            rows.append({"step": "tip", "frame": f, "line": 0, "theta_deg": 0.0,
                         "sx_mm": cmd[i, 0], "sy_mm": cmd[i, 1], "sz_mm": cmd[i, 2],
                         "d_mm": dd[i], "amplitude": a[i], "modality": "oa"})
    return rows


def _cylinder_hits(orig: np.ndarray, v: np.ndarray, P: np.ndarray, q: np.ndarray, r: float
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Nearest hit distance along v of rays orig + t v with the infinite cylinder (point P,
    unit direction q, radius r), and cos(incidence) there (0 where missed)."""
    w = orig - P
    vp = v - (v @ q) * q
    wp = w - (w @ q)[..., None] * q
    a = vp @ vp
    b = 2 * (wp @ vp)
    c = (wp * wp).sum(axis=-1) - r * r
    disc = b * b - 4 * a * c
    hit = disc > 0
    t = np.where(hit, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), np.nan)
    H = orig + np.nan_to_num(t)[..., None] * v
    rad = (H - P) - ((H - P) @ q)[..., None] * q
    cos = np.where(hit, -(rad @ v) / r, 0.0)
    return t, np.clip(cos, 0, 1)


def _edge_rows(truth: dict, rig: Rig, ras: Raster, nz: Noise, rng: np.random.Generator,
               hidden: dict) -> list[dict]:
    v, n, xr = truth["v"], truth["n"], truth["X_R"]
    q0 = _unit(n + np.tan(np.radians(rig.edge_tilt_deg)) * (_perp_basis(n) @ rng.uniform(
        -1, 1, 2)) / np.sqrt(2))
    # the filament's foot on the table at theta = 0: offset from X_R within the table plane
    Bn = _perp_basis(n)
    ex = _unit(np.array([1.0, 0, 0]) - n[0] * n)
    ey = np.cross(n, ex)
    P0 = xr + rig.edge_offset_mm[0] * ex + rig.edge_offset_mm[1] * ey
    del Bn
    B = _perp_basis(v)
    rays = rig.spot_rays * rig.spot_w_mm
    offs = np.arange(-ras.edge_half, ras.edge_half + 1e-9, ras.edge_step)
    rows = []
    for f, th in enumerate(ras.angles):
        actual = th + nz.table_deg * rng.standard_normal()
        R = _turn(n, actual)
        P, q = xr + R @ (P0 - xr), R @ q0
        hidden.setdefault("axes", []).append((P, q))
        # the sensor's Y facing the filament at mid height, standoff along v
        mid = P + (np.mean(ras.edge_levels) - P[2]) / q[2] * q
        y = (mid - rig.standoff_mm * v)[1]
        for li, z in enumerate(ras.edge_levels):
            # where along X the beam at (y, z) meets the axis, by eye
            lam_pt = P + (z - P[2]) / q[2] * q
            s = (y - lam_pt[1]) / v[1]
            cx = lam_pt[0] + s * v[0] + rng.uniform(-0.5, 0.5) * ras.edge_step + rng.normal(
                0, rig.aim_mm)
            cmd = np.column_stack([cx + offs, np.full(len(offs), y), np.full(len(offs), z)])
            act = cmd + nz.stage_mm * rng.standard_normal(cmd.shape)
            orig = act[:, None, :] + np.einsum("ij,kj->ki", B, rays)[None]
            t, cos = _cylinder_hits(orig, v, P, q, rig.radius_mm)
            amp, d = _amp_and_depth(t, cos)
            a, dd = _noisy(amp, d, nz, rng, nz.common_mm * rng.standard_normal())
            for i in range(len(cmd)):
                rows.append({"step": "edge", "frame": f, "line": li, "theta_deg": th,
                             "sx_mm": cmd[i, 0], "sy_mm": cmd[i, 1], "sz_mm": cmd[i, 2],
                             "d_mm": dd[i], "amplitude": a[i], "modality": "oa"})
    return rows


def generate(truth: dict, seed: int, noise: Noise | str = "paper",
             raster: Raster | str = "default", rig: Rig | None = None,
             hidden: dict | None = None) -> list[dict]:
    """Raw points (dicts with the rig CSV's columns) of the tip and edge steps for `truth`
    ({"v", "n", "X_R"}, arrays) with the given noise, raster and rig; `hidden`, if given,
    gets the tip point ("tip"), the tip face's normal ("tip_axis") and each edge frame's
    actual axis ("axes": point, direction)."""
    nz = NOISE_LEVELS[noise] if isinstance(noise, str) else noise
    ras = RASTERS[raster] if isinstance(raster, str) else raster
    rig = rig or Rig()
    rng = np.random.default_rng(seed)
    truth = {k: np.asarray(x, float) for k, x in truth.items()}
    hidden = {} if hidden is None else hidden
    return (_tip_rows(truth, rig, ras, nz, rng, hidden)
            + _edge_rows(truth, rig, ras, nz, rng, hidden))


def write_csv(rows: list[dict], path: Path) -> Path:
    """The rig CSV (header, one row per raw point; d empty where no echo)."""
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(COLUMNS)
        for r in rows:
            w.writerow([r["step"], r["frame"], r["line"], f"{r['theta_deg']:.6g}",
                        f"{r['sx_mm']:.4f}", f"{r['sy_mm']:.4f}", f"{r['sz_mm']:.4f}",
                        "" if not np.isfinite(r["d_mm"]) else f"{r['d_mm']:.5f}",
                        f"{r['amplitude']:.5g}", r["modality"]])
    return Path(path)


if __name__ == "__main__":
    import argparse

    ap = argparse.ArgumentParser(description="independent calibration-rig CSV")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--noise", choices=sorted(NOISE_LEVELS), default="paper")
    ap.add_argument("--raster", choices=sorted(RASTERS), default="default")
    ap.add_argument("--radius", type=float, default=0.25)
    ap.add_argument("--random-truth", action="store_true")
    a = ap.parse_args()
    tr = random_truth(np.random.default_rng([a.seed, 1])) if a.random_truth else paper_truth()
    write_csv(generate(tr, a.seed, a.noise, a.raster, Rig(radius_mm=a.radius)), a.out)
    print(json.dumps({k: np.asarray(x).tolist() for k, x in tr.items()}))
