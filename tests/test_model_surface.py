"""The closed surface (host/model/surface.py): sphere, cylinder and box surfaces within their
stated sigma by Monte Carlo at the sensor's noise, watertight and outward, a radius of 15 mm
followed to a few um, holes closed but unsupported, the voxel budget kept."""

import time

import numpy as np
import pytest
from scipy.spatial import cKDTree

from dmdsm.host.model import surface
from dmdsm.host.model.fuse import outliers
from dmdsm.host.model.surface import SurfaceModel, build_surface, point_normals

OA, US = 0.08, 0.18    # the distance's std along the beam (mm)


def unit(a):
    return a / np.linalg.norm(a, axis=-1, keepdims=True)


def sphere(gap, R=20.0):
    """Points about gap mm apart on a sphere, their outward normals, the exact signed distance."""
    n = int(4 * np.pi * R * R / gap ** 2)
    i = np.arange(n) + 0.5
    phi, th = np.arccos(1 - 2 * i / n), np.pi * (1 + 5 ** 0.5) * i
    nr = np.column_stack([np.cos(th) * np.sin(phi), np.sin(th) * np.sin(phi), np.cos(phi)])
    return R * nr, nr, lambda X: np.linalg.norm(X, axis=1) - R


def cylinder(gap, R=15.0, H=40.0, top=True):
    """A capped cylinder (the top cap left out unless top) standing on z = 0."""
    na, nz = int(2 * np.pi * R / gap), int(H / gap)
    th, z = np.meshgrid(np.arange(na) * 2 * np.pi / na, (np.arange(nz) + 0.5) * H / nz)
    th, z = th.ravel(), z.ravel()
    P = [np.column_stack([R * np.cos(th), R * np.sin(th), z])]
    N = [np.column_stack([np.cos(th), np.sin(th), 0 * th])]
    g = np.arange(-R, R + gap, gap)
    X, Y = (a.ravel() for a in np.meshgrid(g, g))
    m = X ** 2 + Y ** 2 < R ** 2 - 0.01
    for zc, nz_ in [(0.0, -1.0)] + ([(H, 1.0)] if top else []):
        P.append(np.column_stack([X[m], Y[m], np.full(m.sum(), zc)]))
        N.append(np.tile([0, 0, nz_], (m.sum(), 1)))

    def dist(Q):
        dr = np.hypot(Q[:, 0], Q[:, 1]) - R
        dz = np.maximum(-Q[:, 2], Q[:, 2] - H)
        return (np.hypot(np.maximum(dr, 0), np.maximum(dz, 0))
                + np.minimum(np.maximum(dr, dz), 0))
    return np.vstack(P), np.vstack(N), dist


def box(gap, a=(40.0, 30.0, 20.0)):
    """A box centred on the origin."""
    a = np.array(a)
    P, N = [], []
    for ax in range(3):
        o = [i for i in range(3) if i != ax]
        G1, G2 = np.meshgrid(np.arange(gap / 2, a[o[0]], gap), np.arange(gap / 2, a[o[1]], gap))
        for side in (0, 1):
            Q = np.zeros((G1.size, 3))
            Q[:, o[0]], Q[:, o[1]], Q[:, ax] = G1.ravel(), G2.ravel(), side * a[ax]
            n = np.zeros(3)
            n[ax] = 1.0 if side else -1.0
            P.append(Q)
            N.append(np.tile(n, (len(Q), 1)))

    def dist(X):
        q = np.abs(X) - a / 2
        return np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(axis=1), 0)
    return np.vstack(P) - a / 2, np.vstack(N), dist


def measure(P, nr, sd, rng, tilt=0.4, stage=0.01):
    """The sensor's view: beams tilted from the normal, the distance's noise along the beam
    (std sd), the stage's noise per axis; returns noisy points, covariances, view_dir."""
    vd = unit(nr + rng.normal(0, tilt, nr.shape))
    steep = np.einsum("ki,ki->k", vd, nr) < 0.3
    vd[steep] = nr[steep]
    Q = P + rng.normal(0, sd, len(P))[:, None] * vd + rng.normal(0, stage, P.shape)
    cov = sd ** 2 * np.einsum("ki,kj->kij", vd, vd) + stage ** 2 * np.eye(3)
    return Q, cov, vd


