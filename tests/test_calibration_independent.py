"""The calibration on rig data the emulator did not make (issue 30, items 3-5 and the 10^6-row
file): tests/independent_rig.py's own filament, spot, raster and noise model, through the rig
CSV. The reported stds hold (RMS z near 1 at every noise level), a negative amplitude is a
weak reading, unit vectors' errors are angles, and a huge file is refused in bounded memory."""

import json
import subprocess
import sys
import time
import tomllib
import tracemalloc

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from independent_rig import NOISE_LEVELS, Rig, generate, paper_truth, random_truth, write_csv

from dmdsm.host.calibration.center_points import (
    MAX_GROUP_POINTS,
    center_points,
    front_depth_mm,
    raster_centroid_cov,
)
from dmdsm.host.calibration.result import load_calibration, result_dict, write_result
from dmdsm.host.calibration.rig_file import COLUMNS, MAX_ROWS, read_raw
from dmdsm.host.calibration.solver import CalibrationError, solve, tangent_errors

COORDS = ("v t1", "v t2", "n t1", "n t2", "X_R x", "X_R y")


def z_values(seed: int, noise: str, tmp_path) -> np.ndarray:
    """(estimate - truth) / reported std over COORDS for one independent data set, read from
    its CSV as `calibrate --from-data` does (the table's reading noise given, --table-std)."""
    truth = random_truth(np.random.default_rng([seed, 1])) if seed % 3 else paper_truth()
    raw = read_raw(write_csv(generate(truth, seed, noise), tmp_path / f"rig{seed}.csv"))
    r = solve(center_points(raw, sigma_theta_deg=NOISE_LEVELS[noise].table_deg))
    e, s = [], []
    for name in ("v", "n"):
        err, sd = tangent_errors(r, name, truth[name])
        e += list(err)
        s += list(sd)
    e += list((r.X_R - truth["X_R"])[:2])
    s += list(r.std["X_R"][:2])
    return np.array(e) / np.array(s)


@pytest.mark.parametrize("noise, sets", [("none", 120), ("paper", 30), ("large", 30)])
def test_reported_stds_hold_on_independent_data(noise, sets, tmp_path):
    """RMS z per first-order coordinate over the data sets (random truths and Table I): 1
    when the stds hold. With 30 sets the RMS of z scatters by about 1/sqrt(60) = 0.13 (more
    with heavy tails), so 0.7-1.4 is ~3 sigma around 1 (bench/calibration_independent.py
    holds 0.8-1.25 at 60 sets). Before the fix: v 0.47-0.63, n 0.21-0.63 with almost no
    noise (the raster model's misfit taken for amplitude noise, the raw depths' spread
    about their mean, the scale pulled to the model's, the HC3 widening) and X_R y 2.6 (a
    fixed table std). With almost no noise, 120 sets: a tip center point's depth error
    that follows its lateral one (the face's slope) was not in its covariance, and v's z
    reached 6.7 (RMS 1.56 over these sets; 2.8 and 0.94 with it)."""
    z = np.array([z_values(seed, noise, tmp_path) for seed in range(sets)])
    rms = np.sqrt(np.mean(z ** 2, axis=0))
    assert ((rms > 0.7) & (rms < 1.4)).all(), dict(zip(COORDS, np.round(rms, 2)))
    assert np.abs(z).max() < 4.5, dict(zip(COORDS, np.round(np.abs(z).max(axis=0), 1)))


def test_a_tip_center_point_s_depth_follows_the_face_it_lies_on(tmp_path):
    """The tip's face is a few degrees off the beam: where the raster's centroid misses its
    centre, the center point's depth misses with the face's slope. center_points measures
    that slope (tip_grad) from the raw depths, and the covariance then says the point is
    exact across the face (along its normal), not along the stage axis the raster does not
    step."""
    from dmdsm.host.calibration import mle
    from dmdsm.host.calibration.solver import mle_problem, svd_estimate

    truth, hid = paper_truth(), {}
    raw = read_raw(write_csv(generate(truth, 3, "none", hidden=hid), tmp_path / "rig.csv"))
    data = center_points(raw)
    v, nf = truth["v"], hid["tip_axis"]
    slope = -nf / (v @ nf)  # the face's depth change per mm of stage (X, Z: the raster)
    assert data.tip_grad is not None
    # within 0.02: near the face's rim the depth is that of the lit part (the spot is as
    # wide as the face), which lies nearer its centre, so the raw depths' slope is ~15 %
    # flatter than the face's (-0.083 / 0.079 against -0.096 / 0.087 here)
    assert np.allclose(data.tip_grad[:, [0, 2]], slope[[0, 2]], atol=0.02), \
        (data.tip_grad, slope)
    est = svd_estimate(data)
    pb = mle_problem(data, est.frames, est.thetas)
    gauge, p = mle.gauge_fix(v, truth["n"], truth["X_R"], hid["tip"], est.lines, est.thetas)
    _, cov = mle._tip(pb, gauge.unpack(p, len(est.frames)), 1.0)
    across = np.einsum("i,kij,j->k", nf, cov, nf)        # along the face's normal
    lateral = np.einsum("i,kij,j->k", [1.0, 0, 0], cov, [1.0, 0, 0])
    assert (np.sqrt(across) < 0.05 * np.sqrt(lateral)).all(), (across, lateral)
    # and the center points do lie on the face: their error along its normal is that small
    err = (data.tip_S + data.tip_d[:, None] * v - hid["tip"]) @ nf
    assert np.abs(err).max() < 0.05 * np.sqrt(lateral).min(), err


