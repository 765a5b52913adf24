"""Golden vectors, generated-C freshness and the C codec checked against the Python one."""

import json
import re
import subprocess
from pathlib import Path

from hypothesis import given, settings
from hypothesis import strategies as st

from dmdsm.protocol import (
    FrameDecoder,
    FrameError,
    Message,
    encode_frame,
    from_jsonable,
    pack_payload,
    to_jsonable,
)
from dmdsm.protocol.gen_c import stale_files
from dmdsm.protocol.spec import parse_spec
from dmdsm.protocol.vectors import VECTOR_DIR, build, c_format
from strategies import SPEC, any_message

ROOT = Path(__file__).resolve().parents[1]
GOLDEN = json.loads((VECTOR_DIR / "golden.json").read_text())


def test_golden_vectors_decode_to_their_meaning_and_encode_back():
    assert len(GOLDEN) >= 25
    for rec in GOLDEN:
        frame = bytes.fromhex(rec["frame"])
        dec = FrameDecoder(report_errors=True)
        items = dec.feed(frame)
        if "reject" in rec:
            assert [type(i) for i in items] == [FrameError], rec["name"]
            assert items[0].kind == rec["reject"], rec["name"]
            continue
        (msg,) = items
        assert to_jsonable(msg) == rec["message"], rec["name"]
        assert encode_frame(from_jsonable(rec["message"])) == frame, rec["name"]


def test_golden_files_are_what_the_vector_builder_makes():
    records, lines = build()
    assert records == GOLDEN
    text = (VECTOR_DIR / "golden.txt").read_text().splitlines()
    assert [ln for ln in text if not ln.startswith("#")] == lines


def test_every_message_type_has_a_golden_vector():
    names = {rec["message"]["type"] for rec in GOLDEN if "message" in rec}
    assert names == set(SPEC.by_name)


def test_generated_c_is_not_stale():
    assert stale_files() == [], "run: python -m dmdsm.protocol.gen_c"


def test_spec_hash_is_in_the_c_header_and_changes_with_the_spec():
    header = (ROOT / "protocol/c/dmdsm_spec.h").read_text()
    m = re.search(r"DMDSM_SPEC_HASH UINT64_C\(0x([0-9a-f]{16})\)", header)
    assert m and int(m.group(1), 16) == SPEC.hash
    edited = SPEC.text.replace('name = "nonce", type = "u32"', 'name = "nonce", type = "u16"', 1)
    assert parse_spec(edited).hash != SPEC.hash


def _c_decode(tool: Path, data: bytes) -> list[str]:
    r = subprocess.run([str(tool), "decode"], input=data, capture_output=True, check=True)
    return r.stdout.decode().splitlines()


def _py_decode(data: bytes) -> list[str]:
    dec = FrameDecoder(report_errors=True)
    lines = []
    for item in dec.feed(data):
        if isinstance(item, FrameError):
            lines.append(f"ERR {item.kind}")
        else:
            lines.append(f"FRAME {item.spec.id} {item.seq} {item.flags} {c_format(item)}")
    s = dec.stats
    lines.append(f"STATS frames={s.frames} crc_errors={s.crc_errors} malformed={s.malformed} "
                 f"oversize={s.oversize} unknown_type={s.unknown_type} "
                 f"bad_version={s.bad_version}")
    return lines


def test_c_decoder_agrees_on_the_golden_stream(proto_tool):
    stream = b"".join(bytes.fromhex(r["frame"]) for r in GOLDEN)
    assert _c_decode(proto_tool, stream) == _py_decode(stream)


@settings(max_examples=150)
@given(st.lists(st.one_of(any_message.map(encode_frame), st.binary(max_size=40)),
                max_size=8), st.data())
def test_c_and_python_decoders_agree_on_random_streams(proto_tool, parts, data):
    stream = bytearray(b"".join(parts))
    for _ in range(data.draw(st.integers(0, 3))):
        if stream:
            i = data.draw(st.integers(0, len(stream) - 1))
            stream[i] = data.draw(st.integers(0, 255))
    assert _c_decode(proto_tool, bytes(stream)) == _py_decode(bytes(stream))


@settings(max_examples=100)
@given(st.lists(any_message, min_size=1, max_size=10))
def test_c_encoder_matches_the_python_encoder(proto_tool, msgs):
    lines = "".join(f"{m.spec.id} {m.seq} {m.flags} {pack_payload(m).hex()}\n" for m in msgs)
    r = subprocess.run([str(proto_tool), "encode"], input=lines.encode(), capture_output=True,
                       check=True)
    assert r.stdout.decode().split() == [encode_frame(m).hex() for m in msgs]


def test_c_decoder_counts_oversize_like_python(proto_tool):
    stream = (b"\x00" + b"\x41" * (SPEC.max_encoded + 1) + b"\x00"
              + encode_frame(Message("ping", seq=1, nonce=2)))
    out = _c_decode(proto_tool, stream)
    assert out == _py_decode(stream)
    assert out[0] == "ERR oversize" and out[1].startswith("FRAME 1 1 0")