def check_mesh(m: SurfaceModel):
    assert m.vertices_mm.dtype == np.float64 and m.faces.dtype == np.int32
    assert m.params["watertight"]
    assert np.allclose(np.linalg.norm(m.normals, axis=1), 1.0)
    assert np.array_equal(np.isnan(m.sigma_mm), ~m.supported)


@pytest.mark.parametrize("sd", [OA, US])
@pytest.mark.parametrize("shape", [sphere, cylinder, box])
def test_sigma_holds_by_monte_carlo(shape, sd):
    """Three noise draws at 0.9, 1.2 and 1.5 mm spacing: RMS of (vertex error / sigma) within
    0.8..1.25, no bias beyond a fifth of sigma, every vertex supported, normals outward."""
    rng = np.random.default_rng(int(sd * 1000) + len(shape.__name__))
    z, e = [], []
    for gap in (0.9, 1.2, 1.5):
        P, nr, dist = shape(gap)
        Q, cov, vd = measure(P, nr, sd, rng)
        m = build_surface(Q, cov, vd)
        check_mesh(m)
        assert m.supported.all()
        err = dist(m.vertices_mm)
        z.append(err / m.sigma_mm)
        e.append(err)
        h = 1e-3   # the exact surface's gradient: outward
        grad = np.column_stack([dist(m.vertices_mm + h * np.eye(3)[i]) - err
                                for i in range(3)]) / h
        assert np.median(np.einsum("ki,ki->k", unit(grad), m.normals)) > 0.99
        assert (np.einsum("ki,ki->k", unit(grad), m.normals) > 0).mean() > 0.98
    z = np.concatenate(z)
    rms = np.sqrt(np.mean(z ** 2))
    assert 0.8 < rms < 1.25, rms
    assert abs(z.mean()) < 0.2
    assert np.sqrt(np.mean(np.concatenate(e) ** 2)) < sd     # the fit beats a single point


@pytest.mark.parametrize("shape", [sphere, cylinder])
def test_curvature_bias_is_a_few_um(shape):
    """Exact points on a radius of 15 mm: the supported vertices lie on it within 5 um (away
    from the cylinder's cap edges, where a smooth fit must round the corner)."""
    P, nr, dist = shape(1.0, R=15.0)
    cov = np.tile(1e-6 * np.eye(3), (len(P), 1, 1))
    m = build_surface(P, cov, nr)
    e = dist(m.vertices_mm)
    away = m.supported & (np.abs(m.vertices_mm[:, 2] - 20) < 16)
    assert np.abs(e[away]).max() < 0.005


def test_holes_are_closed_but_unsupported():
    """An open-topped cylinder with a window cut from its side: the mesh closes over both, the
    vertices far from every point are unsupported with sigma NaN, and the supported ones still
    lie within their sigma of the cylinder."""
    rng = np.random.default_rng(3)
    P, nr, dist = cylinder(1.0, top=False)
    window = (P[:, 0] > 0) & (np.abs(np.arctan2(P[:, 1], P[:, 0])) < 0.5) & \
        (np.abs(P[:, 2] - 20) < 6)
    P, nr = P[~window], nr[~window]
    Q, cov, vd = measure(P, nr, OA, rng)
    m = build_surface(Q, cov, vd)
    check_mesh(m)
    near = cKDTree(Q).query(m.vertices_mm)[0]
    R = m.params["support_radius_mm"]
    assert not m.supported[near > R].any()
    assert (near > 2 * R).sum() > 50            # the top and the window are closed over
    top = m.vertices_mm[:, 2] > 40 + 1
    assert top.sum() > 20 and not m.supported[top].any()
    win = ((m.vertices_mm[:, 0] > 12) & (np.abs(m.vertices_mm[:, 1]) < 3)
           & (np.abs(m.vertices_mm[:, 2] - 20) < 2))
    assert win.sum() > 3 and not m.supported[win].any()
    z = dist(m.vertices_mm[m.supported]) / m.sigma_mm[m.supported]
    assert 0.8 < np.sqrt(np.mean(z ** 2)) < 1.25
    assert (m.support[~m.supported] < m.params["min_support"]).any()
    assert (m.support[m.supported] >= m.params["min_support"]).all()


