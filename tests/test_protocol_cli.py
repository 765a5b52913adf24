"""`dmdsm protocol decode|encode` as a user runs them, and the docs' hand-written frame."""

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np

from dmdsm.protocol import FrameDecoder, Message, encode_frame
from dmdsm.protocol.gen_docs import DOC
from dmdsm.protocol.gen_docs import main as gen_docs_main

ROOT = Path(__file__).resolve().parents[1]


def dmdsm(*args, stdin=b""):
    return subprocess.run([sys.executable, "-m", "dmdsm.host", *args], input=stdin,
                          capture_output=True, cwd=ROOT)


def _doc_example() -> bytes:
    text = DOC.read_text()
    block = text.split("<!-- worked-example -->", 1)[1].split("```")[1]
    return bytes.fromhex(block.strip())


def test_frame_written_by_hand_from_the_docs_decodes():
    r = dmdsm("protocol", "decode", "--json", "-", stdin=_doc_example())
    assert r.returncode == 0, r.stderr
    (obj,) = [json.loads(x) for x in r.stdout.decode().splitlines()]
    assert obj["type"] == "set_config" and obj["seq"] == 4
    assert obj["fields"]["n_samples"] == 1024 and obj["fields"]["trigger_timeout_ms"] == 1000
    summary = json.loads(r.stderr.decode().splitlines()[-1])["summary"]
    assert summary["frames"] == 1 and summary["crc_errors"] == 0


def test_docs_message_reference_is_generated_from_the_spec():
    assert gen_docs_main(["--check"]) == 0


def _capture(tmp_path: Path) -> tuple[Path, list[Message]]:
    msgs = [Message("ping", seq=1, nonce=5),
            Message("waveform", seq=0, shot_id=0, timestamp=10, trigger_phase=3, n_average=2,
                    pretrigger=4, sample_rate_div=1, sample_format=0, modality=1,
                    triggers_skipped=0, adc_overruns=0, integrity_faults=0,
                    sync_steps=0, sync_steps_a=0,
                    samples=np.arange(100, dtype="<u2")),
            Message("nak", seq=1, flags=1, command=4, error=3, detail=1)]
    data = bytearray(b"".join(encode_frame(m) for m in msgs))
    data[len(encode_frame(msgs[0])) + 40] ^= 0xFF  # damage the waveform
    path = tmp_path / "cap.bin"
    path.write_bytes(bytes(data) + b"\x05\x41")  # and leave an unfinished frame
    return path, msgs


def test_decode_table_shows_messages_errors_and_summary(tmp_path):
    path, _ = _capture(tmp_path)
    r = dmdsm("protocol", "decode", str(path))
    out = r.stdout.decode()
    assert r.returncode == 0
    assert re.search(r"^\s+1\s+1\s+--\s+ping\s+nonce=5$", out, re.M)
    assert "! crc_errors" in out or "! malformed" in out
    assert re.search(r"nak\s+command=4 error=out_of_range detail=1", out)
    assert out.splitlines()[-1].startswith("2 messages in ")
    assert "2 bytes of an unfinished frame" in out.splitlines()[-1]


def test_decode_json_then_encode_reproduces_the_frames(tmp_path):
    msgs = [Message("set_config", seq=9, n_samples=512, sample_rate_div=2, n_average=4,
                    pretrigger=8, trigger_edge=1, modality=1, sample_format=1,
                    trigger_timeout_ms=0),
            Message("waveform", seq=3, shot_id=3, timestamp=2**40, trigger_phase=1,
                    n_average=4, pretrigger=8, sample_rate_div=2, sample_format=1, modality=1,
                    triggers_skipped=1, adc_overruns=0, integrity_faults=0,
                    sync_steps=0, sync_steps_a=0,
                    samples=np.arange(50, dtype="<u4") * 999)]
    data = b"".join(encode_frame(m) for m in msgs)
    r = dmdsm("protocol", "decode", "--json", "-", stdin=data)
    r2 = dmdsm("protocol", "encode", stdin=r.stdout)
    assert r2.returncode == 0, r2.stderr
    assert r2.stdout == data
    assert FrameDecoder().feed(r2.stdout) == msgs


def test_encode_accepts_enum_names_and_writes_a_file(tmp_path):
    line = json.dumps({"type": "set_config", "seq": 1, "fields": {
        "n_samples": 1024, "sample_rate_div": 1, "n_average": 1, "pretrigger": 0,
        "trigger_edge": "falling", "modality": "us", "sample_format": "u16_mean",
        "trigger_timeout_ms": 5}})
    out = tmp_path / "f.bin"
    r = dmdsm("protocol", "encode", "-o", str(out), stdin=line.encode())
    assert r.returncode == 0, r.stderr
    (m,) = FrameDecoder().feed(out.read_bytes())
    assert m.trigger_edge == 1 and m.modality == 1


def test_user_errors_are_one_line_without_traceback(tmp_path):
    cases = [
        (("protocol", "decode", str(tmp_path / "missing.bin")), b"", "cannot read capture"),
        (("protocol", "encode"), b"{not json\n", "line 1: not JSON"),
        (("protocol", "encode"), b'{"type": "pingg"}\n', "line 1: unknown message type"),
        (("protocol", "encode"), b'{"type": "ping", "fields": {}}\n', "missing nonce"),
        (("protocol", "encode"), b'{"type": "set_config", "fields": {"trigger_edge": "up"}}\n',
         "'up' is not one of rising, falling"),
        (("protocol", "encode"), bytes(range(128, 256)) * 4, "not UTF-8 text"),  # a raw capture
        (("protocol", "encode", "--json"), b'{"type": "ping"}\n', "--json needs -o FILE"),
    ]
    for args, stdin, text in cases:
        r = dmdsm(*args, stdin=stdin)
        err = r.stderr.decode()
        assert r.returncode == 2, (args, err)
        assert text in err and "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_arbitrary_garbage_decodes_without_crashing():
    rng = np.random.default_rng(0)
    r = dmdsm("protocol", "decode", "-", stdin=rng.integers(0, 256, 200_000, dtype=np.uint8)
              .tobytes())
    assert r.returncode == 0 and "Traceback" not in r.stderr.decode()
