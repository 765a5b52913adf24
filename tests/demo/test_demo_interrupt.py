"""Ctrl-C or SIGTERM during `dmdsm demo` stops it: the running stage stops, no later stage
runs, the report of what finished is written (marked interrupted), one line says what was
stopped and how to start again, and the exit code is 130 or 143 like every command's."""

import json
import os
import signal
import subprocess
import sys
import threading
import time

import pytest

from dmdsm.host.commands.errors import Terminated
from dmdsm.host.demo.session import Demo, HeldStderr

STAGES = {1: "1. Ranging", 2: "2. Scanner calibration", 3: "3. Aluminium block",
          4: "4. Household set", 5: "5. Material classification", 6: "6. The 3D contour"}


def _demo(out):
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    # as from a terminal: Ctrl-C's default action (a shell's background job ignores it)
    return subprocess.Popen([sys.executable, "-m", "dmdsm.host", "demo", "--quick", "--out",
                             str(out)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, env=env,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


def _wait_for(proc, event, timeout=600):
    """Lines up to and including the first that starts with `event` (the stage's own
    output: no fixed sleep); a watchdog kills a demo that never gets there."""
    timer = threading.Timer(timeout, proc.kill)
    timer.start()
    lines = []
    try:
        for line in proc.stdout:
            lines.append(line)
            if line.startswith(event):
                return lines
    finally:
        timer.cancel()
    pytest.fail(f"the demo ended before {event!r}:\n" + "".join(lines))


@pytest.mark.realtime
@pytest.mark.parametrize("sig, event, stage", [
    (signal.SIGINT, "dmdsm sim: mounted rig_horizontal", 2),  # the rig's tip step runs
    (signal.SIGTERM, "dmdsm sim: mounted apple_red", 4),  # the household scans run
])
def test_a_signal_stops_the_demo_and_keeps_the_report(tmp_path, sig, event, stage):
    out = tmp_path / "out"
    with _demo(out) as proc:
        try:
            before = _wait_for(proc, event)
            t = time.monotonic()
            proc.send_signal(sig)
            rest, _ = proc.communicate(timeout=120)
            stop_s = time.monotonic() - t
        finally:
            if proc.poll() is None:
                proc.kill()
    text = "".join(before) + rest
    name = "SIGTERM" if sig == signal.SIGTERM else "Ctrl-C"
    assert proc.returncode == (143 if sig == signal.SIGTERM else 130), text
    assert "Traceback" not in text and "Error" not in rest, text
    mine = [line for line in rest.splitlines() if line.startswith("dmdsm demo:")]
    assert len(mine) == 1, text  # one line: what stopped, what finished, how to start again
    assert mine[0].startswith(f"dmdsm demo: stopped by {name} during stage {stage} ("), mine
    assert f"run `dmdsm demo --quick --out {out}` to start over" in mine[0]
    done = ", ".join(str(k) for k in range(1, stage))
    assert f"; stage{'s' if stage > 2 else ''} {done} finished;" in mine[0], mine
    # the commands' own stop lines would say "run the same command": not the demo's way
    assert "dmdsm: interrupted" not in rest and "dmdsm: terminated" not in rest, rest
    assert "run the same command" not in rest, rest
    for k in range(stage, 7):  # neither the stopped stage nor a later one reports a result
        assert not any(line.startswith(STAGES[k]) for line in rest.splitlines()), rest
    assert not (out / "classify").exists()
    summary = json.loads((out / "summary.json").read_text())
    st = summary["stages"]
    assert summary["interrupted"].startswith(f"stopped by {name}") and not summary["ok"]
    assert [st[str(k)]["status"] for k in range(stage, 7)] == \
        ["interrupted"] + ["not run"] * (6 - stage)
    assert all(st[str(k)]["status"] in ("ok", "FAILED") for k in range(1, stage))
    html = (out / "report.html").read_text()
    assert html.rstrip().endswith("</html>") and "(interrupted)" in html
    assert "not run" in (out / "report.md").read_text()
    assert stop_s < 60, stop_s


def test_a_command_stopped_by_a_signal_stops_the_demo():
    """Demo.run: a command that took its Ctrl-C path (exit 130/143) raises it again, so the
    demo never goes on to the next stage; another failure is a RuntimeError as before."""
    d = object.__new__(Demo)
    for rc, kind in ((130, KeyboardInterrupt), (143, Terminated)):
        d.command = lambda argv, rc=rc: rc
        with pytest.raises(kind) as e:
            d.run("scan")
        assert type(e.value) is kind
    d.command = lambda argv: 2
    with pytest.raises(RuntimeError, match="exited with 2"):
        d.run("scan")


def test_the_commands_stop_lines_are_held_and_dropped_on_a_signal():
    import io

    target = io.StringIO()
    err = HeldStderr(target)
    print("scan x stopped after 3 of 9 points; they are saved in f.h5; run the same command "
          "to continue", file=err)
    err.write("\r 40%|####  |")  # a progress bar's redraw goes through at once
    print("dmdsm: interrupted", file=err)
    assert target.getvalue() == "\r 40%|####  |"
    err.drop()
    assert target.getvalue() == "\r 40%|####  |"
    target = io.StringIO()
    err = HeldStderr(target)
    print("warning: something", file=err)
    print("tip step stopped after 3 raw points", file=err)
    assert target.getvalue() == "warning: something\n"
    err.release()  # no signal: everything is shown
    assert target.getvalue() == "warning: something\ntip step stopped after 3 raw points\n"