def test_normals_follow_the_view_not_the_order():
    """Point normals point toward the sensor whatever side PCA picked."""
    P, nr, _ = sphere(1.0)
    assert (np.einsum("ki,ki->k", point_normals(P, nr), nr) > 0.99).all()
    assert (np.einsum("ki,ki->k", point_normals(P, -nr), nr) < -0.99).all()


def test_voxel_budget_coarsens_the_grid():
    P, nr, dist = sphere(1.0)
    cov = np.tile(0.01 * np.eye(3), (len(P), 1, 1))
    m = build_surface(P, cov, nr, spacing_mm=0.25, max_voxels=100_000)
    assert np.prod(m.params["grid_shape"]) <= 100_000
    assert m.params["spacing_mm"] > 0.25
    check_mesh(m)


def test_refuses_too_few_or_mismatched_points():
    P, nr, _ = sphere(1.0)
    cov = np.tile(0.01 * np.eye(3), (len(P), 1, 1))
    with pytest.raises(ValueError, match="too few"):
        build_surface(P[:19], cov[:19], nr[:19])
    with pytest.raises(ValueError, match="must match"):
        build_surface(P, cov[:-1], nr)


def test_20k_points_build_in_seconds():
    rng = np.random.default_rng(5)
    P, nr, dist = sphere(1.0, R=40.0)
    assert len(P) > 20000
    Q, cov, vd = measure(P, nr, OA, rng)
    # the work it takes, in this process's CPU seconds (6.5 s on 2026-12-07): a loaded
    # machine (make test beside two busy loops) stretches the wall clock 3x, not the work;
    # bench/model.py has the wall-clock figures of whole scans
    t = time.process_time()
    m = build_surface(Q, cov, vd)
    assert time.process_time() - t < 15.0
    assert m.supported.all()


def test_scan_rows_a_level_apart():
    """A scan's sampling: rows of points 0.25 mm apart, levels 2 mm apart, open top and
    bottom. The support radius spans levels, the side is supported and within its sigma, and
    the outlier rule keeps every point, and finds 20 moved 1 mm off."""
    rng = np.random.default_rng(6)
    R = 20.0
    th, z = np.meshgrid(np.arange(0, 2 * np.pi, 0.25 / R), np.arange(1.0, 40.0, 2.0))
    th, z = th.ravel(), z.ravel()
    nr = np.column_stack([np.cos(th), np.sin(th), 0 * th])
    P = R * nr + np.column_stack([0 * z, 0 * z, z])
    Q, cov, vd = measure(P, nr, OA, rng)
    keep, _ = outliers(Q, cov)
    assert keep.all()
    bad = rng.choice(len(P), 20, replace=False)
    Qb = Q + nr * np.isin(np.arange(len(P)), bad)[:, None] * 1.0
    keep, _ = outliers(Qb, cov)
    assert not keep[bad].any() and keep.sum() == len(P) - 20
    m = build_surface(Q, cov, vd)
    check_mesh(m)
    assert m.params["support_radius_mm"] > 2.0
    side = np.abs(m.vertices_mm[:, 2] - 20) < 16
    assert m.supported[side].all()
    e = np.hypot(m.vertices_mm[side, 0], m.vertices_mm[side, 1]) - R
    assert 0.8 < np.sqrt(np.mean((e / m.sigma_mm[side]) ** 2)) < 1.25


