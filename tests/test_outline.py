"""The measured outline (host/scan/outline.py): known shapes give their radius where the first
look closed the outline and the bounding cylinder elsewhere; the keep-out turns with the table;
straight moves on all four axes are refused where they pass through it, a turn of the table
that sweeps a corner into the parked sensor included, and cleared where they stay out."""

import time

import numpy as np
import pytest
from hypothesis import event, given, settings
from hypothesis import strategies as st

from dmdsm.host.calibration.geometry import rodrigues
from dmdsm.host.links.safety import KeepOut, UnsafeMove
from dmdsm.host.scan.outline import (
    Outline,
    OutlineKeepOut,
    check_moves,
    outline_from_points,
)
from dmdsm.host.scan.reconstruct import object_points, table_frame
from dmdsm.marlin_patch import load_machine

X_R = np.array([235.21, 288.17, 0.0])
N = np.array([-0.0007, 0.0022, 0.9999]) / np.linalg.norm([-0.0007, 0.0022, 0.9999])
V = np.array([0.0656, 0.9955, -0.0678]) / np.linalg.norm([0.0656, 0.9955, -0.0678])
LIMITS = load_machine()
B = table_frame(N)
H = 40.0          # object height (mm)
R_BOUND = 25.0    # the plan's bounding cylinder


def to_stage(P, theta_deg):
    """Stage positions of object-frame points P (k, 3) with the table at theta_deg: the
    inverse of reconstruct.object_points."""
    P = np.atleast_2d(P)
    th = np.broadcast_to(np.asarray(theta_deg, float), (len(P),))
    return np.array([X_R + rodrigues(N, np.radians(t)) @ (B @ p) for p, t in zip(P, th)])


def cylinder_points(r=20.0, n=20_000, z=(0.0, H), seed=0):
    rng = np.random.default_rng(seed)
    phi = rng.uniform(0, 2 * np.pi, n)
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), rng.uniform(*z, n)])


BOX = (15.0, 10.0, np.radians(25.0))  # half sizes (mm) and yaw of a 30 x 20 box


def box_radius(phi_rad):
    """Radius of the rotated 30 x 20 box's side along object-frame azimuths."""
    hx, hy, yaw = BOX
    a = np.asarray(phi_rad) - yaw
    with np.errstate(divide="ignore"):
        return np.minimum(hx / np.abs(np.cos(a)), hy / np.abs(np.sin(a)))


def box_points(n=40_000, seed=1):
    """Points on the sides of the box (perimeter uniformly, z uniformly in 0..H)."""
    hx, hy, yaw = BOX
    rng = np.random.default_rng(seed)
    s = rng.uniform(0, 4 * (hx + hy), n)
    w, h = 2 * hx, 2 * hy
    u = np.select([s < w, s < w + h, s < 2 * w + h],
                  [np.column_stack([s - hx, -hy + 0 * s]).T,
                   np.column_stack([hx + 0 * s, s - w - hy]).T,
                   np.column_stack([hx - (s - w - h), hy + 0 * s]).T],
                  np.column_stack([-hx + 0 * s, hy - (s - 2 * w - h)]).T)
    c, si = np.cos(yaw), np.sin(yaw)
    x, y = c * u[0] - si * u[1], si * u[0] + c * u[1]
    return np.column_stack([x, y, rng.uniform(0, H, n)])


def bottle_radius(z):
    """A bottle: body 12 mm up to z 15, shoulder down to a 6 mm neck at z 25, neck to 40."""
    return np.interp(z, [0, 15, 25, 40], [12, 12, 6, 6])


def bottle_points(n=40_000, seed=2):
    rng = np.random.default_rng(seed)
    z = rng.uniform(0, H, n)
    phi = rng.uniform(0, 2 * np.pi, n)
    r = bottle_radius(z)
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def cell_truth(o, radius_of):
    """(nphi, nz) true outermost radius over each cell: radius_of(phi_rad, z) maximised on a
    fine grid inside the cell."""
    nphi, nz = o.r_mm.shape
    f = np.linspace(0, 1, 41)
    truth = np.empty((nphi, nz))
    for i in range(nphi):
        phi = np.radians((i + f) * o.phi_step_deg)
        for j in range(nz):
            z = o.z_edges_mm[j] + f * (o.z_edges_mm[j + 1] - o.z_edges_mm[j])
            truth[i, j] = radius_of(phi[:, None], z[None, :]).max()
    return truth


