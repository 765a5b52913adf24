"""An object's 3D model from its scans in the database: the points fused with covariances, the
surface, and each vertex's material from the classifier's probabilities of the waveforms near it.

Every finished scan of the object in the catalogue whose file still matches its content hash
is used (all levels, angles, both modalities, several sessions); a scan file that changed or
is gone is left out and said. The model records each scan's content hash, so a later change
makes it stale (host/model/store.py).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from ..calibration.result import joint_covariance
from ..classify.materials import WINDOW, ClassifyError, FusedModel, scan_dataset
from ..classify.model_file import check_provenance, load_model
from ..ranging.calibrate import RangingSetup
from ..scan.catalogue import list_scans, verify
from ..scan.points import MODS, scan_points
from ..scan.reach import US_MAX_INCIDENCE_DEG
from ..scan.reconstruct import object_points
from ..scan.scanfile import ScanData, ScanFileError, read_scan
from .fuse import REASONS, covariance_parts, outliers, travel_covariance
from .store import ModelError, ObjectModel, check_object_id, utc_now
from .surface import build_surface

MATERIAL_RADIUS_MM = 3.0   # waveforms within this of a vertex give it their probabilities
MATERIAL_SMEAR_MM = 0.4    # a waveform whose shots' depth changed by more than about one
# period of the 1 MHz OA pulse in air (0.34 mm) over its travel is averaged out of shape: on
# a fly-scanned soda can 85-91 % of the waveforms below 0.4 mm were right, 50 % at 0.4-0.8
# and 18 % beyond (the classifier learns standing shots)
MATERIAL_CLEAN_RADIUS_MM = 8.0  # the clean waveforms within this of a vertex give it their
# probabilities (weighted by distance) before any smeared one within MATERIAL_RADIUS_MM
SPOT_RADIUS_MM = 0.25      # the laser spot's radius at the target (OA points' footprint)
STAGE_STD_MM = 0.005       # the stage's repeatability per axis (Marlin's step: 1/80 mm)
TABLE_STD_DEG = 0.01       # the turntable's angle repeatability
MIN_POINTS = 50            # points a surface needs (after the outliers are out)
Progress = Callable[[str], None]


def object_scans(db_dir: Path, object_id: str) -> tuple[list[dict], list[str]]:
    """The catalogue rows of the object's finished scans whose files match their hashes, and
    one line per scan left out (unfinished, changed, missing)."""
    rows, left = [], []
    for row in list_scans(Path(db_dir), object_id):
        state = verify(row)
        if state == "ok":
            rows.append(row)
        else:
            left.append(f"scan {row['scan_id']} left out: {state}")
    return rows, left


def _view_dirs(scan: ScanData, theta_deg: np.ndarray) -> np.ndarray:
    """Unit vectors (k, 3) from each point toward the sensor, in the object frame: -v
    turned back by the table's angle (the direction part of object_points)."""
    cal = scan.calibration
    v = np.asarray(cal["v"], float)
    v = v / np.linalg.norm(v)
    zero = np.zeros(3)
    return -object_points(np.tile(v, (len(theta_deg), 1)), theta_deg, np.asarray(cal["n"]),
                          zero)


def _std(cal: dict, key: str) -> np.ndarray:
    """A calibration's per-component std (zeros where the file carries none)."""
    s = np.asarray(cal.get(key, (0.0, 0.0, 0.0)), float).reshape(-1)
    return s if s.shape == (3,) and np.all(np.isfinite(s)) else np.zeros(3)


def _joint_cov(cal: dict) -> np.ndarray | None:
    """A scan's calibration's joint 9 x 9 covariance of v, n, X_R, or None where it carries
    none or one that is not a covariance: then the per-component stds are used, as for
    calibrations written before it."""
    return joint_covariance(cal.get("cov", ()))