@pytest.mark.parametrize("sd", [OA, US])
def test_a_smooth_surface_takes_a_wider_fit_and_an_edge_does_not(sd, monkeypatch):
    """Per vertex the widest of 1, 1.3 and 1.7 support radii whose height agrees with the
    narrower ones' (and fits as well): on a scan's rows a level apart on a cylinder nearly
    every vertex takes the widest and comes out 1.3x closer (RMS) than with the support radius
    alone, its sigma holding (RMS z 0.8-1.25); on a box the vertices by its edges come out
    no further off than with the support radius alone (the wider fit would round them)."""
    rng = np.random.default_rng(6)
    R = 20.0
    th, z = np.meshgrid(np.arange(0, 2 * np.pi, 0.25 / R), np.arange(1.0, 40.0, 2.0))
    nr = np.column_stack([np.cos(th.ravel()), np.sin(th.ravel()), 0 * th.ravel()])
    Q, cov, vd = measure(R * nr + np.column_stack([0 * nr[:, :2], z.ravel()]), nr, sd, rng)
    Pb, nb, dist = box(1.0)
    Qb = Pb + rng.normal(0, sd / 4, len(Pb))[:, None] * nb
    covb = (sd / 4) ** 2 * np.einsum("ki,kj->kij", nb, nb) + 1e-6 * np.eye(3)
    rms, edge = {}, {}
    for wider in (surface.WIDER, (1.0,)):
        monkeypatch.setattr(surface, "WIDER", wider)
        m = build_surface(Q, cov, vd)
        side = m.supported & (np.abs(m.vertices_mm[:, 2] - 20) < 16)
        e = np.hypot(m.vertices_mm[side, 0], m.vertices_mm[side, 1]) - R
        rms[len(wider)] = np.sqrt(np.mean(e ** 2))
        if len(wider) > 1:
            assert m.params["wider_radius_share"]["1.7"] > 0.9
            assert 0.8 < np.sqrt(np.mean((e / m.sigma_mm[side]) ** 2)) < 1.25
        mb = build_surface(Qb, covb, nb)
        V = mb.vertices_mm
        near = mb.supported & (np.sort(np.abs(V) - [20.0, 15.0, 10.0], axis=1)[:, 1] > -1.0)
        edge[len(wider)] = np.abs(dist(V[near])).mean()
    assert rms[1] > 1.3 * rms[3], rms
    assert edge[3] < 1.1 * edge[1] + 0.002, edge


def test_common_errors_are_not_averaged_down():
    """Twelve scans of a sphere, each shifted as a whole (a calibration error, 0.05 mm per
    axis) on top of the point noise: with that part given as cov_common the vertices hold
    their sigma; given as independent noise, the fit averages it down and sigma is too small."""
    rng = np.random.default_rng(7)
    P, nr, dist = sphere(1.5, R=10.0)
    with_c, without = [], []
    for _ in range(12):
        Q, cov, vd = measure(P, nr, OA, rng)
        Q = Q + rng.normal(0, 0.05, 3)
        common = np.tile(0.05 ** 2 * np.eye(3), (len(P), 1, 1))
        for c, out in ((common, with_c), (None, without)):
            m = build_surface(Q, cov + common, vd, cov_common=c)
            out.append(dist(m.vertices_mm) / m.sigma_mm)
    assert 0.8 < np.sqrt(np.mean(np.concatenate(with_c) ** 2)) < 1.25
    assert np.sqrt(np.mean(np.concatenate(without) ** 2)) > 1.3


def test_one_modalitys_offset_counts_by_its_share_of_the_fit():
    """OA and US points interleaved on a sphere, the US ones four times noisier and all
    shifted along their beams by one offset per run (a ranging t0 error, 0.06 mm): the OA
    points carry most of each fit, so a vertex moves by only their share of the offset.
    Given as cov_offset with its group the sigma holds (RMS z 0.8-1.25, 12 runs); as plain
    common variance it is averaged by weight, not by weight squared, and sigma is
    overstated (z 0.69)."""
    rng = np.random.default_rng(11)
    P, nr, dist = sphere(1.2, R=12.0)
    us = rng.random(len(P)) < 0.5
    sd = np.where(us, 4 * 0.03, 0.03)
    grouped, plain = [], []
    for _ in range(12):
        Q, cov, vd = measure(P, nr, 0.0, rng)
        Q = Q + (rng.normal(0, 1, len(P)) * sd)[:, None] * vd
        Q[us] += rng.normal(0, 0.06) * vd[us]
        cov = cov + np.einsum("k,ki,kj->kij", sd ** 2, vd, vd)
        off = np.einsum("k,ki,kj->kij", np.where(us, 0.06 ** 2, 0.0), vd, vd)
        m = build_surface(Q, cov + off, vd, cov_common=off, cov_offset=off,
                          offset_group=us.astype(int))
        grouped.append(dist(m.vertices_mm) / m.sigma_mm)
        m = build_surface(Q, cov + off, vd, cov_common=off)
        plain.append(dist(m.vertices_mm) / m.sigma_mm)
    z = np.sqrt(np.mean(np.concatenate(grouped) ** 2))
    assert 0.8 < z < 1.25, z
    assert np.sqrt(np.mean(np.concatenate(plain) ** 2)) < 0.75  # 0.69


