"""`dmdsm flash stm32` says clearly when the tool or the board is missing."""

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def run(tmp_path, *args, fake_tool=None, target="stm32"):
    bindir = tmp_path / "bin"
    bindir.mkdir(exist_ok=True)
    for tool in ("make", "mkdir", "arm-none-eabi-gcc", "arm-none-eabi-objcopy",
                 "arm-none-eabi-size"):
        real = subprocess.run(["which", tool], capture_output=True, text=True).stdout.strip()
        if real:
            (bindir / tool).symlink_to(real)
    if fake_tool:
        name, script = fake_tool
        (bindir / name).write_text(script)
        (bindir / name).chmod(0o755)
    env = {**os.environ, "PATH": str(bindir)}  # only the tools linked above
    return subprocess.run([sys.executable, "-m", "dmdsm.host", "flash", target, *args],
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


def test_flash_zi2_builds_and_flashes_the_zi2_variant(tmp_path):
    log = tmp_path / "args.txt"
    fake = f"#!/bin/sh\necho \"$@\" > {log}\nexit 0\n"
    r = run(tmp_path, "--nucleo", "zi2", "--json", fake_tool=("openocd", fake))
    assert r.returncode == 0, r.stderr
    assert "program build/nucleo_h743zi2/firmware.elf verify reset exit" in log.read_text()
    assert '"board": "nucleo_h743zi2"' in r.stdout


def test_flash_marlin_explains_avrdude_failures(tmp_path):
    hexfile = tmp_path / "marlin.hex"
    hexfile.write_text(":020000000C945E\n:00000001FF\n")  # one jmp word, then the end
    cases = [
        ("avrdude: ser_open(): can't open device /dev/ttyUSB9: Permission denied",
         "no permission on /dev/ttyUSB9: add yourself to the dialout group"),
        ("avrdude: stk500v2_ReceiveMessage(): timeout", "the board does not answer"),
    ]
    for i, (msg, hint) in enumerate(cases):
        d = tmp_path / f"case{i}"
        d.mkdir()
        fake = f'#!/bin/sh\necho "{msg}" >&2\nexit 1\n'
        r = run(d, "--port", "/dev/ttyUSB9", str(hexfile), fake_tool=("avrdude", fake),
                target="marlin")
        assert r.returncode == 2 and hint in r.stderr and "Traceback" not in r.stderr


def test_flash_marlin_passes_the_right_avrdude_arguments(tmp_path):
    hexfile = tmp_path / "marlin.hex"
    hexfile.write_text(":020000000C945E\n:00000001FF\n")  # one jmp word, then the end
    log = tmp_path / "args.txt"
    r = run(tmp_path, "--port", "/dev/ttyUSB0", str(hexfile),
            fake_tool=("avrdude", f"#!/bin/sh\necho \"$@\" > {log}\n"), target="marlin")
    assert r.returncode == 0, r.stderr
    assert log.read_text().split() == ["-p", "atmega2560", "-c", "wiring", "-P", "/dev/ttyUSB0",
                                       "-b", "115200", "-D", "-U", f"flash:w:{hexfile}:i"]


def test_flash_marlin_refuses_a_file_that_is_not_an_image_before_avrdude_runs(tmp_path):
    """avrdude -D would write whatever it parses: an ELF or a cut file is named first."""
    elf = tmp_path / "Marlin.elf"
    elf.write_bytes(b"\x7fELF" + bytes(60))
    log = tmp_path / "ran.txt"
    r = run(tmp_path, "--port", "/dev/ttyUSB0", str(elf),
            fake_tool=("avrdude", f"#!/bin/sh\ntouch {log}\n"), target="marlin")
    assert r.returncode == 2 and "is an ELF file: flash the .hex beside it" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and not log.exists()
