"""`dmdsm flash stm32`: build the sensor firmware and flash it (OpenOCD, st-flash, pyocd, dfu)."""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
from pathlib import Path

from .ihex import HexError, check_hex

REPO = Path(__file__).resolve().parents[2]
TOOLS = {  # --tool -> (program, Debian/PyPI package, make FLASHER)
    "openocd": ("openocd", "apt-get install openocd", "openocd"),
    "stlink": ("st-flash", "apt-get install stlink-tools", "stlink"),
    "pyocd": ("pyocd", "pip install pyocd", "pyocd"),
    "dfu": ("dfu-util", "apt-get install dfu-util", "dfu"),
}
# --nucleo -> (make NUCLEO=, build folder); the -ZI2 has LD2 on PE1 (docs/firmware.md)
NUCLEOS = {"zi": ("ZI", "nucleo_h743zi"), "zi2": ("ZI2", "nucleo_h743zi2")}
NO_BOARD = ("open failed", "unable to open", "no device found", "no st-link", "couldn't find",
            "no dfu capable", "no connected debug probes", "libusb_open")


class FlashError(Exception):
    """Flashing failed; the message says what to do."""


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register `flash stm32`."""
    p = sub.add_parser("flash", help="build and flash firmware")
    psub = p.add_subparsers(dest="target", required=True)
    s = psub.add_parser("stm32", help="the sensor board (NUCLEO-H743ZI / -ZI2)")
    s.add_argument("--tool", choices=sorted(TOOLS), default="openocd",
                   help="flashing tool (default openocd, board/st_nucleo_h743zi.cfg)")
    s.add_argument("--nucleo", choices=sorted(NUCLEOS), default="zi",
                   help="board variant: zi = NUCLEO-H743ZI (LD2 on PB7, default), zi2 = "
                        "NUCLEO-H743ZI2 (LD2 on PE1); only the blue LED differs")
    s.add_argument("--json", action="store_true", help="machine-readable output")
    s.set_defaults(func=cmd_flash_stm32)
    m = psub.add_parser("marlin", help="the stage board (Chiron, ATmega2560) with avrdude")
    m.add_argument("hex", type=Path, help="firmware .hex built from the patched Marlin")
    m.add_argument("--port", required=True, help="serial port of the board, e.g. /dev/ttyUSB0")
    m.add_argument("--json", action="store_true", help="machine-readable output")
    m.set_defaults(func=cmd_flash_marlin)


def cmd_flash_stm32(args: argparse.Namespace) -> int:
    """Build firmware/stm32 for the NUCLEO and flash it; one clear line on failure."""
    program, install, flasher = TOOLS[args.tool]
    if not (REPO / "firmware/stm32/Makefile").exists():
        raise FlashError("firmware sources not found: run from a dmdsm checkout")
    if shutil.which(program) is None:
        raise FlashError(f"{program} not found: {install} (or choose --tool "
                         f"{'|'.join(t for t in TOOLS if t != args.tool)})")
    variant, build = NUCLEOS[args.nucleo]
    r = subprocess.run(["make", "-C", str(REPO / "firmware/stm32"), "BOARD=nucleo_h743zi",
                        f"NUCLEO={variant}", f"FLASHER={flasher}", "flash"],
                       capture_output=True, text=True)
    out = (r.stdout + r.stderr).lower()
    if r.returncode:
        if any(s in out for s in NO_BOARD):
            raise FlashError(f"no board found by {program}: plug the NUCLEO's ST-LINK USB "
                             f"(CN1), check the cable and udev permissions, then retry")
        last = (r.stderr or r.stdout).strip().splitlines()[-1:] or ["?"]
        raise FlashError(f"{program} failed: {last[0]}")
    elf = f"firmware/stm32/build/{build}/firmware.elf"
    print(json.dumps({"flashed": elf, "board": build, "tool": program})
          if args.json else f"flashed {elf} with {program}")
    return 0


AVRDUDE_HINTS = (  # (text in avrdude's output, what to tell the user)
    ("permission denied", "no permission on {port}: add yourself to the dialout group "
                          "(sudo usermod -aG dialout $USER) and log in again"),
    ("no such file or directory", "{port} does not exist: check the cable; `dmdsm` lists "
                                  "ports with `python -m serial.tools.list_ports`"),
    ("device or resource busy", "{port} is in use: close OctoPrint, Pronterface or `dmdsm` "
                                "sessions that hold it"),
    ("not in sync", "the board does not answer on {port}: wrong port, or the bootloader did "
                    "not start (press reset just before flashing)"),
    ("timeout", "the board does not answer on {port}: wrong port, or the bootloader did not "
                "start (press reset just before flashing)"),
    ("verification error", "flash verification failed: retry; if it persists the board's "
                           "flash or bootloader is damaged"),
)


def cmd_flash_marlin(args: argparse.Namespace) -> int:
    """Flash a Marlin .hex to the Chiron's ATmega2560 with avrdude (wiring/stk500v2 bootloader)."""
    if not args.hex.is_file():
        raise FlashError(f"{args.hex} not found: build the patched Marlin first (docs/marlin.md)")
    try:
        check_hex(args.hex)  # before avrdude erases the board's flash
    except HexError as e:
        raise FlashError(str(e)) from None
    if shutil.which("avrdude") is None:
        raise FlashError("avrdude not found: apt-get install avrdude")
    cmd = ["avrdude", "-p", "atmega2560", "-c", "wiring", "-P", args.port, "-b", "115200",
           "-D", "-U", f"flash:w:{args.hex}:i"]
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode:
        out = (r.stdout + r.stderr).lower()
        for needle, hint in AVRDUDE_HINTS:
            if needle in out:
                raise FlashError(hint.format(port=args.port))
        last = (r.stderr or r.stdout).strip().splitlines()[-1:] or ["?"]
        raise FlashError(f"avrdude failed: {last[0]}")
    print(json.dumps({"flashed": str(args.hex), "board": "atmega2560", "port": args.port,
                      "tool": "avrdude"}) if args.json else
          f"flashed {args.hex} to the ATmega2560 on {args.port}")
    return 0