def test_dense_rows_from_many_table_angles_give_no_wild_vertex():
    """A turntable scan's points: at each of 12 table angles, rows 2 mm apart of points
    0.7 mm apart along the row, noise along the beam. A vertex's nearest points then span two
    rows only (near the band's edge, or with a small radius): its fit must still be right (a
    plane across the rows), not singular; found on such data as vertices 1-2 mm off."""
    R, rng = 25.0, np.random.default_rng(3)
    x = np.arange(-20.0, 20.01, 0.7)
    P, V = [], []
    for th in np.radians(np.arange(0.0, 360.0, 30.0)):
        c, s = np.cos(-th), np.sin(-th)
        Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        for z in np.arange(10.0, 30.01, 2.0):
            y = -np.sqrt(R * R - x * x) + rng.normal(0, 0.06, len(x))
            P.append(np.column_stack([x, y, np.full(len(x), z)]) @ Rz.T)
            V.append(np.tile(Rz @ [0.0, -1.0, 0.0], (len(x), 1)))
    P, V = np.vstack(P), np.vstack(V)
    cov = np.tile(np.diag([1e-6, 0.06 ** 2, 1e-6]), (len(P), 1, 1))
    for radius in (None, 5.0):
        s = build_surface(P, cov, V, spacing_mm=1.0, support_radius_mm=radius)
        e = np.hypot(*s.vertices_mm[s.supported, :2].T) - R
        assert s.supported.sum() > 3000
        assert np.abs(e).max() < 0.3 and np.abs(e).mean() < 0.03, (radius, np.abs(e).max())


def test_a_lone_row_is_not_taken_for_a_surface_it_does_not_span():
    """A first look's sampling: a band of three rows 1 mm apart on a block's sides, and 15 mm
    above and below it one lone row each, seen head on and at 45 degrees (noise along the
    beams). A lone row's points lie in the plane of its beams: fitted there, a vertex got
    that plane, edge on to the face, and a sigma of um for errors of tenths (RMS z 20-35 on
    the block's model of tests/e2e/test_auto_scan.py). By Monte Carlo: the supported
    vertices hold their sigma, the band's are supported (away from its rims) and a lone
    row's are not."""
    half = np.array([20.0, 15.0])
    rng = np.random.default_rng(12)
    z_all, lone_sup, band_sup = [], 0, []
    for _ in range(3):
        P, V = [], []
        for ax, sign in ((0, 1), (0, -1), (1, 1), (1, -1)):
            nrm = np.zeros(3)
            nrm[ax] = sign
            t = np.zeros(3)
            t[1 - ax] = 1.0
            u = np.arange(-half[1 - ax] + 1.0, half[1 - ax] - 0.9, 2.0)
            rows = [(z, 0.0) for z in (19.0, 20.0, 21.0)] + \
                [(z, tilt) for z in (5.0, 35.0) for tilt in (0.0, 0.785)]
            for z, tilt in rows:
                sgn = rng.choice([-1.0, 1.0], len(u))
                vd = np.cos(tilt) * nrm + np.sin(tilt) * sgn[:, None] * t
                X = u[:, None] * t + half[ax] * sign * np.abs(nrm) + [0.0, 0.0, z]
                P.append(X + rng.normal(0, OA, len(u))[:, None] * vd
                         + rng.normal(0, 0.002, X.shape))
                V.append(vd)
        P, V = np.vstack(P), np.vstack(V)
        cov = OA ** 2 * np.einsum("ki,kj->kij", V, V) + 0.002 ** 2 * np.eye(3)
        m = build_surface(P, cov, V, spacing_mm=1.0)
        check_mesh(m)
        X = m.vertices_mm
        face = np.abs(np.abs(X[:, :2]) - half).min(axis=1) < 1.0
        sup = m.supported & face
        lone = (np.abs(X[:, 2] - 5) < 1.5) | (np.abs(X[:, 2] - 35) < 1.5)
        band = face & (np.abs(X[:, 2] - 20) < 0.5) & (np.abs(np.abs(X[:, :2]) - half).max(1) > 4)
        z_all.append((np.abs(X[sup, :2]) - half).max(axis=1) / m.sigma_mm[sup])
        lone_sup += int((sup & lone).sum())
        band_sup.append(m.supported[band].mean())
    z_all = np.concatenate(z_all)
    rms = np.sqrt(np.mean(z_all ** 2))
    assert lone_sup == 0 and min(band_sup) > 0.9
    assert 0.7 < rms < 1.3, (rms, np.abs(z_all).max())


