"""Material classification on a small hil_sim database (seven materials, two objects each):
trains and evaluates end to end, a label shuffle drops to chance, provenance is checked,
one-modality variants, and live prediction through the emulated sensor."""

import json
import shutil

import h5py
import numpy as np
import pytest

from dmdsm.host.classify import materials as classify
from dmdsm.host.classify.materials import (
    WINDOW,
    ClassifyError,
    assemble,
    evaluate_random,
    per_class_accuracy,
)
from dmdsm.host.commands.cli import main
from dmdsm.host.links.stage import StageClient
from dmdsm.host.scan.catalogue import connect
from dmdsm.sim.data.dataset import make_database, true_setup
from dmdsm.sim.physics.objects import bounding_size, household
from dmdsm.sim.physics.scene import TABLE_I_V, TABLE_I_XR
from dmdsm.sim.physics.signals import SensorModel
from dmdsm.sim.servers.emulator import Emulator
from dmdsm.sim.servers.runner import SimConfig

ARTIFICIAL = ("aluminium", "foam", "glass", "paper", "plastic", "steel")
DISTINCT = ("aluminium", "foam", "glass", "paper", "steel")  # the emulator's plastic ~ apple


@pytest.fixture(scope="module")
def db(tmp_path_factory):
    d = tmp_path_factory.mktemp("db")
    make_database(d, points=24, seed=1)
    return d


@pytest.fixture(scope="module")
def model(db, tmp_path_factory):
    path = tmp_path_factory.mktemp("model") / "m.model"
    assert main(["classify", "train", "--db", str(db), "-o", str(path), "--json"]) == 0
    return path


def run(capsys, *args):
    rc = main(list(args))
    out = capsys.readouterr()
    return rc, out.out, out.err


def test_pipeline_trains_and_evaluates_end_to_end(db, tmp_path, capsys):
    rc, out, err = run(capsys, "classify", "evaluate", "--db", str(db), "--classifiers",
                       "minirocket", "--trials", "4", "--out", str(tmp_path), "--json")
    assert rc == 0, err
    res = json.loads(out)
    assert res["objects"] == 14
    acc = res["classifiers"]["minirocket"]
    assert set(acc["random"]) == set(ARTIFICIAL) | {"apple"}
    for m in ARTIFICIAL:  # told apart when each object has been seen
        assert acc["random"][m] >= 0.8, (m, acc)
    for m in DISTINCT:  # ... and on objects never seen
        assert acc["loo"][m] >= 0.8, (m, acc)
    assert (tmp_path / "confusion_minirocket_random.png").stat().st_size > 5000
    cm = np.loadtxt(tmp_path / "confusion_minirocket_loo.csv", delimiter=",")
    assert cm.shape == (7, 7) and cm.sum() > 100
    # the emulator's apple is plastic-like by design: unseen objects of the two are confused
    # with each other, not with the rest
    pair = [sorted(acc["loo"]).index(m) for m in ("apple", "plastic")]
    assert cm[np.ix_(pair, pair)].sum() >= 0.85 * cm[pair].sum()


def test_train_takes_several_databases_each_scan_once(db, tmp_path, capsys):
    """A user who scanned the same objects standing and on fly lines trains on both (the
    demo's campaign does: its auto scans are fly lines); a database given twice counts
    once; an empty one is named in one line."""
    fly = tmp_path / "fly"
    make_database(fly, points=16, seed=7, objects=["soda_can", "foam_block"], fly_mm=4.0)
    out = tmp_path / "m.model"
    rc, text, err = run(capsys, "classify", "train", "--db", str(db), "--db", str(fly),
                        "--db", str(db), "-o", str(out), "--json")
    assert rc == 0, err
    n_db = len(assemble([p for p in (db / "scans").glob("*.h5")]))
    n_fly = len(assemble(list((fly / "scans").glob("*.h5"))))
    assert json.loads(text)["points"] == n_db + n_fly
    empty = tmp_path / "empty"
    connect(empty, create=True).close()
    rc, text, err = run(capsys, "classify", "train", "--db", str(db), "--db", str(empty),
                        "-o", str(tmp_path / "n.model"))
    assert rc != 0 and f"{empty} has no complete scans" in err
    assert len(err.strip().splitlines()) == 1 and not (tmp_path / "n.model").exists()


