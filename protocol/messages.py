"""Message objects and payload packing for every message type in the spec."""

from __future__ import annotations

import struct
from collections.abc import Mapping
from typing import Any

import numpy as np

from .spec import SAMPLE_DTYPES, MessageSpec, Spec, load_spec


class MessageError(ValueError):
    """A message cannot be built or packed: the text says which field and why."""


class Message:
    """One protocol message: type, sequence number, flags and field values.

    Waveform samples are a numpy array (read-only when decoded, zero-copy from the frame).
    `offset` is the byte position of the frame in the decoded stream (-1 if not decoded).
    """

    __slots__ = ("spec", "seq", "flags", "fields", "offset")

    def __init__(self, kind: str | MessageSpec, seq: int = 0, flags: int = 0,
                 _spec: Spec | None = None, **fields: Any) -> None:
        if isinstance(kind, str):
            spec = _spec or load_spec()
            try:
                kind = spec.by_name[kind]
            except KeyError:
                raise MessageError(f"unknown message type {kind!r}; known: "
                                   f"{', '.join(spec.by_name)}") from None
        self.spec = kind
        self.seq = seq
        self.flags = flags
        self.fields = fields
        self.offset = -1

    @property
    def name(self) -> str:
        """Message type name from the spec."""
        return self.spec.name

    @property
    def is_response(self) -> bool:
        """True if the response flag is set (answers the command with the same seq)."""
        return bool(self.flags & 1)

    def __getattr__(self, item: str) -> Any:
        try:
            return self.fields[item]
        except KeyError:
            raise AttributeError(f"{self.spec.name} has no field {item!r}") from None

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Message):
            return NotImplemented
        if (self.spec.id, self.seq, self.flags) != (other.spec.id, other.seq, other.flags):
            return False
        if self.fields.keys() != other.fields.keys():
            return False
        for k, v in self.fields.items():
            w = other.fields[k]
            if isinstance(v, np.ndarray) or isinstance(w, np.ndarray):
                if not np.array_equal(np.asarray(v), np.asarray(w)):
                    return False
            elif v != w and not (v != v and w != w):  # NaN == NaN for f32 round trips
                return False
        return True

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        parts = []
        for k, v in self.fields.items():
            if isinstance(v, np.ndarray):
                parts.append(f"{k}=<{v.size} x {v.dtype}>")
            else:
                parts.append(f"{k}={v!r}")
        return (f"Message({self.spec.name!r}, seq={self.seq}, flags={self.flags}, "
                f"{', '.join(parts)})")


def pack_payload(msg: Message) -> bytes:
    """Payload bytes of a message (fixed fields little-endian, then the tail)."""
    ms = msg.spec
    f = msg.fields
    names = [fs.name for fs in ms.fields]
    missing = [n for n in names if n not in f]
    extra = [n for n in f if n not in names]
    if missing or extra:
        what = f"missing {', '.join(missing)}" if missing else f"unknown {', '.join(extra)}"
        raise MessageError(f"{ms.name}: {what} (fields: {', '.join(names) or 'none'})")
    values = [f[fs.name] for fs in ms.scalar_fields]
    try:
        head = ms.fixed.pack(*values)
    except struct.error:
        for fs, v in zip(ms.scalar_fields, values):
            rng = fs.int_range()
            if rng and (not isinstance(v, int) or not rng[0] <= v <= rng[1]):
                raise MessageError(f"{ms.name}.{fs.name}={v!r} does not fit {fs.type} "
                                   f"({rng[0]}..{rng[1]})") from None
        raise MessageError(f"{ms.name}: field values do not fit {ms.fixed.format}") from None
    tail = ms.tail
    if tail is None:
        return head
    v = f[tail.name]
    if tail.type == "str":
        return head + str(v).encode()
    if tail.type == "bytes":
        return head + bytes(v)
    dtype = np.dtype(SAMPLE_DTYPES.get(f["sample_format"], "V"))
    if dtype.kind == "V":
        raise MessageError(f"{ms.name}.sample_format={f['sample_format']} is not defined")
    arr = np.asarray(v)
    if arr.dtype != dtype:
        if arr.size and (arr.min() < 0 or arr.max() > np.iinfo(dtype).max):
            raise MessageError(f"{ms.name}.samples do not fit {dtype.name}")
        arr = arr.astype(dtype)
    return head + arr.tobytes()