def test_a_smear_every_scan_repeats_is_not_averaged_down_across_scans():
    """Four scans of one cylinder by the same plan: each point's travel smear (a uniform
    spread along a travel at 45 degrees to the surface, std 0.15 mm along the normal) is the
    same error in every scan - the surface's slope along the travel sets it - and the noise
    along the beam is new. Given as cov_repeat with the scan as group, the vertices hold
    their sigma (RMS z 0.8-1.25) with 1, 2 and 4 scans; as independent noise the fit averages
    it down by the number of scans and sigma is too small (RMS z > 1.3 with 4)."""
    rng = np.random.default_rng(11)
    P, nr, dist = cylinder(1.2, top=False)
    side = np.abs(nr[:, 2]) < 0.5
    P, nr = P[side], nr[side]
    tangent = unit(np.cross([0.0, 0.0, 1.0], nr))
    travel = 0.735 * unit(nr + tangent)               # mm; 0.15 mm std along the normal
    smear_cov = np.einsum("ki,kj->kij", travel, travel) / 12.0
    z_with, z_without = {}, []
    for _draw in range(3):
        shift = rng.uniform(-0.5, 0.5, len(P))[:, None] * travel   # drawn once: every scan
        scans = []
        for _ in range(4):
            Q, cov, vd = measure(P + shift, nr, OA, rng)
            scans.append((Q, cov + smear_cov, vd))
        for k in (1, 2, 4):
            Q, cov, vd = (np.concatenate(a) for a in zip(*scans[:k]))
            group = np.repeat(np.arange(k), len(P))
            m = build_surface(Q, cov, vd, cov_repeat=np.tile(smear_cov, (k, 1, 1)),
                              group=group)
            band = m.supported & (np.abs(m.vertices_mm[:, 2] - 20.0) < 14.0)
            z_with.setdefault(k, []).append(dist(m.vertices_mm[band]) / m.sigma_mm[band])
            if k == 4:
                m = build_surface(Q, cov, vd)
                band = m.supported & (np.abs(m.vertices_mm[:, 2] - 20.0) < 14.0)
                z_without.append(dist(m.vertices_mm[band]) / m.sigma_mm[band])
    for k, z in z_with.items():
        assert 0.8 < np.sqrt(np.mean(np.concatenate(z) ** 2)) < 1.25, k
    assert np.sqrt(np.mean(np.concatenate(z_without) ** 2)) > 1.3


def test_repeat_needs_its_groups():
    P, nr, _ = cylinder(1.5, top=False)
    Q, cov, vd = measure(P, nr, OA, np.random.default_rng(1))
    with pytest.raises(ValueError, match="cov_repeat"):
        build_surface(Q, cov, vd, cov_repeat=cov[:10], group=np.zeros(len(P), int))


