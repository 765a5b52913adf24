"""The demo's run: the six stages in order through the `dmdsm` commands, then the report files."""

from __future__ import annotations

import contextlib
import json
import signal
import sys
import time
from collections.abc import Iterator
from pathlib import Path

from ..commands.cli import main
from ..commands.errors import Terminated
from ..files import atomic_output, one_line
from ..report.page import Section, html_page, markdown
from .household import stage_household
from .models import stage_models
from .session import TITLES, Demo, stage_block, stage_classify, stage_ranging, stage_rig


def keep_previous_databases(out: Path) -> None:
    """Each demo scans into fresh databases: a previous run's `db`, `validation` and the
    campaign's `db_models` (and its calibrations, classifier and classification results)
    move to out/previous/<name>-<time of their last change>, so neither the classifier nor
    an object's model mixes runs (other calibrations, sample rates, code) and nothing a user
    may want is deleted."""
    for name in ("db", "db_fly", "validation", "db_models", "classify", "ranging.json",
                 "calibration.toml", "materials.npz"):
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


def _write(path: Path, text: str) -> None:
    """Write through a temporary file renamed over `path`: a reader (or a second Ctrl-C)
    sees the old report or the new one, never half of one."""
    with atomic_output(path, flag="--out") as tmp:
        tmp.write_text(text)


def write_report(out: Path, sections: list[Section], quick: bool, total: float,
                 rates: dict[str, float], interrupted: str = "") -> dict:
    """out/report.md, out/report.html and out/summary.json of the stages run; the summary.
    interrupted: what a signal stopped ("" if nothing), shown under the title."""
    title = f"dmdsm demo{' (quick)' if quick else ''}: the paper's experiments on the emulator"
    if interrupted:
        title += " (interrupted)"
    ran = [s for s in sections if s.state != "not run"] or sections
    if ran:
        ran[-1].text.append(f"Total {total:.0f} s on this machine.")
    _write(out / "report.md", markdown(title, sections, interrupted))
    _write(out / "report.html", html_page(title, sections, interrupted))
    summary = {"ok": bool(sections) and all(s.status == "ok" for s in sections),
               "interrupted": interrupted or None, "seconds": total,
               "report": str(out / "report.html"), "household_points_per_s": rates,
               "stages": {s.title.split(".")[0]: s.summary() for s in sections}}
    _write(out / "summary.json", json.dumps(summary, indent=1, default=float))
    return summary


def rig_checks(sec: Section) -> None:
    """Stage 2's criteria, stated beside its status: the errors against the emulator's
    truth that stage_rig's own verdict uses (v within 2 deg, n within 0.5 deg, X_R within
    0.3 mm in the table plane); nothing if the stage states its own or has no figures."""
    v = sec.values
    if sec.checks or not all(k in v for k in ("v_error_deg", "n_error_deg", "X_R_error_mm")):
        return
    ok = sec.ok
    for what, key, unit, limit in (("v", "v_error_deg", "deg", 2.0),
                                   ("n", "n_error_deg", "deg", 0.5),
                                   ("X_R (table plane)", "X_R_error_mm", "mm", 0.3)):
        sec.check(f"{what} error vs the emulator's truth", f"{v[key]:.3f} {unit}",
                  f"< {limit} {unit}", v[key] < limit)
    sec.ok = ok and sec.ok


def _stage_name(title: str) -> str:
    """ "4. Household set scanned into the database (paper ...)" -> "stage 4 (household set
    scanned into the database)"."""
    num, _, name = title.split(" (")[0].partition(". ")
    return f"stage {num} ({name[:1].lower()}{name[1:]})"


@contextlib.contextmanager
def _signals_held() -> Iterator[None]:
    """While the demo cleans up after a signal (stops the emulator, writes the report), a
    second Ctrl-C or SIGTERM waits until that is done, so the report is always written."""
    pending: list[int] = []
    held = {}
    try:
        for sig in (signal.SIGINT, signal.SIGTERM):
            held[sig] = signal.signal(sig, lambda signum, frame: pending.append(signum))
    except ValueError:  # not the main thread (a test calling run_demo): nothing to hold
        pass
    try:
        yield
    finally:
        for sig, handler in held.items():
            signal.signal(sig, handler)


