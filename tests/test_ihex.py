"""The Intel HEX check that runs before avrdude erases the stage board (dmdsm flash marlin)."""

from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dmdsm.host.commands.ihex import FLASH_BYTES, HexError, check_hex


def record(kind: int, address: int, payload: bytes) -> str:
    body = bytes([len(payload), address >> 8 & 0xFF, address & 0xFF, kind]) + payload
    return ":" + (body + bytes([-sum(body) & 0xFF])).hex().upper()


def image(data: bytes, start: int = 0) -> str:
    """data at `start` in 16-byte records, with extended linear address records as needed."""
    lines, upper = [], -1
    for i in range(0, len(data), 16):
        a = start + i
        if a >> 16 != upper:
            upper = a >> 16
            lines.append(record(4, 0, upper.to_bytes(2, "big")))
        lines.append(record(0, a & 0xFFFF, data[i:i + 16]))
    return "\n".join(lines + [record(1, 0, b"")]) + "\n"


@settings(max_examples=60, deadline=None)
@given(data=st.binary(min_size=1, max_size=3000), start=st.integers(0, FLASH_BYTES - 3000))
def test_a_well_formed_image_is_accepted_with_its_size(tmp_path_factory, data, start):
    path = tmp_path_factory.mktemp("h") / "m.hex"
    path.write_text(image(data, start))
    assert check_hex(path) == len(data)


@settings(max_examples=200, deadline=None)
@given(blob=st.binary(max_size=400))
def test_any_bytes_are_accepted_or_refused_in_one_line(tmp_path_factory, blob):
    path = tmp_path_factory.mktemp("h") / "x.hex"
    path.write_bytes(blob)
    try:
        check_hex(path)
    except HexError as e:
        assert "\n" not in str(e)


@settings(max_examples=60, deadline=None)
@given(data=st.binary(min_size=16, max_size=200), where=st.integers(0, 10**6),
       digit=st.sampled_from("0123456789ABCDEF"))
def test_one_changed_digit_is_caught(tmp_path_factory, data, where, digit):
    text = image(data)
    hexdigits = [i for i, c in enumerate(text) if c in "0123456789ABCDEF"]
    i = hexdigits[where % len(hexdigits)]
    if text[i] == digit:
        return
    path = tmp_path_factory.mktemp("h") / "m.hex"
    path.write_text(text[:i] + digit + text[i + 1:])
    with pytest.raises(HexError):
        check_hex(path)


@pytest.mark.parametrize("content, words", [
    (b"\x7fELF\x01\x01\x01" + bytes(100), "is an ELF file: flash the .hex beside it"),
    (image(b"\x0c\x94" * 8).rsplit(":", 1)[0].encode(), "no end-of-file record"),
    (image(b"\x00" * 16, FLASH_BYTES - 8).encode(), "writes past the ATmega2560's 256 KiB"),
    ((record(1, 0, b"") + "\n").encode(), "holds no program data"),
    (b"hello\n", "line 1 is not an Intel HEX record"),
])
def test_wrong_files_are_named(tmp_path, content, words):
    path = tmp_path / "m.hex"
    path.write_bytes(content)
    with pytest.raises(HexError, match=words.replace(".", r"\.")):
        check_hex(path)


def test_the_built_marlin_image_if_present_is_accepted():
    """The image `make check-marlin` builds (not in CI: Marlin's code is not committed)."""
    built = Path(__file__).resolve().parents[1] / "build/marlin/Marlin.hex"
    if built.exists():
        assert 30_000 < check_hex(built) < FLASH_BYTES
