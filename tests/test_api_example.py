"""docs/api.md's worked example runs as written against the emulator, and gives what it says."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def blocks() -> list[str]:
    text = (ROOT / "docs/api.md").read_text()
    return re.findall(r"```python\n(.*?)```", text, re.S)


def test_the_worked_example_runs_as_written(tmp_path, monkeypatch, capsys):
    code = blocks()
    assert len(code) == 5
    monkeypatch.chdir(tmp_path)
    ns: dict = {"__name__": "api_example"}
    for block in code:
        exec(compile(block, "docs/api.md", "exec"), ns)
    out = capsys.readouterr().out
    run = ns["run"]
    assert run.status == "complete" and run.points == run.planned > 40
    assert out.startswith(f"complete {run.points} points in {run.path}")
    # the block scanned with the true calibration meets the paper's contour error
    assert ns["fits"]["oa"]["e_mean_mm"] < 0.15
    assert ns["fits"]["us"]["e_mean_mm"] < 0.3
    assert ns["verdict"]["material"] == "aluminium"
    assert (tmp_path / "db" / "catalogue.sqlite").exists()
    assert (tmp_path / "ranging.json").exists() and (tmp_path / "material.model").exists()


def test_the_face_exports_what_the_doc_names():
    import dmdsm.host as dm

    for name in dm.__all__:
        assert getattr(dm, name) is not None
    text = (ROOT / "docs/api.md").read_text()
    for name in re.findall(r"\bdm\.(\w+)", text):
        assert name in dm.__all__, name
    assert sorted(dm.__all__[1:]) == sorted(dm._EXPORTS)
