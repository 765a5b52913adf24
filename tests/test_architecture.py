"""The layers of docs/architecture.md hold: import-linter's contracts are kept, no module of
dmdsm is on an import cycle (typing-only imports counted), none imports the API face, and a
change that breaks a layer, or a module given no layer, fails with the contract's name."""

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LAYOUT = {"host": "host", "sim": "hil_sim", "protocol": "protocol",
          "marlin_patch": "firmware/marlin_patch"}


def package_view(where: Path, copy: bool = False) -> Path:
    """dmdsm laid out on disk as installed (dmdsm.sim = hil_sim/, ...)."""
    pkg = where / "dmdsm"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text('"""dmdsm."""\n')
    for name, src in LAYOUT.items():
        if copy:
            shutil.copytree(ROOT / src, pkg / name, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            (pkg / name).symlink_to(ROOT / src)
    return where


def lint_imports(where: Path) -> subprocess.CompletedProcess:
    exe = Path(sys.executable).parent / "lint-imports"
    return subprocess.run([str(exe), "--no-cache", str(ROOT / "pyproject.toml")], cwd=where,
                          env={**os.environ, "PYTHONPATH": str(where)}, capture_output=True,
                          text=True, timeout=300)


def test_contracts_are_kept(tmp_path):
    r = lint_imports(package_view(tmp_path))
    assert r.returncode == 0, r.stdout[-3000:]
    assert "0 broken" in r.stdout


CYCLES = """
import grimp

g = grimp.build_graph("dmdsm", exclude_type_checking_imports=False)
assert len(g.modules) > 70, sorted(g.modules)
for m in sorted(g.find_modules_that_directly_import("dmdsm.host")):
    print(m, "imports the API face dmdsm.host")
for m in sorted(g.modules):
    for dep in sorted(g.find_modules_directly_imported_by(m)):
        back = g.find_shortest_chain(importer=dep, imported=m) if dep != m else None
        if dep.startswith("dmdsm.") and back:
            print(" -> ".join((m, *back)))
"""


def test_no_module_is_on_an_import_cycle(tmp_path):
    # in a fresh interpreter: this one has dmdsm from the editable install's import hook,
    # which grimp cannot walk
    r = subprocess.run([sys.executable, "-c", CYCLES], cwd=package_view(tmp_path),
                       env={**os.environ, "PYTHONPATH": str(tmp_path)}, capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout == "", "import cycles:\n" + r.stdout[:2000]


@pytest.mark.parametrize("module, line, contract", [
    ("host/ranging/matched_filter.py", "from ..links import transport  # noqa",
     "pure computation imports no I/O"),
    ("host/links/stage.py", "from ..scan import plan  # noqa",
     "device clients know nothing of ranging, calibration, scans or classes"),
    ("host/scan/executor.py", "from ..commands import errors  # noqa", "host layers"),
    ("host/scan/session.py", "from .. import __version__  # noqa", "imports the API face"),
    ("sim/boards/sensor/rehost/bus.py", "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n"
     "    from .h743 import H743  # noqa", "no import cycles"),
])
def test_breaking_a_layer_is_reported_by_the_contract_name(tmp_path, module, line, contract):
    view = package_view(tmp_path, copy=True)
    path = view / "dmdsm" / module
    text = path.read_text()
    cut = text.index("\n\n", text.index('"""', 3)) + 1  # after the docstring
    path.write_text(text[:cut] + line + "\n" + text[cut:])
    r = lint_imports(view)
    assert r.returncode != 0
    broken = r.stdout.split("Broken contracts")[-1]
    assert contract in broken, r.stdout[-2000:]


@pytest.mark.parametrize("module, contract", [
    ("host/extra.py", "host layers"),
    ("sim/extra.py", "emulator: boards and physics below"),
])
def test_a_module_given_no_layer_is_reported(tmp_path, module, contract):
    view = package_view(tmp_path, copy=True)
    (view / "dmdsm" / module).write_text('"""New."""\n')
    r = lint_imports(view)
    assert r.returncode != 0
    assert contract in r.stdout.split("Broken contracts")[-1], r.stdout[-2000:]
