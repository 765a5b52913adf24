"""Wire framing 0x00 | COBS(header | payload | CRC-32) | 0x00; streaming decoder with counters."""

from __future__ import annotations

import zlib
from dataclasses import asdict, dataclass

from cobs import cobs

from .messages import Message, MessageError, pack_payload, unpack_payload
from .spec import CRC_SIZE, HEADER, Spec, load_spec

DELIMITER = b"\x00"
MIN_RAW = HEADER.size + CRC_SIZE


def cobs_extension_loaded() -> bool:
    """True if the `cobs` package runs its C extension (the pure-Python fallback is ~40x slower)."""
    return bool(getattr(cobs, "_using_extension", False))


def encode_raw(type_id: int, seq: int, flags: int, payload: bytes, version: int = 1) -> bytes:
    """Frame bytes (with both delimiters) for an already packed payload."""
    raw = HEADER.pack(version, type_id, flags, seq) + payload
    raw += zlib.crc32(raw).to_bytes(4, "little")
    return b"\x00" + cobs.encode(raw) + b"\x00"


def encode_frame(msg: Message, spec: Spec | None = None) -> bytes:
    """Frame bytes (with both delimiters) for a message."""
    spec = spec or load_spec()
    payload = pack_payload(msg)
    if len(payload) > spec.max_payload:
        raise MessageError(f"{msg.name}: payload {len(payload)} B exceeds the "
                           f"{spec.max_payload} B maximum")
    return encode_raw(msg.spec.id, msg.seq, msg.flags, payload, spec.version)


@dataclass
class DecodeStats:
    """Counters of a decoder: good frames and every kind of rejected frame."""

    frames: int = 0        #: messages decoded
    crc_errors: int = 0    #: CRC-32 mismatch
    malformed: int = 0     #: bad COBS, shorter than header+CRC, or payload length wrong for type
    oversize: int = 0      #: longer than the spec's maximum frame; discarded unread
    unknown_type: int = 0  #: CRC good, type id not in the spec
    bad_version: int = 0   #: CRC good, protocol version not ours
    bytes: int = 0         #: bytes fed

    @property
    def errors(self) -> int:
        """All rejected frames."""
        return (self.crc_errors + self.malformed + self.oversize + self.unknown_type
                + self.bad_version)

    def as_dict(self) -> dict[str, int]:
        """Counters as a plain dict (for JSON and status lines)."""
        return asdict(self)


@dataclass(frozen=True)
class FrameError:
    """A rejected frame: kind is a DecodeStats counter name; offset/length in stream bytes."""

    kind: str
    offset: int
    length: int
    detail: str = ""


class FrameDecoder:
    """Streaming decoder: feed any chunk of bytes, get messages; never raises on input.

    Memory is bounded by the spec's maximum encoded frame plus one fed chunk. With
    report_errors=True, feed() also returns a FrameError for each rejected frame.
    """

    def __init__(self, spec: Spec | None = None, *, report_errors: bool = False,
                 max_encoded: int | None = None) -> None:
        self.spec = spec or load_spec()
        self.max_encoded = max_encoded or self.spec.max_encoded
        self.report_errors = report_errors
        self.stats = DecodeStats()
        self._buf = bytearray()
        self._buf_offset = 0      # stream offset of _buf[0]
        self._discarding = False  # inside an oversize frame, waiting for a delimiter
        self._by_id = self.spec.by_id

    def _error(self, out: list, kind: str, offset: int, length: int, detail: str) -> None:
        setattr(self.stats, kind, getattr(self.stats, kind) + 1)
        if self.report_errors:
            out.append(FrameError(kind, offset, length, detail))

    def feed(self, data: bytes | bytearray | memoryview) -> list[Message | FrameError]:
        """Decode what `data` completes; keep the unfinished tail for the next call."""
        out: list[Message | FrameError] = []
        buf = self._buf
        buf += data
        self.stats.bytes += len(data)
        start = 0
        find = buf.find
        while True:
            end = find(0, start)
            if end < 0:
                break
            n = end - start
            if self._discarding:
                self._discarding = False
            elif n > self.max_encoded:
                self._error(out, "oversize", self._buf_offset + start, n,
                            f"{n} B > {self.max_encoded} B")
            elif n:
                self._frame(out, buf, start, end)
            start = end + 1
        if start:
            del buf[:start]
            self._buf_offset += start
        if len(buf) > self.max_encoded:
            if not self._discarding:
                self._error(out, "oversize", self._buf_offset, len(buf),
                            f"no delimiter within {self.max_encoded} B")
            self._discarding = True
            self._buf_offset += len(buf)
            buf.clear()
        return out

    def _frame(self, out: list, buf: bytearray, start: int, end: int) -> None:
        offset = self._buf_offset + start
        n = end - start
        try:
            raw = cobs.decode(buf[start:end])
        except cobs.DecodeError as e:
            self._error(out, "malformed", offset, n, f"COBS: {e}")
            return
        size = len(raw)
        if size < MIN_RAW:
            self._error(out, "malformed", offset, n, f"runt: {size} B after COBS")
            return
        body = size - CRC_SIZE
        if zlib.crc32(memoryview(raw)[:body]) != int.from_bytes(raw[body:], "little"):
            self._error(out, "crc_errors", offset, n, "CRC-32 mismatch")
            return
        version, type_id, flags, seq = HEADER.unpack_from(raw)
        if version != self.spec.version:
            self._error(out, "bad_version", offset, n,
                        f"protocol version {version}, expected {self.spec.version}")
            return
        ms = self._by_id.get(type_id)
        if ms is None:
            self._error(out, "unknown_type", offset, n, f"type 0x{type_id:02x}")
            return
        fields = unpack_payload(ms, memoryview(raw)[HEADER.size:body])
        if fields is None:
            self._error(out, "malformed", offset, n,
                        f"{ms.name}: payload {body - HEADER.size} B does not fit")
            return
        msg = Message(ms, seq, flags, **fields)
        msg.offset = offset
        self.stats.frames += 1
        out.append(msg)

    def reset(self) -> None:
        """Forget any partial frame (e.g. after reopening the port); counters are kept."""
        self._buf.clear()
        self._discarding = False