@pytest.mark.parametrize("shape", [sphere, box])
def test_precise_points_count_more_than_noisy_ones_and_sigma_holds(shape):
    """Half the points at a std of 0.03 mm along their beam, half at 0.4 mm (a fly scan's
    head-on points beside smeared or weak ones), interleaved: the surface is weighted by each
    point's stated variance, so its vertices are about as close as the precise points' fit
    alone would put them (RMS error 0.033 mm; equal weights give 0.12) and their sigma holds
    (RMS z 0.8-1.25)."""
    rng = np.random.default_rng(5)
    z, e = [], []
    for gap in (0.9, 1.2):
        P, nr, dist = shape(gap)
        sd = np.where(rng.random(len(P)) < 0.5, 0.03, 0.4)
        vd = nr.copy()
        Q = P + rng.normal(0, 1, len(P))[:, None] * sd[:, None] * vd
        cov = np.einsum("k,ki,kj->kij", sd ** 2, vd, vd) + 1e-6 * np.eye(3)
        m = build_surface(Q, cov, vd)
        away = m.supported & (np.abs(dist(m.vertices_mm)) < 1)
        if shape is box:   # the edges are rounded by any smooth fit: faces only
            q = np.abs(m.vertices_mm) - np.array([20.0, 15.0, 10.0])
            away &= np.sort(q, axis=1)[:, 1] < -3.0
        err = dist(m.vertices_mm[away])
        e.append(err)
        z.append(err / m.sigma_mm[away])
    assert np.sqrt(np.mean(np.concatenate(e) ** 2)) < 0.045
    assert 0.8 < np.sqrt(np.mean(np.concatenate(z) ** 2)) < 1.25


def test_sigma_follows_the_points_scatter_where_it_is_less_than_stated():
    """Points stated at 0.12 mm along the beam that scatter by 0.04 mm (the ranging's floor is
    its calibration target's scatter; a waveform averaged over a moving spot has less): the
    vertices' sigma comes down to what the fits' residuals show (RMS z 0.8-1.25, not ~0.33);
    stated right (0.12 mm) it stays (the Monte Carlo test above)."""
    rng = np.random.default_rng(8)
    z = []
    for gap in (0.9, 1.2, 1.5):
        P, nr, dist = sphere(gap)
        Q, _, vd = measure(P, nr, 0.04, rng)
        cov = 0.12 ** 2 * np.einsum("ki,kj->kij", vd, vd) + 0.01 ** 2 * np.eye(3)
        m = build_surface(Q, cov, vd)
        z.append(dist(m.vertices_mm[m.supported]) / m.sigma_mm[m.supported])
    assert 0.8 < np.sqrt(np.mean(np.concatenate(z) ** 2)) < 1.25


def step(gap):
    """A box 40 x 30 x 10 mm with a 20 x 30 x 10 mm box on half its top: convex edges and one
    concave edge (x = 0, z = 10) along y."""
    PA, NA, dA = box(gap, (40.0, 30.0, 10.0))
    PB, NB, dB = box(gap, (20.0, 30.0, 10.0))

    def dist(X):
        return np.minimum(dA(X - [0.0, 0.0, 5.0]), dB(X - [-10.0, 0.0, 15.0]))
    P, N = np.vstack([PA + [0.0, 0.0, 5.0], PB + [-10.0, 0.0, 15.0]]), np.vstack([NA, NB])
    keep = (np.abs(dist(P)) < 1e-9) & (dist(P + 0.01 * N) > 0.005)  # not the faces they share
    return P[keep], N[keep], dist


