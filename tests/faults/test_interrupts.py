"""Interrupted and misdirected acquisitions (issue 19, item 6): an output that cannot be
written is refused before anything is measured; Ctrl-C and SIGTERM keep the shots that
arrived and leave the board disarmed, so the next acquisition works."""

import re
import signal
import subprocess
import sys
import threading
import time

import h5py
import pytest

CMD = [sys.executable, "-m", "dmdsm.host"]


def test_an_output_that_cannot_be_written_is_refused_first(emulator, tmp_path):
    emu = emulator(speed=1.0)
    for out, words in ((tmp_path / "missing" / "r.h5", "does not exist"),
                       (tmp_path, "is a folder")):
        t0 = time.perf_counter()
        r = subprocess.run(CMD + ["acquire", "--sensor", emu.sensor, "--shots", "500", "-o",
                                  str(out)], capture_output=True, text=True, timeout=60)
        assert time.perf_counter() - t0 < 15
        assert r.returncode == 2 and words in r.stderr and "Traceback" not in r.stderr
        assert len(r.stderr.strip().splitlines()) == 1
    assert emu.sim.sensor.core.state == 0  # never armed


@pytest.mark.parametrize("sig, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_a_stopped_acquisition_keeps_its_shots_and_disarms(emulator, tmp_path, sig, code):
    emu = emulator(speed=0.5)
    out = tmp_path / "shots.h5"
    proc = subprocess.Popen(CMD + ["acquire", "--sensor", emu.sensor, "--shots", "400",
                                   "--average", "16", "-o", str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    # the host has taken in shots (its progress bar on stderr says how many): the event,
    # not the board's count, which ran ahead of a host still reading on a loaded machine
    # (the signal then came before any shot was in: "0 < 0")
    chars: list[str] = []
    reader = threading.Thread(target=lambda: chars.extend(iter(lambda: proc.stderr.read(1),
                                                               "")), daemon=True)
    reader.start()

    def host_received() -> int:
        return max(map(int, re.findall(r"(\d+)/400", "".join(chars))), default=0)

    deadline = time.monotonic() + 120
    while host_received() < 2 and time.monotonic() < deadline:
        time.sleep(0.05)
    proc.send_signal(sig)
    proc.wait(timeout=60)
    reader.join(10)
    proc.stdout.close()
    proc.stderr.close()
    err = "".join(chars)
    assert proc.returncode == code, err
    assert "Traceback" not in err and "saved in" in err
    with h5py.File(out, "r") as f:
        got = int(f["/entry/data/received"][:].sum())
        assert f["/entry"].attrs["status"] == "interrupted"
    assert 0 < got < 400
    r = subprocess.run(CMD + ["acquire", "--sensor", emu.sensor, "--shots", "3", "-o",
                              str(tmp_path / "again.h5")], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stderr  # not "refused set_config (busy)"
