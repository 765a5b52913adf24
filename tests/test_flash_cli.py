"""`dmdsm flash stm32` says clearly when the tool or the board is missing."""

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def run(tmp_path, *args, fake_tool=None):
    bindir = tmp_path / "bin"
    bindir.mkdir(exist_ok=True)
    for tool in ("make", "arm-none-eabi-gcc", "arm-none-eabi-objcopy", "arm-none-eabi-size"):
        real = subprocess.run(["which", tool], capture_output=True, text=True).stdout.strip()
        if real:
            (bindir / tool).symlink_to(real)
    if fake_tool:
        name, script = fake_tool
        (bindir / name).write_text(script)
        (bindir / name).chmod(0o755)
    env = {**os.environ, "PATH": str(bindir)}  # only the tools linked above
    return subprocess.run([sys.executable, "-m", "dmdsm.host", "flash", "stm32", *args],
                          capture_output=True, text=True, env=env, cwd=ROOT)


def test_missing_tool_names_the_package_and_alternatives(tmp_path):
    r = run(tmp_path, "--tool", "openocd")
    assert r.returncode == 2
    assert r.stderr.strip() == ("dmdsm: error: openocd not found: apt-get install openocd "
                                "(or choose --tool stlink|pyocd|dfu)")


def test_no_board_attached_is_one_clear_line(tmp_path):
    fake = "#!/bin/sh\necho 'Error: open failed' >&2\nexit 1\n"
    r = run(tmp_path, fake_tool=("openocd", fake))
    assert r.returncode == 2, r.stderr
    assert "no board found by openocd: plug the NUCLEO" in r.stderr
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1


def test_flash_runs_the_tool_on_the_built_elf(tmp_path):
    log = tmp_path / "args.txt"
    fake = f"#!/bin/sh\necho \"$@\" > {log}\nexit 0\n"
    r = run(tmp_path, fake_tool=("openocd", fake))
    assert r.returncode == 0, r.stderr
    args = log.read_text()
    assert "board/st_nucleo_h743zi.cfg" in args
    assert "program build/nucleo_h743zi/firmware.elf verify reset exit" in args
