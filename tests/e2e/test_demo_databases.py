"""A demo run starts fresh databases and keeps the previous run's, so runs never mix."""

import os

from dmdsm.host.demo.run import keep_previous_databases


def test_previous_databases_move_aside_and_nothing_is_lost(tmp_path):
    for run in range(2):
        for name in ("db", "validation"):
            (tmp_path / name).mkdir()
            (tmp_path / name / f"scan{run}.h5").write_text(f"run {run}")
            os.utime(tmp_path / name, (1_700_000_000, 1_700_000_000))  # same stamp twice
        keep_previous_databases(tmp_path)
        assert not (tmp_path / "db").exists() and not (tmp_path / "validation").exists()
    kept = sorted(p.name for p in (tmp_path / "previous").iterdir())
    assert len(kept) == 4 and len({k.rsplit("-", 1)[0] for k in kept}) >= 2
    texts = sorted(f.read_text() for f in (tmp_path / "previous").rglob("*.h5"))
    assert texts == ["run 0", "run 0", "run 1", "run 1"]


def test_the_campaigns_database_starts_fresh_so_a_model_is_this_runs_scans(tmp_path):
    """A campaign into a kept db_models scans every object again: without the move each
    demo's model fused the scans of every earlier run (other calibrations and code), and the
    report judged that mix as this run's."""
    (tmp_path / "db_models" / "scans").mkdir(parents=True)
    (tmp_path / "db_models" / "scans" / "soda_can-1.h5").write_text("run 0")
    (tmp_path / "materials.npz").write_text("classifier 0")
    keep_previous_databases(tmp_path)
    assert not (tmp_path / "db_models").exists() and not (tmp_path / "materials.npz").exists()
    kept = sorted(p.name for p in (tmp_path / "previous").iterdir())
    assert [k.split("-")[0] for k in kept] == ["db_models", "materials"]
    assert (tmp_path / "previous" / kept[0] / "scans" / "soda_can-1.h5").read_text() == "run 0"
    assert kept[1].endswith(".npz")


def test_nothing_to_move_on_a_first_run(tmp_path):
    keep_previous_databases(tmp_path)
    assert list(tmp_path.iterdir()) == []


def test_a_previous_runs_calibrations_move_aside_too(tmp_path):
    (tmp_path / "ranging.json").write_text("{}")
    (tmp_path / "calibration.toml").write_text("[calibration]\n")
    keep_previous_databases(tmp_path)
    kept = sorted(p.name for p in (tmp_path / "previous").iterdir())
    assert [k.split("-")[0] for k in kept] == ["calibration", "ranging"]
    assert kept[0].endswith(".toml") and kept[1].endswith(".json")
    assert not (tmp_path / "ranging.json").exists()


def test_keep_previous_moves_an_earlier_calibration_aside_with_its_time(tmp_path):
    """calibrate and calibrate-range never write over an earlier result: it is renamed,
    stamped with the time it was written, and a second one in that second does not collide."""
    import time

    from dmdsm.host.commands.errors import keep_previous

    assert keep_previous(tmp_path / "ranging.json") is None
    names = []
    for text in ("first", "second"):
        (tmp_path / "ranging.json").write_text(text)
        os.utime(tmp_path / "ranging.json", (1_700_000_000, 1_700_000_000))
        names.append(keep_previous(tmp_path / "ranging.json"))
    stamp = time.strftime("%Y%m%d-%H%M%S", time.localtime(1_700_000_000))
    assert names[0].name == f"ranging.{stamp}.json"
    assert names[1].name == f"ranging.{stamp}-1.json"
    assert [n.read_text() for n in names] == ["first", "second"]
    assert not (tmp_path / "ranging.json").exists()