@pytest.mark.parametrize("shape", ["cylinder", "box", "bottle"])
def test_outline_of_a_known_shape_has_its_radius_in_closed_cells(shape):
    points, radius_of = {
        "cylinder": (cylinder_points(), lambda p, z: 20.0 + 0 * p * z),
        "box": (box_points(), lambda p, z: box_radius(p) + 0 * z),
        "bottle": (bottle_points(), lambda p, z: bottle_radius(z) + 0 * p),
    }[shape]
    o = outline_from_points(points, R_BOUND, H)
    assert o.r_mm.shape == (72, 20) and o.z_edges_mm[0] == 0 and o.z_edges_mm[-1] >= H
    closed = o.closed()
    assert closed.all()  # dense points all round: every cell measured
    err = np.abs(o.r_mm - cell_truth(o, radius_of))
    assert err.max() < 0.5, err.max()
    # the keep-out radius is never below the surface inside the cell
    i, j = np.meshgrid(np.arange(72), np.arange(20), indexing="ij")
    phi = (i + 0.5) * 5.0
    z = 0.5 * (o.z_edges_mm[j] + o.z_edges_mm[j + 1])
    assert np.all(o.keep_radius_mm(phi, z) >= radius_of(np.radians(phi), z) - 0.5)
    s = o.surface_points()
    assert s.shape == (closed.sum(), 3)
    assert np.allclose(np.hypot(s[:, 0], s[:, 1]), o.r_mm[closed])


def test_noise_and_isolated_outliers_do_not_move_the_outline():
    rng = np.random.default_rng(3)
    P = cylinder_points(seed=4)
    P[:, :2] *= (1 + rng.normal(0, 0.1, len(P)) / 20)[:, None]   # 0.1 mm radial noise
    stray = cylinder_points(r=23.0, n=30, seed=5)                  # echoes 3 mm out, alone
    far = np.array([[0.0, 40.0, 10.0], [5.0, 5.0, 60.0]])          # outside the bound: ignored
    o = outline_from_points(np.vstack([P, stray, far]), R_BOUND, H)
    assert np.all(np.abs(o.r_mm - 20.0) < 0.5)


def test_unseen_cells_are_open_and_fall_back_to_the_bounding_radius():
    P = cylinder_points(z=(0.0, 20.0))          # the first look saw only the lower half
    phi = np.degrees(np.arctan2(P[:, 1], P[:, 0])) % 360
    P = P[~((phi >= 90) & (phi < 105)) & ~((phi >= 200) & (phi < 210))]
    o = outline_from_points(P, R_BOUND, H, max_gap=2)
    closed = o.closed()
    assert closed[:, :10][np.r_[0:18, 21:72]].all()
    assert not closed[:, 10:].any()               # above 20 mm nothing was seen
    assert not closed[18:21, :].any()             # a 3-bin (15 deg) gap stays open
    assert closed[40:42, :10].all()               # a 2-bin gap is closed between its sides
    assert np.isnan(o.r_mm[40:42]).all()          # ... filled, not measured
    z = np.full(4, 10.0)
    assert np.allclose(o.keep_radius_mm(np.array([92.5, 102.0, 202.5, 300.0]), z),
                       [R_BOUND, R_BOUND, 20.0, 20.0], atol=0.3)
    assert np.all(o.keep_radius_mm(np.array([0.0, 300.0]), np.array([30.0, 39.9])) == R_BOUND)
    assert np.all(o.keep_radius_mm(np.array([0.0, 300.0]), np.array([40.5, 100.0])) == 0.0)
    assert len(o.surface_points()) == closed.sum()
    empty = outline_from_points(np.zeros((0, 3)), R_BOUND, H)
    assert not empty.closed().any() and len(empty.surface_points()) == 0


def test_outline_rejects_a_step_that_does_not_divide_a_turn():
    with pytest.raises(ValueError, match="divide 360"):
        outline_from_points(cylinder_points(n=100), R_BOUND, H, phi_step_deg=7.0)


CYL = outline_from_points(cylinder_points(), R_BOUND, H)
BOXO = outline_from_points(box_points(), R_BOUND, H)