def test_center_points_depth_noise_is_not_the_targets_shape(tmp_path):
    """With almost no noise a tip face a few degrees off the beam makes the raw depths
    differ by ~0.01 mm across the raster; the center point's depth is still right to
    0.0001 mm, and its declared std must say so (it said 0.003 mm: sigma_P / n about the
    mean)."""
    raw = read_raw(write_csv(generate(paper_truth(), 3, "none"), tmp_path / "rig.csv"))
    data = center_points(raw)
    assert np.sqrt(data.tip_var_d).max() < 0.001, np.sqrt(data.tip_var_d)


def test_a_negative_amplitude_is_a_weak_reading(tmp_path):
    """Additive noise makes a weak or empty reading negative: below any threshold, not a
    broken file; read as 0 and said once with the count."""
    rows = generate(paper_truth(), 5, "paper")
    n_neg = sum(r["amplitude"] < 0 for r in rows)
    assert n_neg > 10
    path = write_csv(rows, tmp_path / "rig.csv")
    notes: list[str] = []
    raw = read_raw(path, notes)
    assert (raw["amplitude"] >= 0).all() and len(notes) == 1 and f"{n_neg} raw point" in notes[0]
    out = tmp_path / "cal.toml"
    r = subprocess.run([sys.executable, "-m", "dmdsm.host", "calibrate", "--from-data",
                        str(path), "-o", str(out), "--json"], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if "negative amplitude" in ln]
    assert len(lines) == 1 and f"{n_neg} raw point" in lines[0], r.stderr
    json.loads(r.stdout)


def test_an_infinite_amplitude_is_still_refused(tmp_path):
    rows = generate(paper_truth(), 5, "paper")
    rows[7]["amplitude"] = float("inf")
    with pytest.raises(CalibrationError, match="row 8 .*amplitude must be a finite number"):
        read_raw(write_csv(rows, tmp_path / "rig.csv"))



def test_the_joint_covariance_is_written_read_back_and_checked(tmp_path):
    """calibration.toml carries the solve's 9 x 9 covariance of v, n, X_R (models propagate
    it: the rig's X_R y and n y are one error, correlated about -0.9); it reads back to 1e-8;
    a file without it still loads (the stds are used); a broken one is one line to fix."""
    from dmdsm.host.calibration.solver import CalibrationError

    raw = read_raw(write_csv(generate(paper_truth(), 3, "paper"), tmp_path / "rig.csv"))
    r = solve(center_points(raw))
    write_result(r, tmp_path / "cal.toml", str(tmp_path / "rig.csv"))
    cal, text = load_calibration(tmp_path / "cal.toml")
    c = np.array(cal["cov"])
    assert np.allclose(c, r.cov, rtol=1e-8, atol=1e-8 * np.abs(r.cov).max())
    sd = np.sqrt(np.diag(c))
    assert np.allclose(sd[6:8], cal["X_R_std"][:2], rtol=1e-6)
    assert c[7, 4] / (sd[7] * sd[4]) < -0.5   # the axis, not X_R alone, is what the rig fixes
    no_cov = "\n".join(ln for ln in text.splitlines() if not ln.startswith("cov"))
    (tmp_path / "old.toml").write_text(no_cov)
    assert "cov" not in load_calibration(tmp_path / "old.toml")[0]
    for bad in ("cov = [[1, 2], [3, 4]]", "cov = \"none\"",
                "cov = [" + ", ".join(["[" + ", ".join(["nan"] * 9) + "]"] * 9) + "]"):
        (tmp_path / "bad.toml").write_text(no_cov + "\n" + bad + "\n")
        with pytest.raises(CalibrationError, match="cov must be the symmetric 9 x 9") as e:
            load_calibration(tmp_path / "bad.toml")
        assert "\n" not in str(e.value)