def ranging_offset_std_mm(ranging_json: str, geometric: str = "oa") -> dict[str, float]:
    """The std (mm) of the error every distance of a modality shares: its ranging
    calibration's t0 (std times c, halved for the US round trip) less what the geometric
    calibration absorbed. That one (`dmdsm calibrate --modality`, recorded in its file and
    so in the scan's; OA in files from before) measured its centre points with the
    `geometric` modality's distances, so their t0 error is in X_R and cancels from that
    modality's points; the other modality's points keep both t0 errors. {} if the setup is
    not readable."""
    try:
        cals = RangingSetup.from_json(ranging_json).cals
    except (ValueError, KeyError, TypeError):
        return {}
    t0 = {m: c.t0_std_s * c.c_mm_s / (1.0 if m == "oa" else 2.0) for m, c in cals.items()}
    return {m: float(np.hypot(s, t0.get(geometric, 0.0))) for m, s in t0.items()
            if m != geometric}


def scan_point_set(scan: ScanData, stage_std_mm: float = STAGE_STD_MM,
                   table_std_deg: float = TABLE_STD_DEG, calibration_part: bool = True
                   ) -> dict[str, np.ndarray]:
    """One scan's points of both modalities (object frame, mm) with their 3x3 covariances
    (mm^2; `common`: the part shared by neighbours, calibration and table; `offset`: the
    part of common that is the modality's ranging offset, shared by its points only;
    `repeat`: the travel smear, which every scan of a place repeats), the direction
    toward the sensor, modality (0 OA, 1 US) and row in the file (`index`).
    calibration_part=False leaves out what the calibrations' errors add (v, n, X_R and the
    ranging offsets: one draw shared by a whole run, which one run cannot check)."""
    pts = scan_points(scan)
    cal = scan.calibration
    offset = ranging_offset_std_mm(scan.ranging_json, str(cal.get("modality", "oa"))) \
        if calibration_part else {}
    cal_std = {k: _std(cal, k) if calibration_part else np.zeros(3)
               for k in ("v_std", "n_std", "X_R_std")}
    keys = ("P", "cov", "common", "offset", "repeat", "view", "mod", "index")
    out: dict[str, list[np.ndarray]] = {k: [] for k in keys}
    for k, m in enumerate(MODS):
        p = pts[m]
        if not len(p["P"]):
            continue
        d_std = np.where(np.isfinite(p["d_std"]), p["d_std"], np.nan)
        if np.isnan(d_std).any():
            raise ModelError(f"{scan.path} carries no ranging setup for {m.upper()} distance "
                             f"stds: rescan with this dmdsm, or range it again")
        P, own, common = covariance_parts(
            p["S"], p["d"], d_std, p["theta_deg"], cal["v"], cal["n"], cal["X_R"],
            cal_std["v_std"], cal_std["n_std"], cal_std["X_R_std"],
            stage_std_mm=stage_std_mm, table_std_deg=table_std_deg, travel_mm=p["travel"],
            cal_cov=_joint_cov(cal) if calibration_part else None,
            offset_std_mm=offset.get(m, 0.0))
        out["P"].append(P)
        out["repeat"].append(travel_covariance(p["theta_deg"], cal["n"], p["travel"]))
        out["cov"].append(own + common)
        out["common"].append(common)
        view = _view_dirs(scan, p["theta_deg"])  # the offset's part of common: along the beam
        out["offset"].append(offset.get(m, 0.0) ** 2 * np.einsum("ki,kj->kij", view, view))
        out["view"].append(view)
        out["mod"].append(np.full(len(P), k, np.uint8))
        out["index"].append(np.asarray(p["row"], np.int32))
    if not out["P"]:
        return {"P": np.zeros((0, 3)), "cov": np.zeros((0, 3, 3)),
                "common": np.zeros((0, 3, 3)), "offset": np.zeros((0, 3, 3)),
                "repeat": np.zeros((0, 3, 3)),
                "view": np.zeros((0, 3)),
                "mod": np.zeros(0, np.uint8), "index": np.zeros(0, np.int32)}
    return {k: np.concatenate(v) for k, v in out.items()}