@pytest.mark.parametrize("theta", [0.0, 37.0, 90.0, 200.5, 315.0])
def test_the_keep_out_turns_with_the_table(theta):
    rng = np.random.default_rng(int(theta))
    zone = OutlineKeepOut(CYL, X_R, N, margin_mm=2.0)
    phi = rng.uniform(0, 2 * np.pi, 300)
    z = rng.uniform(0.5, H - 0.5, 300)
    for dr, want in ((0.3, False), (-0.3, True)):
        P = np.column_stack([(22 + dr) * np.cos(phi), (22 + dr) * np.sin(phi), z])
        S = to_stage(P, theta)
        assert np.allclose(object_points(S, np.full(len(S), theta), N, X_R), P)
        assert np.all(zone.inside(S, theta) == want)
    above = to_stage([[0, 0, H + 2.3], [10, 0, H + 1.7], [0, 0, -2.3], [0, 10, -1.7]], theta)
    assert zone.inside(above, theta).tolist() == [False, True, False, True]

    box = OutlineKeepOut(BOXO, X_R, N, margin_mm=2.0)
    P = np.column_stack([(box_radius(phi) + 1.7) * np.cos(phi),
                         (box_radius(phi) + 1.7) * np.sin(phi), z])
    assert box.inside(to_stage(P, theta), theta).all()   # never cut, corners included
    faces = BOX[2] + np.radians([0, 90, 180, 270])       # face centres: the radius is flat
    r = box_radius(faces) + 2.3
    P = np.column_stack([r * np.cos(faces), r * np.sin(faces), np.full(4, 20.0)])
    assert not box.inside(to_stage(P, theta), theta).any()


@given(st.lists(st.tuples(st.floats(-60, 60), st.floats(-60, 60), st.floats(-10, 60),
                          st.floats(0, 360)), min_size=1, max_size=20))
def test_inside_is_object_points_then_the_keep_radius(rows):
    rows = np.array(rows)
    S = X_R + rows[:, :3]
    zone = OutlineKeepOut(BOXO, X_R, N)
    P = object_points(S, rows[:, 3], N, X_R)
    keep = BOXO.keep_radius_mm(np.degrees(np.arctan2(P[:, 1], P[:, 0])),
                               np.clip(P[:, 2], 0, H))
    r = np.hypot(P[:, 0], P[:, 1])
    want = (r < keep + 2) & (P[:, 2] > -2) & (P[:, 2] < H + 2)
    sure = np.abs(r - keep - 2) > 1e-6   # not on the boundary itself
    assert np.array_equal(zone.inside(S, rows[:, 3])[sure], want[sure])


# the hypothesis check: an outline of 10 mm with a fin of 20 mm between azimuths 50 and 70
# (grown by its neighbour cells to 45..75), so that the table's angle matters; and the turntable
_R = np.full((72, 20), 10.0)
_R[10:14] = 20.0
FIN = Outline(5.0, np.arange(21) * 2.0, _R, R_BOUND, H)
ZONES = [OutlineKeepOut(FIN, X_R, N, 2.0), KeepOut(X_R - 1000 * N, N, 60.0, 1000.0)]
E1, E2 = np.radians(45.0), np.radians(75.0)


def _segment_distance(x, y, a):
    """2D distance from points to the segment from the origin to 22 mm along azimuth a."""
    t = np.clip(x * np.cos(a) + y * np.sin(a), 0.0, 22.0)
    return np.hypot(x - t * np.cos(a), y - t * np.sin(a))


def turned_back(S, theta):
    """object_points (B^T R_n(-theta) (S - X_R)) for many angles at once: Rodrigues' formula
    on the vectors, R_n(a) u = u cos a + (n x u) sin a + n (n . u)(1 - cos a)."""
    u = S - X_R
    a = -np.radians(theta)[:, None]
    w = u * np.cos(a) + np.cross(N, u) * np.sin(a) + np.outer(u @ N, N) * (1 - np.cos(a))
    return w @ B


def test_turned_back_is_object_points():
    rng = np.random.default_rng(8)
    S = X_R + rng.uniform(-50, 50, (200, 3))
    theta = rng.uniform(-400, 400, 200)
    assert np.allclose(turned_back(S, theta), object_points(S, theta, N, X_R))