def test_unit_vectors_errors_are_angles_in_json_toml_and_the_demo_table(tmp_path):
    """v and n carry an angular std (deg), the root of the trace of their tangent-plane
    covariance; the demo's table shows their angle to the truth against it, X_R in the
    table plane; an old calibration.toml without the angular stds still loads."""
    from dmdsm.host.demo.session import _rig_rows

    truth = paper_truth()
    raw = read_raw(write_csv(generate(truth, 2, "paper"), tmp_path / "rig.csv"))
    r = solve(center_points(raw))
    d = result_dict(r)
    for k in ("v", "n"):
        _, sd = tangent_errors(r, k, truth[k])
        assert d["angle_std_deg"][k] == pytest.approx(np.degrees(np.hypot(*sd)))
    write_result(r, tmp_path / "cal.toml", str(tmp_path / "rig.csv"))
    cal, text = load_calibration(tmp_path / "cal.toml")
    assert cal["n_angle_std_deg"] == pytest.approx(r.angle_std_deg["n"], rel=1e-5)
    old = "\n".join(ln for ln in text.splitlines() if "angle_std" not in ln)
    (tmp_path / "old.toml").write_text(old)
    assert "n_angle_std_deg" not in load_calibration(tmp_path / "old.toml")[0]
    ang = {k: float(np.degrees(np.arccos(np.clip(r.__dict__[k] @ truth[k], -1, 1))))
           for k in ("v", "n")}
    rows = _rig_rows(json.loads(json.dumps(d)), truth, ang)
    assert [row[0] for row in rows] == ["v", "n", "X_R (x, y mm)"]
    for row, k in zip(rows, ("v", "n")):
        assert "deg" in row[1] and ";" not in row[4]  # one angle, not three components
        assert float(row[4]) == pytest.approx(ang[k] / r.angle_std_deg[k], abs=0.05)
    assert len(rows[2][4].split(";")) == 2  # x and y; z = 0 is the gauge


