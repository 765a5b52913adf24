#!/usr/bin/env python3
"""Applies chiron_turntable.toml to a Marlin checkout's Configuration.h / Configuration_adv.h.

Usage: python3 firmware/marlin_patch/apply.py MARLIN_DIR [--dry-run] [--force]
MARLIN_DIR is the checkout (or its Marlin/ folder) with the Chiron example configuration
copied in. Every setting is verified after writing; a missing line or a different Marlin
version stops the script before anything is written.
"""

from __future__ import annotations

import argparse
import re
import sys
from dataclasses import dataclass
from pathlib import Path

if __package__:
    from .settings import SETTINGS_PATH, load_settings, marlin_value
else:  # run as a script
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from settings import SETTINGS_PATH, load_settings, marlin_value  # type: ignore[no-redef]

FILES = ("Configuration.h", "Configuration_adv.h")


class PatchError(Exception):
    """The checkout cannot be patched; the message says why and what to do."""


@dataclass(frozen=True)
class Edit:
    """One change to a #define: set (value), enable, disable, or require (check only)."""

    file: str
    name: str
    action: str
    value: str | None
    reason: str


def plan(settings: dict) -> list[Edit]:
    """The edits of the settings file, with `value_from` resolved from [machine]."""
    machine = settings["machine"]
    edits = []
    for e in settings["edit"]:
        value = e.get("value")
        if "value_from" in e:
            value = marlin_value(machine[e["value_from"]])
        if e["action"] not in ("set", "enable", "disable", "require"):
            raise PatchError(f"{e['name']}: unknown action {e['action']!r}")
        if e["file"] not in FILES:
            raise PatchError(f"{e['name']}: unknown file {e['file']!r}")
        edits.append(Edit(e["file"], e["name"], e["action"], value, e.get("reason", "")))
    return edits


def _pattern(name: str) -> re.Pattern[str]:
    return re.compile(r"^(?P<indent>\s*)(?P<off>//\s*)?#define\s+" + re.escape(name)
                      + r"(?![A-Za-z0-9_])(?P<rest>.*)$")


def _split_value(rest: str) -> tuple[str, str]:
    """(value, trailing comment with its leading spaces) of the text after the name."""
    depth = 0
    for i, ch in enumerate(rest):
        if ch in "({":
            depth += 1
        elif ch in ")}":
            depth -= 1
        elif rest.startswith("//", i) and depth == 0:
            value = rest[:i].strip()
            return value, " " * max(1, len(rest[:i]) - len(rest[:i].rstrip())) + rest[i:]
    return rest.strip(), ""


def _find(lines: list[str], edit: Edit) -> list[int]:
    pat = _pattern(edit.name)
    return [i for i, line in enumerate(lines) if pat.match(line)]


def apply_text(text: str, edits: list[Edit], file: str) -> tuple[str, list[str]]:
    """New text of one file and a description of each change; raises PatchError."""
    lines = text.split("\n")
    changes = []
    for edit in (e for e in edits if e.file == file):
        where = _find(lines, edit)
        if not where:
            raise PatchError(f"{file}: no '#define {edit.name}' line (is this the Chiron example "
                             f"configuration for the Marlin version in {SETTINGS_PATH.name}?)")
        if len(where) > 1:
            raise PatchError(f"{file}: '#define {edit.name}' appears {len(where)} times "
                             f"(lines {', '.join(str(i + 1) for i in where)}); edit it by hand")
        i = where[0]
        m = _pattern(edit.name).match(lines[i])
        assert m is not None
        indent, off, rest = m.group("indent"), m.group("off"), m.group("rest")
        value, comment = _split_value(rest)
        if edit.action == "require":
            continue  # checked by verify()
        if edit.action == "disable":
            new = lines[i] if off else f"{indent}//#define {edit.name}{rest}"
        elif edit.action == "enable":
            new = f"{indent}#define {edit.name}{rest}"
        else:
            sep = rest[:len(rest) - len(rest.lstrip())] or " "
            new = f"{indent}#define {edit.name}{sep}{edit.value}{comment}"
        if new != lines[i]:
            changes.append(f"{file}:{i + 1}: {edit.action} {edit.name}"
                           f"{' ' + edit.value if edit.action == 'set' else ''}  ({edit.reason})")
            lines[i] = new
    return "\n".join(lines), changes


