"""The demo's run: the five stages in order through the `dmdsm` commands, then the report files."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from ..commands.cli import main
from ..report.page import Section, html_page, markdown
from .household import stage_household
from .session import TITLES, Demo, stage_block, stage_classify, stage_ranging, stage_rig


def keep_previous_databases(out: Path) -> None:
    """Each demo scans into fresh databases: a previous run's `db` and `validation` (and its
    calibrations) move to out/previous/<name>-<time of their last change>, so the classifier
    never mixes runs (or sample rates) and nothing a user may want is deleted."""
    for name in ("db", "db_fly", "validation", "ranging.json", "calibration.toml"):
        old = out / name
        if old.exists() and not old.is_symlink():
            stamp = time.strftime("%Y%m%d-%H%M%S", time.localtime(old.stat().st_mtime))
            target = out / "previous" / f"{old.stem}-{stamp}{old.suffix}"
            n = 1
            while target.exists():
                n += 1
                target = out / "previous" / f"{old.stem}-{stamp}-{n}{old.suffix}"
            target.parent.mkdir(exist_ok=True)
            old.rename(target)


def write_report(out: Path, sections: list[Section], quick: bool, total: float,
                 rates: dict[str, float]) -> dict:
    """out/report.md, out/report.html and out/summary.json of the stages run; the summary."""
    title = f"dmdsm demo{' (quick)' if quick else ''}: the paper's experiments on the emulator"
    sections[-1].text.append(f"Total {total:.0f} s on this machine.")
    (out / "report.md").write_text(markdown(title, sections))
    (out / "report.html").write_text(html_page(title, sections))
    summary = {"ok": bool(all(s.ok for s in sections)), "seconds": total,
               "report": str(out / "report.html"), "household_points_per_s": rates,
               "stages": {s.title.split(".")[0]: {"title": s.title, "ok": bool(s.ok),
                                                  "seconds": s.seconds, "values": s.values}
                          for s in sections}}
    (out / "summary.json").write_text(json.dumps(summary, indent=1, default=float))
    return summary


def run_demo(out_dir: str, quick: bool = False, speed: float = 8.0, as_json: bool = False,
             stage_firmware: str = "") -> int:
    """Run every stage through the `dmdsm` commands (commands.cli.main), write
    out/report.html, out/report.md and out/summary.json; 0 if all passed. as_json: progress
    to stderr, the summary as one JSON line on stdout. stage_firmware: a Marlin ELF run
    under simavr as the stage board, at most 2x real time (simavr's pace on one core)."""
    say = sys.stderr if as_json else sys.stdout
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    keep_previous_databases(out)
    t_all = time.perf_counter()
    if stage_firmware:
        speed = min(speed, 2.0)
    d = Demo(out, quick, speed, main, stage_firmware)
    sections: list[Section] = []
    stages = [stage_ranging, stage_rig, stage_block, stage_household, stage_classify]
    try:
        for stage in stages:
            t0 = time.perf_counter()
            try:
                got = stage(d)
            except (RuntimeError, ValueError, OSError) as e:
                got = Section(TITLES[stage.__name__], ok=False, text=[str(e)])
            sec = got[0] if isinstance(got, tuple) else got
            sec.seconds = time.perf_counter() - t0
            sections.append(sec)
            print(f"{sec.title}: {'ok' if sec.ok else 'FAILED'} ({sec.seconds:.0f} s)",
                  flush=True, file=say)
            if not sec.ok and stage in (stage_ranging, stage_rig):
                break  # later stages need these
    finally:
        d.close()
    total = time.perf_counter() - t_all
    summary = write_report(out, sections, quick, total, d.rates)
    print(f"report: {out / 'report.html'} ({total:.0f} s)", file=say)
    if as_json:
        print(json.dumps(summary, default=float))
    return 0 if all(s.ok for s in sections) and len(sections) == len(stages) else 1