def test_one_modality_sees_only_its_materials_and_prints_the_table(db, tmp_path, capsys):
    rc, out, err = run(capsys, "classify", "evaluate", "--db", str(db), "--classifiers",
                       "minirocket", "--modality", "oa", "--trials", "2", "--no-loo",
                       "--out", str(tmp_path))
    assert rc == 0, err
    table = out[out.index("true/pred"):].splitlines()
    rows = {line.split()[0]: line.split()[1:] for line in table[1:8]}
    assert rows["glass"] == ["-"] * 7 and rows["steel"] == ["-"] * 7  # no OA on them
    assert float(rows["foam"][2]) >= 80.0  # foam's diagonal cell, percent
    assert (tmp_path / "confusion_minirocket_random_oa.csv").exists()


def test_boss_with_the_papers_alphabet_runs_on_the_same_data(db, monkeypatch):
    monkeypatch.setattr(classify, "BOSS_PER_CLASS", 12)  # its search costs ~n^2
    ds = assemble(sorted((db / "scans").glob("*.h5")))
    keep = np.isin(ds.y, ["foam", "glass", "aluminium"])
    sub = ds.subset(np.nonzero(keep)[0])
    cm = evaluate_random(sub, "boss", trials=1)
    acc = per_class_accuracy(cm, np.unique(sub.y))
    assert min(acc.values()) >= 0.7, acc


def test_label_shuffle_drops_accuracy_to_chance(db):
    ds = assemble(sorted((db / "scans").glob("*.h5")))
    cm = evaluate_random(ds, "minirocket", trials=3)
    real = np.trace(cm) / cm.sum()
    ds.y = np.random.default_rng(0).permutation(ds.y)
    cm = evaluate_random(ds, "minirocket", trials=3)
    shuffled = np.trace(cm) / cm.sum()
    chance = max(np.mean(ds.y == c) for c in np.unique(ds.y))
    assert real >= 0.85
    assert shuffled <= chance + 0.12, (shuffled, chance)


def test_model_file_predicts_and_refuses_other_sample_rates(db, model, tmp_path, capsys):
    scan = next((db / "scans").glob("foam_block-*.h5"))
    rc, out, err = run(capsys, "classify", "predict", "--model", str(model), "--scan",
                       str(scan), "--json")
    assert rc == 0, err
    got = json.loads(out)
    assert got["material"] == "foam" and got["confidence"] > 0.5
    other = tmp_path / "other_rate.h5"
    shutil.copy(scan, other)
    with h5py.File(other, "r+") as f:
        f["/entry/instrument/sensor"].attrs["adc_rate_hz"] = 2_000_000
    rc, out, err = run(capsys, "classify", "predict", "--model", str(model), "--scan",
                       str(other))
    assert rc == 2 and "trained on 3333333 Hz data" in err and "retrain" in err
    assert len(err.strip().splitlines()) == 1
    rc, out, err = run(capsys, "classify", "predict", "--model", str(model), "--scan",
                       str(scan), "--window", "96")
    assert rc == 2 and f"trained on {WINDOW}-sample windows, not 96" in err
    (tmp_path / "junk.model").write_bytes(b"not a model")
    rc, out, err = run(capsys, "classify", "predict", "--model",
                       str(tmp_path / "junk.model"), "--scan", str(scan))
    assert rc == 2 and "is not a dmdsm classifier model" in err


def test_live_prediction_refuses_a_ranging_setup_at_another_rate(model, tmp_path, capsys):
    setup = true_setup(SensorModel())
    setup.fs_hz /= 2
    setup.save(tmp_path / "ranging.json")
    rc, out, err = run(capsys, "classify", "predict", "--model", str(model), "--sensor",
                       str(tmp_path / "no-such-port"), "--ranging", str(tmp_path / "ranging.json"))
    assert rc == 2 and "these waveforms are 1666667 Hz" in err  # refused before the port


