"""`dmdsm sim` as a user runs it: two ports by name, both boards answer, Ctrl-C stops it."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest  # noqa: E402
import serial

from dmdsm.protocol import FrameDecoder, Message, encode_frame, load_spec

pytestmark = pytest.mark.realtime  # serves the emulator in a subprocess, in real time


def interruptible():
    """Ctrl-C reaches the child even when this test run was started in the background (a
    shell then ignores SIGINT, and Python keeps an inherited SIG_IGN)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def start(*args):
    p = subprocess.Popen([sys.executable, "-m", "dmdsm.host", "sim", "--json", *args],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         preexec_fn=interruptible)
    line = p.stdout.readline()
    if not line:  # it exited instead of serving: show why, and leave no pipe open
        _, err = p.communicate(timeout=10)
        raise AssertionError(f"dmdsm sim exited with {p.returncode}: {err.strip()[-500:]}")
    return p, json.loads(line)


def test_sim_serves_both_boards_on_ptys_and_stops_on_ctrl_c(tmp_path):
    p, ports = start("--seed", "3", "--link-dir", str(tmp_path))
    try:
        assert ports["sensor"] == str(tmp_path / "sensor")
        assert os.path.realpath(ports["stage"]).startswith("/dev/pts/")
        stage = serial.Serial(ports["stage"], 250000, timeout=0.2)
        stage.reset_input_buffer()
        stage.write(b"M115\n")
        text = b""
        end = time.monotonic() + 3
        while b"ok" not in text and time.monotonic() < end:
            text += stage.read(4096)
        assert b"AXIS_COUNT:4" in text
        sensor = serial.Serial(ports["sensor"], 2_000_000, timeout=0.2)
        sensor.write(encode_frame(Message("identify", seq=9)))
        dec, got = FrameDecoder(), []
        end = time.monotonic() + 3
        while not got and time.monotonic() < end:
            got = dec.feed(sensor.read(4096))
        assert got[0].name == "identify_reply" and got[0].spec_hash == load_spec().hash
    finally:
        p.send_signal(signal.SIGINT)
        out, err = p.communicate(timeout=10)
    assert p.returncode == 0 and "stopped" in err and "Traceback" not in err


def test_unknown_scene_is_one_clear_line():
    r = subprocess.run([sys.executable, "-m", "dmdsm.host", "sim", "--scene", "banana"],
                       capture_output=True, text=True, timeout=30)
    assert r.returncode == 2
    assert r.stderr.startswith("dmdsm: error: unknown scene 'banana'; known: rig_horizontal")
    assert len(r.stderr.strip().splitlines()) == 1


def test_injected_disconnect_drops_the_port_and_brings_it_back(tmp_path):
    p, ports = start("--faults", "stage.disconnect=1,stage.reconnect_s=0.3",
                     "--link-dir", str(tmp_path))
    try:
        stage = serial.Serial(ports["stage"], 250000, timeout=0.05)
        lost = False
        end = time.monotonic() + 10
        while not lost and time.monotonic() < end:
            try:
                stage.read(100)
            except (serial.SerialException, OSError):
                lost = True  # the host sees the board go away
        assert lost
        stage.close()
        text = b""
        end = time.monotonic() + 5
        while b"AXIS_COUNT:4" not in text and time.monotonic() < end:
            try:  # reconnect by the same name, as a host would
                with serial.Serial(ports["stage"], 250000, timeout=0.2) as again:
                    again.write(b"M115\n")
                    text += again.read(4096) + again.read(4096)
            except (serial.SerialException, OSError):
                time.sleep(0.1)
        assert b"AXIS_COUNT:4" in text
    finally:
        p.send_signal(signal.SIGINT)
        p.communicate(timeout=10)


def test_sim_runs_the_nucleo_elf_on_the_rehosted_h743():
    p, ports = start("--sensor-firmware", "nucleo")
    try:
        link = serial.serial_for_url(ports["sensor"], timeout=0.05)
        link.write(encode_frame(Message("identify", seq=9)))
        dec, got, end = FrameDecoder(), [], time.monotonic() + 5
        while not got and time.monotonic() < end:
            got = [m for m in dec.feed(link.read(4096)) if m.seq == 9]
        assert got and got[0].board.startswith("NUCLEO-H743ZI rev V")
        assert got[0].spec_hash == load_spec().hash
    finally:
        p.send_signal(signal.SIGINT)
        out, err = p.communicate(timeout=10)
    assert p.returncode == 0, err


def test_sim_names_a_firmware_file_it_cannot_run(tmp_path):
    for path, words in ((tmp_path / "missing.elf", "no such firmware ELF"),
                        (tmp_path, "no such firmware ELF")):
        r = subprocess.run([sys.executable, "-m", "dmdsm.host", "sim", "--sensor-firmware",
                            str(path)], capture_output=True, text=True, timeout=30)
        assert r.returncode == 2 and words in r.stderr and len(r.stderr.splitlines()) == 1
    text = tmp_path / "notes.txt"
    text.write_text("not firmware\n")
    an500 = Path(__file__).parents[1] / "firmware/stm32/build/qemu_an500/firmware.elf"
    cut = tmp_path / "cut.elf"
    cut.write_bytes(an500.read_bytes()[:60])
    for path, words in ((text, "not a 32-bit little-endian ARM ELF"),
                        (cut, "truncated or damaged ELF"), (an500, "not an H743 image")):
        r = subprocess.run([sys.executable, "-m", "dmdsm.host", "sim", "--sensor-firmware",
                            str(path)], capture_output=True, text=True, timeout=30)
        assert r.returncode == 2 and words in r.stderr, r.stderr
        assert len(r.stderr.splitlines()) == 1