def test_calibrate_prints_angular_stds(tmp_path):
    path = write_csv(generate(paper_truth(), 4, "paper"), tmp_path / "rig.csv")
    r = subprocess.run([sys.executable, "-m", "dmdsm.host", "calibrate", "--from-data",
                        str(path), "-o", str(tmp_path / "cal.toml"), "--table-std", "0.02"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.count(" deg") >= 2 and "gauge" in r.stdout, r.stdout
    cal = tomllib.loads((tmp_path / "cal.toml").read_text())["calibration"]
    assert cal["v_angle_std_deg"] > 0 and cal["n_angle_std_deg"] > 0


def test_a_huge_csv_is_refused_early_in_bounded_memory(tmp_path):
    """10^6 rows once asked for 34.8 GiB after 15 s: now one line naming the limit, within
    a second or two and a few MB, read no further than MAX_ROWS."""
    path = tmp_path / "huge.csv"
    line = "tip,0,0,0,235.0,266.0,20.0,6.5,1.0,oa\n"
    path.write_text(",".join(COLUMNS) + "\n" + line * 1_000_000)
    tracemalloc.start()
    t0 = time.perf_counter()
    with pytest.raises(CalibrationError, match=f"more than {MAX_ROWS} raw points") as e:
        read_raw(path)
    elapsed = time.perf_counter() - t0
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert "\n" not in str(e.value) and "split" in str(e.value)
    assert elapsed < 10 and peak < 100e6, (elapsed, peak)
    r = subprocess.run([sys.executable, "-m", "dmdsm.host", "calibrate", "--from-data",
                        str(path), "-o", str(tmp_path / "cal.toml")], capture_output=True,
                       text=True, timeout=60)
    assert r.returncode != 0 and f"more than {MAX_ROWS}" in r.stderr
    assert "Traceback" not in r.stderr and not (tmp_path / "cal.toml").exists()


def test_a_huge_frame_is_refused_before_the_raster_model():
    n = MAX_GROUP_POINTS + 1
    raw = {"step": np.array(["tip"] * n), "modality": np.array(["oa"] * n),
           "frame": np.zeros(n), "line": np.zeros(n), "theta_deg": np.zeros(n),
           "sx_mm": np.linspace(0, 1, n), "sy_mm": np.zeros(n), "sz_mm": np.zeros(n),
           "d_mm": np.full(n, 6.0), "amplitude": np.ones(n)}
    with pytest.raises(CalibrationError, match=f"more than the {MAX_GROUP_POINTS}"):
        center_points(raw)


def test_the_raster_model_runs_in_bounded_memory():
    """The largest frame taken (MAX_GROUP_POINTS points) costs tens of MB, not the
    draws x points x spot samples array at once (0.8 GB here; 34.8 GiB for a 10^6-row
    file)."""
    x = np.linspace(-1.5, 1.5, MAX_GROUP_POINTS)[:, None]
    amp = np.exp(-x[:, 0] ** 2 / 0.05)
    tracemalloc.start()
    Q = raster_centroid_cov(x, amp, 0.5, "strip", 0.25, 0.25, count=30.0)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert Q.shape == (1, 1) and np.isfinite(Q).all()
    assert peak < 250e6, peak


def test_independent_generator_is_its_own():
    """The generator imports nothing of the emulator or the host (its independence)."""
    import ast
    from pathlib import Path

    import independent_rig

    tree = ast.parse(Path(independent_rig.__file__).read_text())
    names = [a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names]
    names += [n.module or "" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)]
    assert not [m for m in names if m.startswith(("dmdsm", "hil_sim", "host"))], names
    rows = generate(paper_truth(), 0, "paper", rig=Rig(radius_mm=0.4))
    assert {r["step"] for r in rows} == {"tip", "edge"}


def edge_depth_errors_um(seed: int, tmp_path, radius_mm: float = 0.25
                         ) -> tuple[np.ndarray, np.ndarray]:
    """Each edge center point's distance (um) from the rig's true filament axis along the
    beam (across the axis), the beam's obliqueness (1 / sin beta) applied as solve does,
    and its declared depth std (um); almost no noise."""
    truth, hidden = paper_truth(), {}
    rows = generate(truth, seed, "none", rig=Rig(radius_mm=radius_mm), hidden=hidden)
    data = center_points(read_raw(write_csv(rows, tmp_path / f"rig{seed}.csv")),
                         radius_mm=radius_mm)
    v, err = truth["v"], []
    for S, d, f, front in zip(data.edge_S, data.edge_d, data.edge_frame, data.edge_front_mm):
        P, q = hidden["axes"][int(f)]
        k = 1 / np.linalg.norm(np.cross(q, v))
        w = S + (d + (k - 1) * front) * v - P
        w -= (w @ q) * q
        e = v - (v @ q) * q
        err.append(w @ e / np.linalg.norm(e))
    return np.array(err) * 1e3, np.sqrt(data.edge_var_d) * 1e3


def test_edge_depths_are_moved_onto_the_axis_for_the_spot_the_amplitudes_show(tmp_path):
    """The rig's spot is Gaussian; the amplitudes say so (amp_noise's shape) and the front
    depth is then the Gaussian spot's: the edge center points lie on the true axis to
    ~0.5 um RMS with almost no noise (1.2 um with the uniform disk's front depth)."""
    err = np.concatenate([edge_depth_errors_um(seed, tmp_path)[0] for seed in range(6)])
    assert np.sqrt(np.mean(err ** 2)) < 0.8, np.round(err, 2)


def test_an_edge_centers_declared_depth_std_is_its_noise_not_the_models_misfit(tmp_path):
    """With almost no noise, the edge center points' declared depth std against their true
    error (the thick filament: the front-depth model misses most there): RMS z ~0.6 from
    the second differences along each sweep (sweep_depth_var), where the spread about a
    trend shared by all sweeps declared 2.5x the error (RMS z 0.40: n's tilt along the
    beam then came out ~2x too uncertain)."""
    err, sd = map(np.concatenate, zip(*[edge_depth_errors_um(seed, tmp_path, 0.4)
                                        for seed in range(6)]))
    rms_z = np.sqrt(np.mean((err / sd) ** 2))
    assert 0.5 < rms_z < 1.6, (rms_z, np.round(err, 2), np.round(sd, 2))


@settings(max_examples=30, deadline=None)
@given(offset=st.floats(-0.5, 0.5), radius=st.floats(0.1, 0.5), spot=st.floats(0.05, 0.4))
def test_the_gaussian_front_depth_is_the_mean_over_the_spot_on_the_filament(offset, radius,
                                                                            spot):
    """front_depth_mm(..., "gauss"): the mean of sqrt(r^2 - s^2) over a Gaussian spot
    (sigma = spot radius / 2) where it lands on the filament, by quadrature on a fine grid
    (independent of the function's own sampling), wherever 1 % of the spot or more lands
    on it."""
    s = offset + np.linspace(-6, 6, 200001) * spot / 2
    g = np.exp(-0.5 * ((s - offset) / (spot / 2)) ** 2)
    w = g * (np.abs(s) < radius)
    if w.sum() < 0.01 * g.sum():
        return  # under 1 % of the spot on the filament: no echo to range
    want = (w * np.sqrt(np.clip(radius ** 2 - s ** 2, 0, None))).sum() / w.sum()
    got = front_depth_mm(offset, radius, spot, "gauss")[0]
    assert got == pytest.approx(want, abs=2e-4)
