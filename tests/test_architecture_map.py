"""docs/architecture.md is the map of the code: every module is on it, and nothing on it is gone.

A new module fails here until its line is written in the map; a moved or deleted one fails
until the map follows. The test index (tests/INDEX.md) is kept true the same way.
"""

import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FOLDERS = ("host", "hil_sim", "protocol", "firmware/marlin_patch")
MAP = ROOT / "docs" / "architecture.md"


def source_modules() -> set[str]:
    """Repository paths of every Python module of dmdsm (package __init__ files left out:
    the map names their folders)."""
    return {str(p.relative_to(ROOT)) for f in FOLDERS for p in (ROOT / f).rglob("*.py")
            if p.name != "__init__.py" and "__pycache__" not in p.parts}


def mapped() -> set[str]:
    """Every `path/to/module.py` written in the map (in backquotes)."""
    return set(re.findall(r"`((?:host|hil_sim|protocol|firmware/marlin_patch)/[\w/]*\.py)`",
                          MAP.read_text()))


def test_every_module_is_on_the_map():
    missing = sorted(source_modules() - mapped())
    assert not missing, f"docs/architecture.md does not name: {', '.join(missing)}"


def test_nothing_on_the_map_is_gone():
    gone = sorted(m for m in mapped() if not (ROOT / m).exists())
    assert not gone, f"docs/architecture.md names modules that do not exist: {', '.join(gone)}"


def test_every_folder_of_the_map_says_what_is_inside():
    text = MAP.read_text()
    folders = {str(Path(m).parent) for m in source_modules()}
    missing = sorted(f for f in folders if f"`{f}/`" not in text)
    assert not missing, f"docs/architecture.md has no heading line for: {', '.join(missing)}"


def test_the_test_index_is_current():
    r = subprocess.run([sys.executable, str(ROOT / "tests" / "index.py"), "--check"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
