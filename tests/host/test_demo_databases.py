"""A demo run starts fresh databases and keeps the previous run's, so runs never mix."""

import os

from dmdsm.host.report.demo import keep_previous_databases


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


def test_nothing_to_move_on_a_first_run(tmp_path):
    keep_previous_databases(tmp_path)
    assert list(tmp_path.iterdir()) == []