def depth_and_clearance(S, theta):
    """Per sample: how deep inside a zone (mm, > 0 inside), and how far outside every zone,
    exact for the zones' convex parts: the core cylinder r < 12, the fin's pie slice r < 22
    from 45 to 75 deg (both for -2 < z < H + 2) and the turntable (r < 62, z < 2)."""
    P = turned_back(S, theta)
    x, y, z = P.T
    r = np.hypot(x, y)
    phi = np.arctan2(y, x) % (2 * np.pi)
    dz_in = np.minimum(z + 2.0, H + 2.0 - z)
    dz_out = np.maximum(np.maximum(-2.0 - z, z - H - 2.0), 0)
    deep_core = np.minimum(12.0 - r, dz_in)
    in_wedge = (phi >= E1) & (phi <= E2)
    deep_fin = np.where(in_wedge, np.minimum.reduce([22.0 - r, r * np.sin(phi - E1),
                                                     r * np.sin(E2 - phi), dz_in]), -1.0)
    d2_fin = np.where(in_wedge, np.maximum(r - 22.0, 0),
                      np.minimum(_segment_distance(x, y, E1), _segment_distance(x, y, E2)))
    out_core = np.hypot(np.maximum(r - 12.0, 0), dz_out)
    out_fin = np.hypot(d2_fin, dz_out)
    deep_t = np.minimum(62.0 - r, 2.0 - z)
    out_t = np.hypot(np.maximum(r - 62.0, 0), np.maximum(z - 2.0, 0))
    return (np.maximum.reduce([deep_core, deep_fin, deep_t]),
            np.minimum.reduce([out_core, out_fin, out_t]))


def test_the_fin_keep_out_is_what_the_checks_assume():
    rng = np.random.default_rng(7)
    S = X_R + rng.uniform([-30, -30, -4], [30, 30, 46], (20_000, 3))
    theta = rng.uniform(0, 360, len(S))
    deep, clear = depth_and_clearance(S, theta)
    inside = ZONES[0].inside(S, theta) | ZONES[1].inside(S)
    assert inside[deep > 1e-6].all() and not inside[clear > 1e-6].any()
    assert (deep > 0).sum() > 1000 and (clear > 0).sum() > 1000


move = st.tuples(st.floats(-35, 35), st.floats(-35, 35), st.floats(0, 50), st.floats(-30, 400))


@settings(max_examples=300)
@given(st.lists(move, min_size=2, max_size=5))
def test_random_multi_axis_moves_are_refused_exactly_when_they_enter(path):
    pts = np.array(path)
    pts[:, :3] += X_R
    labels = [f"point {i}" for i in range(len(pts))]
    t = np.linspace(0, 1, 1000)[:, None]
    deep, clear = [], []                  # per label: the first point, then each move into one
    for a, b in zip(np.vstack([pts[:1], pts[:-1]]), pts):
        X = a + t * (b - a)               # densely sampled: all axes together
        d, c = depth_and_clearance(X[:, :3], X[:, 3])
        deep.append(d.max())
        clear.append(c.min())
    try:
        check_moves([tuple(p) for p in pts], labels, None, LIMITS, ZONES)
        refused = None
    except UnsafeMove as e:
        refused = str(e)
    event("refused" if refused else "cleared")
    if max(deep) > 0.3:
        assert refused is not None
    if min(clear) > 0.5:
        assert refused is None, refused
    if refused is not None:               # the first move that enters is named
        j = int(refused.split(": point ")[1].split()[0])
        assert deep[j] > -0.5
        assert all(d <= 0.3 for d in deep[:j])


def test_turning_the_table_sweeps_a_corner_into_the_parked_sensor():
    zone = OutlineKeepOut(outline_from_points(box_points(), R_BOUND, H), X_R, N)
    # parked 18.5 mm out along the box's short face at A 0 (face at 15 mm): clear by 1.5 mm
    face = BOX[2]
    p = np.array([18.5 * np.cos(face), 18.5 * np.sin(face), 20.0])
    S = to_stage(p, 0.0)[0]
    assert not zone.inside(S, 0.0)[0] and not zone.inside(S, 90.0)[0]  # long face at A 90
    check_moves([(*S, 0.0)], ["park"], None, LIMITS, [zone])
    check_moves([(*S, 90.0)], ["park"], None, LIMITS, [zone])
    with pytest.raises(UnsafeMove, match=r"turn A90 .*measured outline \(\+2 mm\)"):
        check_moves([(*S, 90.0)], ["turn A90"], (*S, 0.0), LIMITS, [zone])
    # further out the corner (18 mm) passes by
    q = to_stage(np.array([21.0 * np.cos(face), 21.0 * np.sin(face), 20.0]), 0.0)[0]
    check_moves([(*q, 90.0), (*q, 360.0)], ["turn", "turn back"], (*q, 0.0), LIMITS, [zone])


