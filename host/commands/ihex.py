"""Checks an Intel HEX image for the ATmega2560 before avrdude sees it: a wrong file is named."""

from __future__ import annotations

from pathlib import Path

FLASH_BYTES = 256 * 1024   # ATmega2560 program memory
MAX_FILE_BYTES = 2 << 20   # a 256 KiB image is ~720 KB of hex text


class HexError(ValueError):
    """Not a flashable image; str() is one line saying what it is instead."""


def check_hex(path: Path) -> int:
    """Bytes of program data in an Intel HEX file, after checking every record's length and
    checksum, the end record and that the image fits the ATmega2560's flash."""
    if path.stat().st_size > MAX_FILE_BYTES:
        raise HexError(f"{path} is {path.stat().st_size} bytes: far larger than any ATmega2560 "
                       f"image (a Marlin .hex is under 1 MB)")
    raw = path.read_bytes()
    if raw.startswith(b"\x7fELF"):
        raise HexError(f"{path} is an ELF file: flash the .hex beside it (Marlin.hex), or "
                       f"convert it with avr-objcopy -O ihex -R .eeprom {path.name} Marlin.hex")
    base = data = 0
    ended = False
    for n, line in enumerate(raw.splitlines(), 1):
        line = line.strip()
        if not line:
            continue
        where = f"{path} line {n}"
        if ended:
            raise HexError(f"{where}: records after the end-of-file record")
        try:
            rec = bytes.fromhex(line[1:].decode("ascii"))
        except (UnicodeDecodeError, ValueError):
            rec = b""
        if not line.startswith(b":") or len(rec) < 5 or len(rec) != rec[0] + 5:
            raise HexError(f"{where} is not an Intel HEX record: is {path.name} a Marlin "
                           f".hex from build_debian.sh (docs/marlin.md)?")
        if sum(rec) & 0xFF:
            raise HexError(f"{where} fails its checksum: the file is damaged; build or copy "
                           f"it again")
        count, address, kind, payload = rec[0], rec[1] << 8 | rec[2], rec[3], rec[4:-1]
        if kind == 0:
            if base + address + count > FLASH_BYTES:
                raise HexError(f"{where} writes past the ATmega2560's {FLASH_BYTES // 1024} "
                               f"KiB of flash: not an image for the Chiron's board")
            data += count
        elif kind == 1:
            ended = True
        elif kind == 2 and count == 2:  # extended segment address: x16
            base = (payload[0] << 8 | payload[1]) << 4
        elif kind == 4 and count == 2:  # extended linear address: upper 16 bits
            base = (payload[0] << 8 | payload[1]) << 16
        elif kind not in (3, 5):  # start addresses mean nothing to an AVR; skipped
            raise HexError(f"{where} has an unknown record type {kind}")
    if not ended:
        raise HexError(f"{path} has no end-of-file record: it was cut short; build or copy it "
                       f"again")
    if not data:
        raise HexError(f"{path} holds no program data")
    return data