def verify(text: str, edits: list[Edit], file: str) -> list[str]:
    """Settings of this file that the text does not have (empty when all landed)."""
    lines = text.split("\n")
    problems = []
    for edit in (e for e in edits if e.file == file):
        active = [_pattern(edit.name).match(lines[i]) for i in _find(lines, edit)]
        active = [m for m in active if m and not m.group("off")]
        want_on = edit.action != "disable"
        if want_on != bool(active):
            problems.append(f"{file}: {edit.name} should be "
                            f"{'enabled' if want_on else 'disabled'}")
        elif want_on and edit.value is not None:
            got = _split_value(active[0].group("rest"))[0]
            if got.replace(" ", "") != edit.value.replace(" ", ""):
                problems.append(f"{file}: {edit.name} is {got!r}, expected {edit.value!r}")
    return problems


def check_version(marlin: Path, settings: dict) -> list[str]:
    """Differences between the checkout's version and the one the settings target."""
    want = settings["marlin"]
    problems = []
    version_h = marlin / "src/inc/Version.h"
    if version_h.exists():
        m = re.search(r'^\s*#define\s+SHORT_BUILD_VERSION\s+"([^"]+)"', version_h.read_text(),
                      re.M)
        if m and m.group(1) != want["branch"]:
            problems.append(f"Marlin is {m.group(1)}, this patch targets {want['branch']} "
                            f"({want['commit'][:10]}, {want['distribution_date']})")
    else:
        problems.append(f"{version_h} not found: is {marlin.parent} a Marlin checkout?")
    for name, key in (("Configuration.h", "CONFIGURATION_H_VERSION"),
                      ("Configuration_adv.h", "CONFIGURATION_ADV_H_VERSION")):
        m = re.search(rf"^\s*#define\s+{key}\s+(\w+)", (marlin / name).read_text(), re.M)
        if not m or m.group(1) != want["config_version"]:
            problems.append(f"{name}: {key} is {m.group(1) if m else 'missing'}, expected "
                            f"{want['config_version']} (copy {want['example']} from "
                            f"MarlinFirmware/Configurations {want['branch']})")
    return problems


def marlin_folder(path: Path) -> Path:
    """The folder holding Configuration.h: MARLIN_DIR/Marlin or MARLIN_DIR itself."""
    for cand in (path / "Marlin", path):
        if (cand / "Configuration.h").exists() and (cand / "Configuration_adv.h").exists():
            return cand
    raise PatchError(f"no Configuration.h and Configuration_adv.h in {path} or {path}/Marlin")


def apply_config(path: Path, settings_path: Path = SETTINGS_PATH, dry_run: bool = False,
                 force: bool = False) -> list[str]:
    """Patch a checkout; returns the changes made. Nothing is written if any check fails."""
    settings = load_settings(settings_path)
    marlin = marlin_folder(path)
    problems = check_version(marlin, settings)
    if problems and not force:
        raise PatchError(problems[0] + " (--force to try anyway)")
    edits = plan(settings)
    new_texts, changes = {}, []
    for name in FILES:
        text, ch = apply_text((marlin / name).read_text(), edits, name)
        bad = verify(text, edits, name)
        if bad:
            raise PatchError(bad[0])
        new_texts[name] = text
        changes += ch
    if not dry_run:
        for name, text in new_texts.items():
            (marlin / name).write_text(text)
    return changes


def main(argv: list[str] | None = None) -> int:
    """Command line: apply, print each change, one-line error and exit 2 on failure."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("marlin_dir", type=Path, help="Marlin checkout (or its Marlin/ folder)")
    ap.add_argument("--settings", type=Path, default=SETTINGS_PATH)
    ap.add_argument("--dry-run", action="store_true", help="show the changes, write nothing")
    ap.add_argument("--force", action="store_true", help="patch another Marlin version")
    args = ap.parse_args(argv)
    try:
        changes = apply_config(args.marlin_dir, args.settings, args.dry_run, args.force)
    except (PatchError, OSError) as e:
        print(f"apply.py: error: {e}", file=sys.stderr)
        return 2
    for c in changes:
        print(c)
    verb = "would change" if args.dry_run else "changed"
    print(f"{verb} {len(changes)} settings; all {len(plan(load_settings(args.settings)))} "
          f"verified" if changes else "already patched: all settings verified")
    return 0


if __name__ == "__main__":
    sys.exit(main())