def test_the_refusal_is_one_line_naming_the_label_and_where():
    zone = OutlineKeepOut(CYL, X_R, N)
    a = X_R + np.array([-40.0, 0, 20])
    b = X_R + np.array([40.0, 0, 20])
    with pytest.raises(UnsafeMove) as e:
        check_moves([(*a, 0.0), (*b, 0.0)], ["line 3\ncolumn 7", "across"], None, LIMITS,
                    [zone])
    msg = str(e.value)
    assert "\n" not in msg
    assert msg.startswith("scan plan refused before moving: across (X")
    assert " A0)" in msg and "measured outline (+2 mm) near X" in msg and "at A0.0 deg" in msg
    near = float(msg.split(" near X")[1].split()[0])
    assert abs(near - (X_R[0] - 22)) < 0.5           # where the move first enters
    with pytest.raises(UnsafeMove, match="^scan plan refused before moving: line 3 column 7 "):
        check_moves([(*(X_R + [0, 0, 10]), 0.0)], ["line 3\ncolumn 7"], None, LIMITS, [zone])
    with pytest.raises(UnsafeMove, match=r"^scan plan refused before moving: far \(X500 .*"
                                         r"X500.* outside the machine envelope"):
        check_moves([(*a, 0.0), (500.0, 100.0, 20.0, 0.0)], ["near", "far"], None, LIMITS, [])
    with pytest.raises(UnsafeMove, match="far .*not a position"):
        check_moves([(*a, 0.0), (*a[:2], np.nan, 0.0)], ["near", "far"], None, LIMITS, [])
    cyl = KeepOut(X_R, N, 20.0, H)
    with pytest.raises(UnsafeMove, match=r"^scan plan refused before moving: across .*keep-out "
                                         r"cylinder \(radius 20 \+ 2 mm, height 40 mm\)"):
        check_moves([(*b, 0.0)], ["across"], (*a, 0.0), LIMITS, [cyl])
    check_moves([(*b, 0.0)], ["clear"], (*a, 0.0), LIMITS, [KeepOut(X_R, N, 0.0, H)])
    with pytest.raises(ValueError, match="labels"):
        check_moves([(*a, 0.0)], [], None, LIMITS, [zone])


def test_a_start_inside_and_the_approach_are_checked():
    zone = OutlineKeepOut(CYL, X_R, N)
    front = X_R + np.array([0.0, -40, 20])
    inside = X_R + np.array([0.0, -21, 20])
    check_moves([(*front, 0.0)], ["first"], None, LIMITS, [zone])
    with pytest.raises(UnsafeMove, match="first"):
        check_moves([(*front, 0.0)], ["first"], (*inside, 0.0), LIMITS, [zone])


def test_ten_thousand_moves_check_in_well_under_two_seconds():
    # a bounding cylinder of 60 mm around a 20 mm outline: every sample needs the outline
    o = outline_from_points(cylinder_points(), 60.0, H)
    zones = [OutlineKeepOut(o, X_R, N), KeepOut(X_R - 1000 * N, N, 60.0, 1000.0)]
    k = 10_000
    rng = np.random.default_rng(6)
    ang = np.radians(np.cumsum(rng.uniform(15, 25, k)))      # ~10 mm apart at r 30
    r = 30.0 + rng.uniform(-1, 1, k)
    targets = [(X_R[0] + r[i] * np.cos(ang[i]), X_R[1] + r[i] * np.sin(ang[i]),
                20.0 + rng.uniform(-5, 5), 0.0) for i in range(k)]
    labels = [f"point {i}" for i in range(k)]
    t0 = time.process_time()  # CPU seconds: a loaded machine stretches the wall clock
    check_moves(targets, labels, None, LIMITS, zones)
    assert time.process_time() - t0 < 2.0
    turns = [(*p[:3], (i * 7.0) % 360) for i, p in enumerate(targets)]  # A moves too
    t0 = time.process_time()
    check_moves(turns, labels, None, LIMITS, zones)
    assert time.process_time() - t0 < 2.0


def test_outline_dataclass_takes_the_documented_fields():
    o = Outline(5.0, np.arange(21) * 2.0, np.full((72, 20), 20.0), R_BOUND, H)
    assert o.closed().all() and o.max_gap == 2
    assert np.allclose(o.keep_radius_mm(np.array([0.0, 359.9]), np.array([0.0, 39.0])), 20.0)
