"""Golden vectors shared by the Python and C tests (`python -m dmdsm.protocol.vectors` rewrites).

golden.json holds each vector's meaning (message as JSON, frame hex); golden.txt holds the
same frames in a line format the C tests parse: name|type|seq|flags|payload|frame|fields,
where fields is the C codec's dmdsm_msg_format text. Reject vectors have type REJECT and the
decoder counter they must bump in the seq column.
"""

from __future__ import annotations

import json
import sys
import zlib
from pathlib import Path

import numpy as np

from .frame import encode_raw
from .messages import Message, pack_payload, to_jsonable
from .spec import SCALARS, load_spec

VECTOR_DIR = Path(__file__).with_name("vectors")


def c_format(msg: Message) -> str:
    """The text the C codec's dmdsm_msg_format prints for this message (cross-language check)."""
    parts = []
    payload = pack_payload(msg)
    off = 0
    for fs in msg.spec.scalar_fields:
        v = msg.fields[fs.name]
        parts.append(f"{fs.name}={f'{v:.9g}' if fs.type == 'f32' else int(v)}")
        off += SCALARS[fs.type][1]
    tail = msg.spec.tail
    if tail is not None:
        rest = payload[off:]
        parts.append(f"{tail.name}:len={len(rest)}:crc={zlib.crc32(rest):08x}")
    return " ".join(parts)


def _messages() -> list[tuple[str, Message]]:
    rng = np.random.default_rng(20261122)
    wave16 = (2048 + 300 * np.sin(np.arange(64) / 3.0) + rng.normal(0, 5, 64)).astype("<u2")
    wave32 = (wave16.astype("<u4") * 16)
    cfg = dict(n_samples=1024, sample_rate_div=1, n_average=16, pretrigger=64, trigger_edge=0,
               modality=0, sample_format=0, trigger_timeout_ms=1000)
    wf = dict(shot_id=7, timestamp=480_000_123, trigger_phase=37, n_average=16, pretrigger=8,
              sample_rate_div=1, modality=1, triggers_skipped=2, adc_overruns=0, integrity_faults=3,
              sync_steps=40_321, sync_steps_a=1_234)
    return [
        ("ping", Message("ping", seq=1, nonce=0xDEADBEEF)),
        ("pong", Message("pong", seq=1, flags=1, nonce=0xDEADBEEF)),
        ("identify", Message("identify", seq=2)),
        ("identify_reply", Message(
            "identify_reply", seq=2, flags=1, protocol_version=1, fw_major=0, fw_minor=1,
            fw_patch=0, spec_hash=load_spec().hash, tick_hz=240_000_000,
            adc_rate_hz=3_333_333, max_samples=8192, max_payload=16448,
            board="NUCLEO-H743ZI rev V")),
        ("get_config", Message("get_config", seq=3)),
        ("set_config", Message("set_config", seq=4, **cfg)),
        ("config", Message("config", seq=3, flags=1, **cfg)),
        ("arm_continuous", Message("arm", seq=5, n_shots=0)),
        ("arm_retransmit", Message("arm", seq=6, flags=2, n_shots=100)),
        ("disarm", Message("disarm", seq=0xFFFF)),
        ("get_status", Message("get_status", seq=8)),
        ("status", Message(
            "status", seq=8, flags=1, state=1, last_error=7, uptime_ms=123456,
            shots_remaining=42, triggers=1000, shots_sent=990, triggers_skipped=10,
            adc_overruns=0, no_trigger_timeouts=1, rx_frames=50, rx_crc_errors=2,
            rx_malformed=1, rx_oversize=0, integrity_faults=4)),
        ("clock_sync", Message("clock_sync", seq=9, host_time_ns=1_763_800_000_123_456_789)),
        ("clock_sync_reply", Message("clock_sync_reply", seq=9, flags=1,
                                     host_time_ns=1_763_800_000_123_456_789,
                                     device_ticks=0x1_0000_0001)),
        ("ack", Message("ack", seq=4, flags=1, command=0x04)),
        ("nak", Message("nak", seq=4, flags=1, command=0x04, error=3, detail=1)),
        ("waveform_u16", Message("waveform", seq=10, sample_format=0, samples=wave16, **wf)),
        ("waveform_u32", Message("waveform", seq=11, sample_format=1, samples=wave32, **wf)),
        ("waveform_empty", Message("waveform", seq=12, sample_format=0,
                                   samples=np.zeros(0, "<u2"), **wf)),
        ("waveform_zeros_600", Message("waveform", seq=13, sample_format=0,
                                       samples=np.zeros(300, "<u2"), **wf)),
        ("waveform_no_zero_600", Message("waveform", seq=14, sample_format=0,
                                         samples=np.full(300, 0x0101, "<u2"), **wf)),
        ("log", Message("log", seq=0, level=2, code=7, text="no trigger within 1000 ms")),
        ("motion_sync", Message("motion_sync", seq=1, burst_id=3, first_edge=0x1_2345_6789,
                                last_edge=0x1_2C0D_4BA9, edges=5120, input=0)),
        ("motion_sync_a", Message("motion_sync", seq=2, burst_id=4, first_edge=0x1_3000_0000,
                                  last_edge=0x1_3A00_0000, edges=3200, input=1)),
    ]


def _rejects() -> list[tuple[str, str, bytes]]:
    good = encode_raw(0x01, 1, 0, b"\xef\xbe\xad\xde")
    flipped = bytearray(good)
    flipped[8] ^= 0x10
    return [
        ("reject_crc", "crc_errors", bytes(flipped)),
        ("reject_unknown_type", "unknown_type", encode_raw(0x7E, 1, 0, b"")),
        ("reject_bad_version", "bad_version", encode_raw(0x01, 1, 0, b"\0\0\0\0", version=2)),
        ("reject_short_payload", "malformed", encode_raw(0x01, 1, 0, b"\x01\x02")),
        ("reject_runt", "malformed", b"\x00\x03\x01\x02\x00"),
        ("reject_bad_cobs", "malformed", b"\x00\x09\x01\x02\x00"),
        ("reject_bad_sample_format", "malformed", encode_raw(0xA0, 1, 0, bytes(20) + b"\x07"
                                                             + bytes(17) + b"\x01\x02")),
    ]


def build() -> tuple[list[dict], list[str]]:
    """The golden vectors as (JSON records, golden.txt lines)."""
    records, lines = [], []
    for name, msg in _messages():
        frame = encode_raw(msg.spec.id, msg.seq, msg.flags, pack_payload(msg))
        records.append({"name": name, "frame": frame.hex(), "message": to_jsonable(msg)})
        lines.append("|".join([name, str(msg.spec.id), str(msg.seq), str(msg.flags),
                               pack_payload(msg).hex(), frame.hex(), c_format(msg)]))
    for name, kind, frame in _rejects():
        records.append({"name": name, "frame": frame.hex(), "reject": kind})
        lines.append("|".join([name, "REJECT", kind, "", "", frame.hex(), ""]))
    return records, lines


def main() -> int:
    """Rewrite protocol/vectors/golden.{json,txt}."""
    records, lines = build()
    VECTOR_DIR.mkdir(exist_ok=True)
    (VECTOR_DIR / "golden.json").write_text(json.dumps(records, indent=1) + "\n")
    (VECTOR_DIR / "golden.txt").write_text(
        "# name|type|seq|flags|payload_hex|frame_hex|fields (see protocol/vectors.py)\n"
        + "\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
