"""Material classification on a small hil_sim database (seven materials, two objects each):
trains and evaluates end to end, a label shuffle drops to chance, provenance is checked."""

import json
import shutil

import h5py
import numpy as np
import pytest

from dmdsm.host.classify import ClassifyError, assemble, evaluate_random, per_class_accuracy
from dmdsm.host.cli import main
from dmdsm.sim.dataset import make_database

ARTIFICIAL = ("aluminium", "foam", "glass", "paper", "plastic", "steel")


@pytest.fixture(scope="module")
def db(tmp_path_factory):
    d = tmp_path_factory.mktemp("db")
    make_database(d, points=24, seed=1)
    return d


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
    for m in ARTIFICIAL:  # distinct materials are told apart in both protocols
        assert acc["random"][m] >= 0.8, (m, acc)
        assert acc["loo"][m] >= 0.6, (m, acc)
    assert (tmp_path / "confusion_minirocket_random.png").stat().st_size > 5000
    cm = np.loadtxt(tmp_path / "confusion_minirocket_loo.csv", delimiter=",")
    assert cm.shape == (7, 7) and cm.sum() > 100


def test_boss_with_the_papers_alphabet_runs_on_the_same_data(db):
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


def test_model_file_predicts_and_refuses_other_sample_rates(db, tmp_path, capsys):
    model = tmp_path / "m.model"
    rc, out, err = run(capsys, "classify", "train", "--db", str(db), "--classifier",
                       "minirocket", "-o", str(model), "--json")
    assert rc == 0, err
    assert json.loads(out)["points"] > 200
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
    assert rc == 2 and "trained on 3582090 Hz data" in err and "retrain" in err
    assert len(err.strip().splitlines()) == 1
    (tmp_path / "junk.model").write_bytes(b"not a model")
    rc, out, err = run(capsys, "classify", "predict", "--model",
                       str(tmp_path / "junk.model"), "--scan", str(scan))
    assert rc == 2 and "not a dmdsm classifier model" in err


def test_mixed_sample_rates_are_refused(db, tmp_path):
    scans = sorted((db / "scans").glob("*.h5"))[:2]
    other = tmp_path / "x.h5"
    shutil.copy(scans[1], other)
    with h5py.File(other, "r+") as f:
        f["/entry/instrument/sensor"].attrs["adc_rate_hz"] = 2_000_000
    with pytest.raises(ClassifyError, match="one database per sample rate"):
        assemble([scans[0], other])
