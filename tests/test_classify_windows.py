"""Every window length the classify command accepts trains and predicts with both classifiers,
through the API and the command; a shorter one is one line (issue 36: BOSS on short windows)."""

import json

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from dmdsm.host.classify.materials import (
    BOSS_WORD_MIN,
    SHORTEST_WINDOW,
    WINDOW,
    ClassifyError,
    boss_word_windows,
    fit,
    make_classifier,
)
from dmdsm.host.classify.warm import tiny_dataset
from dmdsm.host.commands.cli import main
from dmdsm.host.links.sensor import config_range
from dmdsm.sim.data.dataset import make_database

LONGEST = config_range("n_samples")[1]
SLOW = settings(max_examples=8, deadline=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture])


@given(st.integers(SHORTEST_WINDOW, LONGEST))
def test_boss_word_windows_fit_in_every_accepted_window(window):
    shortest, longest = boss_word_windows(window)
    assert 1 <= shortest <= longest <= window
    assert longest == int(window * 0.34)
    if longest >= BOSS_WORD_MIN:  # the paper-style bounds where the window allows them
        assert shortest == BOSS_WORD_MIN


def test_the_word_windows_scale_with_the_window():
    assert boss_word_windows(128) == (16, 43)  # the default before the OA window was cut
    assert boss_word_windows(WINDOW) == (16, 21)  # to end before the US echo (64)


@SLOW
@given(st.integers(SHORTEST_WINDOW, 160))
@example(16).via("the shortest accepted")
@example(24).via("the window of the report")
@example(44).via("the longest aeon refused")
@example(47).via("aeon's empty ensemble")
@example(48).via("the first with min_window 16")
@pytest.mark.parametrize("name", ["boss", "minirocket"])
def test_both_classifiers_learn_at_every_window_length(name, window):
    ds = tiny_dataset(window=window)
    model = fit(ds, name)
    assert np.mean(model.predict(ds) == ds.y) >= 0.9  # two distinct tones, seen in training


@pytest.mark.parametrize("window", [1, 8, SHORTEST_WINDOW - 1])
@pytest.mark.parametrize("name", ["boss", "minirocket"])
def test_a_window_too_short_is_one_line_before_any_fit(name, window):
    with pytest.raises(ClassifyError) as e:
        fit(tiny_dataset(window=window), name)
    assert "\n" not in str(e.value) and f"at least {SHORTEST_WINDOW} samples" in str(e.value)
    with pytest.raises(ClassifyError):
        make_classifier(name, window)


@pytest.fixture(scope="module")
def db(tmp_path_factory):
    d = tmp_path_factory.mktemp("db")
    make_database(d, points=12, seed=2,
                  objects=["foam_block", "soda_can", "glass_jar", "paper_cup"])
    return d


@settings(max_examples=4, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.integers(SHORTEST_WINDOW, 47))
@example(24)
def test_boss_trains_and_predicts_through_the_command_at_short_windows(db, tmp_path_factory,
                                                                         capsys, window):
    out = tmp_path_factory.mktemp("m") / "boss.model"
    rc = main(["classify", "train", "--db", str(db), "--classifier", "boss", "--window",
               str(window), "-o", str(out), "--json"])
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    assert json.loads(captured.out)["classifier"] == "boss"
    scan = next((db / "scans").glob("foam_block-*.h5"))
    rc = main(["classify", "predict", "--model", str(out), "--scan", str(scan), "--window",
               str(window), "--json"])  # the model file refits BOSS at this window
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    assert json.loads(captured.out)["points"] > 0


def test_boss_evaluates_through_the_command_at_a_short_window(db, tmp_path, capsys):
    rc = main(["classify", "evaluate", "--db", str(db), "--classifiers", "boss", "minirocket",
               "--window", "24", "--trials", "1", "--out", str(tmp_path), "--json"])
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    res = json.loads(captured.out)
    assert set(res["classifiers"]) == {"boss", "minirocket"}


@pytest.mark.parametrize("window", ["15", "0", "-3", str(LONGEST + 1)])
def test_the_command_names_the_window_range(db, tmp_path, capsys, window):
    rc = main(["classify", "train", "--db", str(db), "--window", window, "-o",
               str(tmp_path / "m.model")])
    err = capsys.readouterr().err
    assert rc != 0 and f"--window must be {SHORTEST_WINDOW}..{LONGEST} samples" in err
    assert "Traceback" not in err and err.strip().count("\n") == 0
    assert not (tmp_path / "m.model").exists()


def test_help_states_the_window_range(capsys):
    with pytest.raises(SystemExit):
        main(["classify", "train", "--help"])
    assert f"{SHORTEST_WINDOW}..{LONGEST}" in " ".join(capsys.readouterr().out.split())