def test_mixed_sample_rates_are_refused(db, tmp_path):
    scans = sorted((db / "scans").glob("*.h5"))[:2]
    other = tmp_path / "x.h5"
    shutil.copy(scans[1], other)
    with h5py.File(other, "r+") as f:
        f["/entry/instrument/sensor"].attrs["adc_rate_hz"] = 2_000_000
    with pytest.raises(ClassifyError, match="one database per sample rate"):
        assemble([scans[0], other])


@pytest.mark.realtime
@pytest.mark.parametrize("name", ["glass_jar", "foam_block", "paper_cup"])
def test_live_prediction_through_the_emulated_sensor(name, model, tmp_path, capsys):
    """glass: US alone, foam: OA alone (lone pulses of unknown modality), paper: both."""
    with Emulator(SimConfig(scene=name, seed=5), speed=50.0) as emu:
        true_setup(SensorModel()).save(tmp_path / "ranging.json")
        w, d, h = bounding_size(household(name)[0])
        v = TABLE_I_V / np.linalg.norm(TABLE_I_V)
        at = TABLE_I_XR + np.array([0.0, 0.0, 0.4 * h]) - (max(w, d) / 2 + 8) * v
        stage = StageClient(emu.stage)
        stage.home()
        stage.move(x=at[0], y=at[1], z=at[2])
        stage.wait()
        stage.close()
        rc, out, err = run(capsys, "classify", "predict", "--model", str(model), "--sensor",
                           emu.sensor, "--ranging",
                           str(tmp_path / "ranging.json"), "--shots", "6", "--json")
    assert rc == 0, err
    got = json.loads(out)
    material = household(name)[0].material
    assert got["material"] == material and got["confidence"] > 0.6, got
    assert got["points"] >= 4


def test_ridge_probabilities_come_from_leave_one_out_decisions():
    """The softmax temperature is fitted on leave-one-out decision values: probabilities
    follow the evidence (a fit on scikit-learn's squared errors gave ~0.5 everywhere)."""
    from dmdsm.host.classify.ridge import CalibratedRidge

    rng = np.random.default_rng(0)
    X = rng.normal(size=(200, 6))
    y = np.where(X[:, 0] + 0.5 * rng.normal(size=200) > 0, "a", "b")
    r = CalibratedRidge(alphas=np.logspace(-3, 3, 10), store_cv_results=True,
                        scoring="accuracy").fit(X, y)
    p = r.predict_proba(X)
    p_true = p[np.arange(len(y)), np.searchsorted(r.classes_, y)]
    assert (r.classes_[p.argmax(axis=1)] == r.predict(X)).all()
    assert p_true.mean() > 0.7
    clear = np.abs(X[:, 0]) > 2  # far from the boundary: confident
    assert p_true[clear].min() > 0.9
    with pytest.raises(ValueError, match="scoring"):
        CalibratedRidge(store_cv_results=True).fit(X, y)


def test_evaluate_and_train_say_what_they_are_doing(tmp_path):
    """Issue 30: `classify evaluate` (272 s) and `classify train --classifier boss` (18 s)
    printed nothing until they ended: a bar per protocol, a line before a fit."""
    import subprocess
    import sys

    from dmdsm.sim.data.dataset import make_database

    make_database(tmp_path / "db", points=8, seed=3)
    r = subprocess.run([sys.executable, "-m", "dmdsm.host", "classify", "evaluate", "--db",
                        str(tmp_path / "db"), "--classifiers", "minirocket", "--trials", "2",
                        "--out", str(tmp_path / "out")], capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == 0, r.stderr
    assert "minirocket random splits" in r.stderr and "2/2" in r.stderr
    assert "minirocket leave one out" in r.stderr
    t = subprocess.run([sys.executable, "-m", "dmdsm.host", "classify", "train", "--db",
                        str(tmp_path / "db"), "--classifier", "minirocket", "-o",
                        str(tmp_path / "m.model")], capture_output=True, text=True,
                       timeout=600)
    assert t.returncode == 0, t.stderr
    assert t.stderr.startswith("training minirocket on ")