def unpack_payload(ms: MessageSpec, payload: bytes | memoryview) -> dict[str, Any] | None:
    """Field values of a payload, or None if its length does not fit the message."""
    n = ms.fixed.size
    size = len(payload)
    tail = ms.tail
    if size < n or (tail is None and size != n):
        return None
    values = ms.fixed.unpack_from(payload)
    fields = dict(zip((fs.name for fs in ms.scalar_fields), values))
    if tail is None:
        return fields
    if tail.type == "samples":
        code = SAMPLE_DTYPES.get(fields["sample_format"])
        if code is None:
            return None
        dtype = np.dtype(code)
        if (size - n) % dtype.itemsize:
            return None
        fields[tail.name] = np.frombuffer(payload, dtype=dtype, offset=n)
    elif tail.type == "str":
        fields[tail.name] = bytes(payload[n:]).decode("utf-8", errors="replace")
    else:
        fields[tail.name] = bytes(payload[n:])
    return fields


def to_jsonable(msg: Message, spec: Spec | None = None) -> dict[str, Any]:
    """A JSON-ready dict of a message (enum values stay numbers; names in "enums")."""
    spec = spec or load_spec()
    fields: dict[str, Any] = {}
    enums: dict[str, str] = {}
    for fs in msg.spec.fields:
        v = msg.fields[fs.name]
        if isinstance(v, np.ndarray):
            v = v.tolist()
        elif isinstance(v, bytes):
            v = v.hex()
        fields[fs.name] = v
        if fs.enum:
            enums[fs.name] = spec.enum_name(fs.enum, v) or f"<undefined {v}>"
    flags = [name for name, bit in spec.flags.items() if msg.flags & bit]
    out: dict[str, Any] = {"type": msg.name, "seq": msg.seq, "flags": flags, "fields": fields}
    if enums:
        out["enums"] = enums
    return out


def from_jsonable(obj: Mapping[str, Any], spec: Spec | None = None) -> Message:
    """Build a message from a dict like to_jsonable's; enum fields may be given by name."""
    spec = spec or load_spec()
    if not isinstance(obj, Mapping) or "type" not in obj:
        raise MessageError('expected an object with "type" (and "seq", "flags", "fields")')
    ms = spec.by_name.get(obj["type"])
    if ms is None:
        raise MessageError(f"unknown message type {obj['type']!r}; known: "
                           f"{', '.join(spec.by_name)}")
    flags = obj.get("flags", 0)
    if isinstance(flags, list):
        bad = [f for f in flags if f not in spec.flags]
        if bad:
            raise MessageError(f"unknown flag {bad[0]!r}; known: {', '.join(spec.flags)}")
        flags = sum(spec.flags[f] for f in flags)
    fields = dict(obj.get("fields", {}))
    for fs in ms.fields:
        v = fields.get(fs.name)
        if fs.enum and isinstance(v, str):
            if v not in spec.enums[fs.enum]:
                raise MessageError(f"{ms.name}.{fs.name}: {v!r} is not one of "
                                   f"{', '.join(spec.enums[fs.enum])}")
            fields[fs.name] = spec.enums[fs.enum][v]
        elif fs.type == "bytes" and isinstance(v, str):
            fields[fs.name] = bytes.fromhex(v)
    seq = obj.get("seq", 0)
    if not isinstance(seq, int) or not 0 <= seq <= 0xFFFF:
        raise MessageError(f"seq={seq!r} must be an integer 0..65535")
    return Message(ms, seq=seq, flags=int(flags), **fields)
