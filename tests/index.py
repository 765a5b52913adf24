"""Writes tests/INDEX.md: for every module of dmdsm, the test files that import it.

A newcomer looks a module up there and finds its tests in one step; `tests/test_index.py`
fails when the file is not what this script writes now (run `make index` after adding a test
or a module). Imports are read from the test files' syntax trees, not by running them.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# where each installed package of dmdsm lives in the repository (pyproject.toml package-dir)
LAYOUT = {"dmdsm.host": "host", "dmdsm.sim": "hil_sim", "dmdsm.protocol": "protocol",
          "dmdsm.marlin_patch": "firmware/marlin_patch"}
INDEX = ROOT / "tests" / "INDEX.md"


def modules() -> dict[str, Path]:
    """Every module of dmdsm (dotted name -> source file), packages as their __init__.py."""
    out: dict[str, Path] = {}
    for package, folder in LAYOUT.items():
        for path in sorted((ROOT / folder).rglob("*.py")):
            rel = path.relative_to(ROOT / folder).with_suffix("")
            parts = [p for p in rel.parts if p != "__init__"]
            if "__pycache__" in parts:
                continue
            out[".".join([package, *parts])] = path
    return out


def imported_by(test: Path, known: set[str]) -> set[str]:
    """The dmdsm modules a test file imports: `import dmdsm.x`, `from dmdsm.x import y`
    (y counted when it is a module itself)."""
    found: set[str] = set()
    for node in ast.walk(ast.parse(test.read_text(), str(test))):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        else:
            continue
        found |= {n for n in names if n in known}
    return found


def commands(mods: dict[str, Path]) -> dict[str, str]:
    """`dmdsm` subcommand -> the commands module that registers it (`sub.add_parser("x"`)."""
    out: dict[str, str] = {}
    for m, path in mods.items():
        if ".commands." not in m:
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                    and node.func.attr == "add_parser" and isinstance(node.func.value, ast.Name)
                    and node.func.value.id == "sub" and node.args
                    and isinstance(node.args[0], ast.Constant)):
                out[node.args[0].value] = m
    return out


def runs(test: Path, names: dict[str, str]) -> set[str]:
    """The commands modules a test runs through the CLI: a list whose first string is a
    subcommand (`main(["scan", ...])`, `[*CMD, "db", "list"]`), or that follows the package
    (`[sys.executable, "-m", "dmdsm.host", "sim", ...]`)."""
    found: set[str] = set()
    for node in ast.walk(ast.parse(test.read_text(), str(test))):
        if isinstance(node, ast.List):
            words = [e.value for e in node.elts
                     if isinstance(e, ast.Constant) and isinstance(e.value, str)]
            if "dmdsm.host" in words:
                words = words[words.index("dmdsm.host") + 1:]
            if words and words[0] in names:
                found.add(names[words[0]])
    return found


def render() -> str:
    """The index as Markdown: one row per module, its tests, or '-' where none imports it."""
    mods = modules()
    tests = sorted(p for p in (ROOT / "tests").rglob("*.py") if "__pycache__" not in p.parts)
    names = commands(mods)
    by_module: dict[str, list[str]] = {m: [] for m in mods}
    for t in tests:
        rel = str(t.relative_to(ROOT / "tests"))
        for m in imported_by(t, set(mods)):
            by_module[m].append(f"`{rel}`")
        for m in runs(t, names) - imported_by(t, set(mods)):
            by_module[m].append(f"`{rel}` (runs it)")
    lines = ["# Which tests import which module",
             "",
             "Written by `python tests/index.py` (`make index`); `tests/test_index.py` fails when",
             "it is out of date. A module with no test of its own (`-`) is exercised through the",
             "modules above it: the end-to-end tests in `tests/e2e/` run the whole pipeline on the",
             "emulator, `tests/stage/` and `tests/conformance/` run against a board or its",
             "emulation.",
             "",
             "| module | source | tests that import it |",
             "|---|---|---|"]
    for m, path in mods.items():
        files = ", ".join(sorted(by_module[m])) or "-"
        lines.append(f"| `{m}` | `{path.relative_to(ROOT)}` | {files} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str]) -> int:
    """Write the index, or with --check exit 1 if it is stale."""
    text = render()
    if "--check" in argv:
        if not INDEX.exists() or INDEX.read_text() != text:
            print("tests/INDEX.md is out of date: run `make index`", file=sys.stderr)
            return 1
        return 0
    INDEX.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
