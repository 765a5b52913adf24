"""The rehost's ELF reader on hostile files: segments or one ValueError, nothing else."""

from pathlib import Path

from hypothesis import example, given, settings
from hypothesis import strategies as st

from dmdsm.sim.boards.sensor.rehost.h743 import load_elf

REPO = Path(__file__).resolve().parents[2]
ELF = (REPO / "firmware/stm32/build/qemu_an500/firmware.elf").read_bytes()[:4096]


@settings(max_examples=200, deadline=None)
@given(cut=st.integers(0, len(ELF)), flips=st.lists(st.tuples(st.integers(0, 255),
                                                              st.integers(0, 255)), max_size=8))
@example(cut=52, flips=[])
@example(cut=len(ELF), flips=[(44, 0xFF), (45, 0xFF)])
def test_damaged_elf_is_one_value_error(tmp_path_factory, cut, flips):
    data = bytearray(ELF[:cut])
    for pos, value in flips:
        if pos < len(data):
            data[pos] = value
    path = tmp_path_factory.mktemp("elf") / "f.elf"
    path.write_bytes(bytes(data))
    try:
        segments = load_elf(path)
    except ValueError as e:
        assert str(e).startswith(str(path))
    else:
        assert all(isinstance(a, int) and isinstance(b, bytes) for a, b in segments)