@pytest.mark.parametrize("sd", [0.002, 0.03])
def test_sharp_edges_stay_sharp_convex_and_concave(sd):
    """Vertices within 1 mm of a box's edges (corners aside) and of a step's concave edge:
    fitted as two planes they lie on the true edge (mean |error| below 0.01 mm plus half the
    noise; a quadratic rounds the box's off by 0.05 mm and fills the step's by 0.018-0.055)
    and their sigma holds (RMS z 0.6-1.25); the faces away from the edges are unchanged."""
    rng = np.random.default_rng(3)
    for shape, near_edge in (
            (box, lambda V: np.sort(np.abs(V) - [20.0, 15.0, 10.0], axis=1)[:, 1] > -1.0),
            (step, lambda V: (np.hypot(V[:, 0], V[:, 2] - 10) < 1) & (np.abs(V[:, 1]) < 13))):
        P, nr, dist = shape(1.0)
        Q = P + rng.normal(0, sd, len(P))[:, None] * nr
        cov = sd ** 2 * np.einsum("ki,kj->kij", nr, nr) + 1e-6 * np.eye(3)
        m = build_surface(Q, cov, nr)
        corner = (np.abs(m.vertices_mm) - [20.0, 15.0, 10.0] > -1.5).sum(axis=1) == 3
        near = m.supported & near_edge(m.vertices_mm) & ~corner
        e = dist(m.vertices_mm)
        assert near.sum() > 40
        assert np.abs(e[near]).mean() < 0.01 + sd / 2, shape.__name__
        assert m.params["edge_vertices"] >= near.sum() * 0.8
        assert 0.6 < np.sqrt(np.mean((e[near] / m.sigma_mm[near]) ** 2)) < 1.25
        far = m.supported & ~near_edge(m.vertices_mm)
        assert np.abs(e[far]).mean() < 0.005 + sd / 2


def test_a_noisy_smooth_surface_gets_no_false_edge():
    """A can's side (radius 33 mm) from a fly scan: half the points precise, half smeared along
    the travel and noisy (the demo's soda can, where two planes once took 34 vertices off by
    0.4 mm): the quadratic does not misfit it, so no vertex is put on two planes."""
    for seed in range(4):
        rng = np.random.default_rng(seed)
        P, nr, _ = cylinder(1.5, R=33.0, H=12.0, top=False)
        side = np.abs(nr[:, 2]) < 0.5
        P, nr = P[side], nr[side]
        sd = np.where(rng.random(len(P)) < 0.5, 0.05, 0.4)
        travel = 1.5 * unit(unit(np.cross([0.0, 0.0, 1.0], nr)) + 0.5 * nr)
        smear = rng.uniform(-0.5, 0.5, len(P))[:, None] * travel * (sd[:, None] > 0.1)
        Q = P + rng.normal(0, 1, len(P))[:, None] * sd[:, None] * nr + smear
        cov = np.einsum("k,ki,kj->kij", sd ** 2, nr, nr) + 1e-4 * np.eye(3)
        assert build_surface(Q, cov, nr).params["edge_vertices"] == 0, seed


def test_the_spots_footprint_counts_across_the_travel_not_along_it():
    """A fly waveform's shots move along the travel: a surface tilted along it smears (the
    travel term), one tilted across it shows every shot the same footprint, whose error the
    shots cannot average: (FOOTPRINT_K * spot * sin(tilt))^2 along the normal. A point that
    stood still (step and shoot) gets none (its neighbours see other footprints)."""
    from dmdsm.host.model.surface import FOOTPRINT_K, footprint_var

    a = np.radians(50.0)
    view = np.tile([0.0, 1.0, 0.0], (4, 1))                   # the beam looks along -y
    normals = np.array([[0.0, np.cos(a), np.sin(a)],          # tilted up: across X travel
                        [np.sin(a), np.cos(a), 0.0],          # tilted sideways: along it
                        [0.0, np.cos(a), np.sin(a)],          # tilted up, stood still
                        [0.0, 1.0, 0.0]])                     # head on
    travel = np.zeros((4, 3, 3))
    travel[[0, 1, 3], 0, 0] = 2.0 ** 2 / 12                    # 2 mm along X
    var = footprint_var(np.full(4, 0.25), normals, view, travel)
    full = (FOOTPRINT_K * 0.25 * np.sin(a)) ** 2
    np.testing.assert_allclose(var, [full, 0.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(footprint_var(np.zeros(4), normals, view, travel), 0.0)
    np.testing.assert_allclose(footprint_var(np.full(4, 0.25), normals, view, None), 0.0)