def run_demo(out_dir: str, quick: bool = False, speed: float = 8.0, as_json: bool = False,
             stage_firmware: str = "") -> int:
    """Run every stage through the `dmdsm` commands (commands.cli.main), write
    out/report.html, out/report.md and out/summary.json; 0 if all passed. as_json: progress
    to stderr, the summary as one JSON line on stdout. stage_firmware: a Marlin ELF run
    under simavr as the stage board, at most 2x real time (simavr's pace on one core).

    Ctrl-C or SIGTERM stops the demo at once: the running command takes its own Ctrl-C path
    (a scan quick-stops the stage board and closes its file), no later stage runs, the
    emulator stops, the report is written with the stages that finished (the stopped one
    "interrupted", the rest "not run") and one line says what stopped and how to start
    again; exit 130 (SIGINT) or 143 (SIGTERM), like every `dmdsm` command."""
    say = sys.stderr if as_json else sys.stdout
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    keep_previous_databases(out)
    t_all = time.perf_counter()
    if stage_firmware:
        speed = min(speed, 2.0)
    stages = [stage_ranging, stage_rig, stage_block, stage_household, stage_classify,
              stage_models]
    sections: list[Section] = []
    d: Demo | None = None
    stopped: KeyboardInterrupt | None = None
    where, skipped = "while starting the emulator", ""
    t0 = time.perf_counter()
    try:
        try:
            d = Demo(out, quick, speed, main, stage_firmware)
            for stage in stages:
                where, t0 = _stage_name(TITLES[stage.__name__]), time.perf_counter()
                try:
                    got = stage(d)
                except (RuntimeError, ValueError, OSError) as e:
                    got = Section(TITLES[stage.__name__], ok=False, text=[str(e)])
                    got.check("the stage's commands:", one_line(str(e), 160),
                              "run to their end", False)
                sec = got[0] if isinstance(got, tuple) else got
                if stage is stage_rig:
                    rig_checks(sec)
                sec.seconds = time.perf_counter() - t0
                sections.append(sec)
                where = f"after {_stage_name(sec.title)}"
                print(f"{sec.title}: {sec.headline} ({sec.seconds:.0f} s)", flush=True,
                      file=say)
                if not sec.ok and stage in (stage_ranging, stage_rig):
                    skipped = f"not run: {_stage_name(sec.title)} failed, and this stage " \
                              f"needs its result"
                    break  # later stages need these
        except KeyboardInterrupt as e:
            stopped = e
            if where.startswith("stage"):
                title = next(t for t in TITLES.values() if _stage_name(t) == where)
                sections.append(Section(title, ok=False, state="interrupted",
                                        seconds=time.perf_counter() - t0, text=[
                                            f"Stopped by {_signal_name(e)} after "
                                            f"{time.perf_counter() - t0:.0f} s; its "
                                            f"results are not in this report."]))
            skipped = f"not run: the demo was stopped by {_signal_name(e)}"
        finally:  # the emulator stops however the stages ended
            with _signals_held() if stopped else contextlib.nullcontext():
                if d is not None:
                    d.close()
    except KeyboardInterrupt as e:  # while the emulator stopped after a normal run
        stopped = stopped or e
        skipped = skipped or f"not run: the demo was stopped by {_signal_name(e)}"
    with _signals_held() if stopped else contextlib.nullcontext():
        done = {s.title for s in sections}
        sections += [Section(TITLES[s.__name__], ok=False, state="not run", text=[skipped])
                     for s in stages if TITLES[s.__name__] not in done]
        total = time.perf_counter() - t_all
        finished = [s.title.split(".")[0] for s in sections if not s.state]
        what = ""
        if stopped:
            during = "during " if where.startswith("stage") else ""
            what = (f"stopped by {_signal_name(stopped)} {during}{where}; "
                    + (f"stage{'s' if len(finished) > 1 else ''} {', '.join(finished)} "
                       f"finished" if finished else "no stage finished"))
        summary = write_report(out, sections, quick, total, d.rates if d else {}, what)
    if stopped:
        again = f"dmdsm demo{' --quick' if quick else ''} --out {out_dir}"
        print(f"dmdsm demo: {what}; the report is {out / 'report.html'}; run `{again}` to "
              f"start over (this run's data moves to {out / 'previous'})", file=sys.stderr,
              flush=True)
        if as_json:
            print(json.dumps(summary, default=float))
        return 143 if isinstance(stopped, Terminated) else 130
    print(f"report: {out / 'report.html'} ({total:.0f} s)", file=say)
    if as_json:
        print(json.dumps(summary, default=float))
    return 0 if summary["ok"] else 1


def _signal_name(e: BaseException) -> str:
    return "SIGTERM" if isinstance(e, Terminated) else "Ctrl-C"