def waveform_probabilities(scan: ScanData, classifier: tuple[FusedModel, dict],
                           model_path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                      np.ndarray]:
    """Object-frame places (k, 3, mm) of the scan's waveforms the classifier can use (the OA
    point, else the US point), its probabilities for them (k, classes), their rows in the
    file (k,) and, for the ones without a US window, the probabilities were that silence
    the geometry's (k, classes; the first where there is an echo): `geometric_silence`
    chooses once the surface is known."""
    model, prov = classifier
    ds = scan_dataset(scan, int(prov.get("window", WINDOW)))
    check_provenance(prov, model_path, ds.fs_hz, ds.window)
    pts = scan_points(scan)
    place = np.full((scan.n_points, 3), np.nan)
    for m in reversed(MODS):  # OA last: it wins where both are there
        place[pts[m]["row"]] = pts[m]["P"]
    rows = ds.usable(model.modalities)
    rows = rows[np.all(np.isfinite(place[rows]), axis=1)]
    if not len(rows):
        empty = np.zeros((0, len(model.classes)))
        return np.zeros((0, 3)), empty, np.zeros(0, np.int64), empty
    said, unsaid = model.predict_proba_silence(ds.subset(rows))
    return place[rows], said, rows, unsaid


def geometric_silence(places_mm: np.ndarray, view: np.ndarray, has_us: np.ndarray,
                      vertices_mm: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Which waveforms (k,) lack a US echo because of the geometry: the nearest vertex's
    normal more than US_MAX_INCIDENCE_DEG from the beam (view: unit vectors toward the
    sensor). A US echo is specular, so beyond that no material returns one; the silence
    says nothing of the material there (the classifier learns standing, head-on shots,
    where it does: glass and steel give no OA, foam no echo)."""
    if not len(places_mm):
        return np.zeros(0, bool)
    _, i = cKDTree(vertices_mm).query(places_mm)
    cos = np.abs(np.sum(normals[i] * view, axis=1))
    return ~np.asarray(has_us, bool) & (cos < np.cos(np.radians(US_MAX_INCIDENCE_DEG)))


def row_view(points: dict[str, np.ndarray], rows: np.ndarray) -> np.ndarray:
    """The unit vector (k, 3) toward the sensor of each row's point in a scan_point_set
    (NaN where the row has none)."""
    out = np.full((len(rows), 3), np.nan)
    rows = np.asarray(rows, np.int64)
    if not len(rows):
        return out
    slot = np.full(int(max(rows.max(), np.max(points["index"], initial=-1))) + 1, -1)
    slot[rows] = np.arange(len(rows))
    i = slot[np.asarray(points["index"], np.int64)]
    out[i[i >= 0]] = points["view"][i >= 0]  # a row's OA and US points share the beam
    return out


def row_travel(points: dict[str, np.ndarray], rows: np.ndarray) -> np.ndarray:
    """The travel covariance (k, 3, 3, mm^2) of each row's point in a scan_point_set (the
    OA point's where both are, as waveform_probabilities places them; zero if none)."""
    out = np.zeros((len(rows), 3, 3))
    rows = np.asarray(rows, np.int64)
    if not len(rows):
        return out
    slot = np.full(int(max(rows.max(), np.max(points["index"], initial=-1))) + 1, -1)
    slot[rows] = np.arange(len(rows))
    for m in sorted(set(points["mod"].tolist()), reverse=True):  # US first, OA overwrites
        k = np.flatnonzero(points["mod"] == m)
        i = slot[np.asarray(points["index"][k], np.int64)]
        out[i[i >= 0]] = points["repeat"][k[i >= 0]]
    return out


def depth_smear_mm(places_mm: np.ndarray, travel_cov_mm2: np.ndarray,
                   vertices_mm: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """How far (mm) the surface's depth changed over each waveform's travel: its travel
    (a uniform spread of travel^2/12 along the path) across the nearest vertex's normal."""
    if not len(places_mm):
        return np.zeros(0)
    _, vi = cKDTree(vertices_mm).query(places_mm)
    n = normals[vi]
    return np.sqrt(12.0 * np.maximum(np.einsum("ki,kij,kj->k", n, travel_cov_mm2, n), 0.0))


def vertex_materials(vertices_mm: np.ndarray, places_mm: np.ndarray, prob: np.ndarray,
                     radius_mm: float = MATERIAL_RADIUS_MM, smear_mm: np.ndarray | None = None,
                     clean_mm: float = MATERIAL_SMEAR_MM,
                     clean_radius_mm: float = MATERIAL_CLEAN_RADIUS_MM) -> np.ndarray:
    """Per vertex the probabilities (V, classes) of the waveforms near it, each weighted
    by a Gaussian of radius_mm in its distance: the clean ones (depth smear over their
    travel at most clean_mm) within clean_radius_mm, else any within radius_mm; NaN rows
    where none is. A smeared waveform's pulse is averaged out of the shape the classifier
    knows, so a few clean ones a little farther away say more than many smeared ones at the
    vertex. smear_mm None: every waveform is taken as clean, within radius_mm."""
    out = np.full((len(vertices_mm), prob.shape[1]), np.nan, np.float32)
    if not len(places_mm):
        return out
    clean = np.ones(len(places_mm), bool) if smear_mm is None else smear_mm <= clean_mm
    near = cKDTree(places_mm).query_ball_point(vertices_mm, radius_mm)
    ci = np.flatnonzero(clean)
    far = cKDTree(places_mm[ci]).query_ball_point(vertices_mm, clean_radius_mm) \
        if len(ci) else [[] for _ in range(len(vertices_mm))]
    for i, idx in enumerate(near):
        use = ci[far[i]] if smear_mm is not None and len(far[i]) else np.asarray(idx, int)
        if len(use):  # nearer ones count more: Gaussian weights of radius_mm
            d2 = np.sum((places_mm[use] - vertices_mm[i]) ** 2, axis=1)
            w = np.exp(-0.5 * d2 / radius_mm ** 2)
            out[i] = w @ prob[use] / w.sum()
    return out


def model_verdict(model: ObjectModel) -> dict | None:
    """The object's material from its model: the class of highest mean probability over the
    supported vertices that have probabilities (each from the clean waveforms near it, so a
    fly scan's smeared ones do not outvote them), that mean as the confidence; None if the
    model carries no materials."""
    p = np.asarray(model.material_prob, float)
    if p.ndim != 2 or p.shape[1] == 0 or len(p) != len(model.supported):
        return None
    sel = np.asarray(model.supported, bool) & np.isfinite(p).all(axis=1)
    if not sel.any():
        return None
    mean = p[sel].mean(axis=0)
    best = int(mean.argmax())
    return {"source": "model", "material": str(model.classes[best]),
            "confidence": float(mean[best]), "vertices": int(sel.sum()),
            "probabilities": {str(c): float(x) for c, x in zip(model.classes, mean)}}


def build_object_model(db_dir: Path, object_id: str, *, classifier: Path | None = None,
                       spacing_mm: float = 1.0, modalities: tuple[str, ...] = MODS,
                       progress: Progress | None = None, calibration_part: bool = True
                       ) -> ObjectModel:
    """The model of one object from its scans in db_dir (not written yet: store.write_model).
    classifier: a `dmdsm classify train` model file giving the vertices' materials (none:
    the model carries no materials); modalities: the points' modalities the surface is built
    from (the bench builds one per modality); calibration_part=False: sigma without the
    calibrations' part (scan_point_set; the demo's check of the rest against one run's
    truth). Raises ModelError with one line on what to do."""
    say = progress or (lambda _s: None)
    check_object_id(object_id)
    rows, left = object_scans(Path(db_dir), object_id)
    if not rows:
        raise ModelError(f"no finished scan of object {object_id!r} in {db_dir}"
                         + (f" ({'; '.join(left)})" if left else "")
                         + ": scan it first (dmdsm scan)")
    clf = None
    if classifier is not None:
        try:
            clf = load_model(Path(classifier))
        except ClassifyError as e:
            raise ModelError(str(e)) from None
    t0 = time.monotonic()
    parts, places, probs, travels, sources = [], [], [], [], []
    free_probs, views, echoes = [], [], []
    for k, row in enumerate(rows):
        try:
            scan = read_scan(Path(row["path"]), waveforms=clf is not None)
        except ScanFileError as e:
            raise ModelError(f"scan {row['scan_id']}: {e}") from None
        one = scan_point_set(scan, calibration_part=calibration_part)
        one["scan"] = np.full(len(one["P"]), k, np.int32)
        parts.append(one)
        if clf is not None:
            try:
                where, p, used, p_free = waveform_probabilities(scan, clf, Path(classifier))
            except ClassifyError as e:
                raise ModelError(f"scan {row['scan_id']}: {e}") from None
            places.append(where)
            probs.append(p)
            free_probs.append(p_free)
            views.append(row_view(one, used))
            echoes.append(np.isfinite(scan.points["distance_us_mm"][used]))
            travels.append(row_travel(one, used))
        sources.append({"scan_id": row["scan_id"], "content_hash": row["content_hash"],
                        "material": row.get("material", "")})
        say(f"read scan {row['scan_id']}: {len(one['P'])} points")
    pts = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    keep = np.isin(pts["mod"], [MODS.index(m) for m in modalities])
    pts = {k: v[keep] for k, v in pts.items()}
    if len(pts["P"]) < MIN_POINTS:
        raise ModelError(f"object {object_id!r} has {len(pts['P'])} points in its scans: too "
                         f"few for a surface; scan it (more levels or angles) first")
    good, why = outliers(pts["P"], pts["cov"])
    bad = ~good
    say(f"{int(bad.sum())} of {len(bad)} points are outliers ("
        + ", ".join(f"{REASONS[int(c)]} {int((why == c).sum())}" for c in np.unique(why[bad]))
        + ")" if bad.any() else "no outliers")
    if good.sum() < MIN_POINTS:
        raise ModelError(f"object {object_id!r} has {int(good.sum())} points left of "
                         f"{len(good)} once the outliers are out: too few for a surface; scan "
                         f"it (more levels or angles) first")
    surf = build_surface(pts["P"][good], pts["cov"][good], pts["view"][good],
                         spacing_mm=spacing_mm, cov_common=pts["common"][good],
                         cov_repeat=pts["repeat"][good], group=pts["scan"][good],
                         cov_offset=pts["offset"][good], offset_group=pts["mod"][good],
                         spot_mm=np.where(pts["mod"][good] == MODS.index("oa"),
                                          SPOT_RADIUS_MM, 0.0))
    classes: list[str] = []
    prob = np.zeros((len(surf.vertices_mm), 0), np.float32)
    if clf is not None:
        classes = [str(c) for c in clf[0].classes]
        where = np.concatenate(places)
        smear = depth_smear_mm(where, np.concatenate(travels), surf.vertices_mm, surf.normals)
        silent = geometric_silence(where, np.concatenate(views), np.concatenate(echoes),
                                   surf.vertices_mm, surf.normals)
        p = np.where(silent[:, None], np.concatenate(free_probs), np.concatenate(probs))
        prob = vertex_materials(surf.vertices_mm, where, p, smear_mm=smear)
    model = ObjectModel(
        object_id=object_id, version=0,
        created=utc_now(), sources=sources,
        params={"spacing_mm": spacing_mm, "material_radius_mm": MATERIAL_RADIUS_MM,
                "material_smear_mm": MATERIAL_SMEAR_MM,
                "material_clean_radius_mm": MATERIAL_CLEAN_RADIUS_MM,
                "stage_std_mm": STAGE_STD_MM, "table_std_deg": TABLE_STD_DEG,
                "classifier": str(classifier) if classifier else "",
                "modalities": list(modalities), **surf.params},
        summary={}, points_mm=pts["P"], points_cov_mm2=pts["cov"],
        points_modality=pts["mod"], points_scan=pts["scan"], points_row=pts["index"],
        points_outlier=bad, vertices_mm=surf.vertices_mm, faces=surf.faces,
        normals=surf.normals, sigma_mm=surf.sigma_mm, support=surf.support,
        supported=surf.supported, classes=classes, material_prob=prob)
    model.summary = model_summary(model, left, time.monotonic() - t0)
    return model


def model_summary(model: ObjectModel, left: list[str], build_s: float) -> dict:
    """The figures a listing shows: points, outliers, vertices, supported share, median
    sigma (mm), the material of the supported vertices, scans left out, build time (s)."""
    sup = model.supported
    mat = model.material
    named = mat[sup & (mat != "")] if len(mat) else np.array([], str)
    kinds, counts = np.unique(named, return_counts=True) if len(named) else ([], [])
    return {"points": int(len(model.points_mm)), "outliers": int(model.points_outlier.sum()),
            "vertices": int(len(model.vertices_mm)), "supported_share": float(sup.mean())
            if len(sup) else 0.0,
            "sigma_median_mm": float(np.nanmedian(model.sigma_mm[sup])) if sup.any() else None,
            "materials": {str(k): int(c) for k, c in zip(kinds, counts)},
            "left_out": left, "build_s": round(build_s, 2)}
