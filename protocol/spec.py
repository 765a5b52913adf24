"""Loads protocol/messages.toml into message layouts; the one source both codecs derive from."""

from __future__ import annotations

import hashlib
import struct
import tomllib
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path

SPEC_PATH = Path(__file__).with_name("messages.toml")

#: fixed-width scalar types: struct code and size in bytes
SCALARS: dict[str, tuple[str, int]] = {
    "u8": ("B", 1), "u16": ("H", 2), "u32": ("I", 4), "u64": ("Q", 8),
    "i8": ("b", 1), "i16": ("h", 2), "i32": ("i", 4), "i64": ("q", 8),
    "f32": ("f", 4),
}
#: variable-length types allowed only as the last ("tail") field
TAILS = ("bytes", "str", "samples")
#: numpy dtype of a waveform's samples for each sample_format value
SAMPLE_DTYPES = {0: "<u2", 1: "<u4"}

HEADER = struct.Struct("<BBBH")  # version, type, flags, seq
CRC_SIZE = 4


class SpecError(ValueError):
    """The spec file is inconsistent (a bug in messages.toml, not in user input)."""


@dataclass(frozen=True)
class FieldSpec:
    """One field of a message: name, wire type and what it means."""

    name: str
    type: str
    doc: str = ""
    unit: str = ""
    enum: str = ""
    min: int | None = None
    max: int | None = None

    @property
    def is_tail(self) -> bool:
        """True for the variable-length last field."""
        return self.type in TAILS

    def int_range(self) -> tuple[int, int] | None:
        """Representable range of an integer field (None for f32 and tails)."""
        if self.type.startswith("u"):
            return 0, (1 << (8 * SCALARS[self.type][1])) - 1
        if self.type.startswith("i"):
            bits = 8 * SCALARS[self.type][1]
            return -(1 << (bits - 1)), (1 << (bits - 1)) - 1
        return None

    def allowed(self) -> tuple[int, int]:
        """The values the spec allows: its min/max where given, else its type's range."""
        lo, hi = self.int_range() or (0, 0)
        return (self.min if self.min is not None else lo), (self.max if self.max is not None
                                                            else hi)


@dataclass(frozen=True)
class MessageSpec:
    """Layout of one message type: id, direction, fixed fields and optional tail."""

    name: str
    id: int
    dir: str
    doc: str
    fields: tuple[FieldSpec, ...]
    reply: str = ""
    fixed: struct.Struct = field(compare=False, default=struct.Struct("<"))

    @property
    def tail(self) -> FieldSpec | None:
        """The variable-length last field, if any."""
        return self.fields[-1] if self.fields and self.fields[-1].is_tail else None

    @property
    def scalar_fields(self) -> tuple[FieldSpec, ...]:
        """The fixed-width fields, in wire order."""
        return self.fields[:-1] if self.tail else self.fields


@dataclass(frozen=True)
class Spec:
    """The whole protocol: version, limits, flags, enums and messages."""

    version: int
    max_payload: int
    max_command_payload: int
    sync_quiet_ms: int  # a motion-sync burst ends after this quiet time (ms)
    flags: dict[str, int]
    flag_docs: dict[str, str]
    enums: dict[str, dict[str, int]]
    enum_docs: dict[str, dict[str, str]]
    messages: tuple[MessageSpec, ...]
    hash: int
    text: str

    @property
    def by_name(self) -> dict[str, MessageSpec]:
        """Messages keyed by name."""
        return {m.name: m for m in self.messages}

    @property
    def by_id(self) -> dict[int, MessageSpec]:
        """Messages keyed by type id."""
        return {m.id: m for m in self.messages}

    @property
    def max_raw(self) -> int:
        """Largest un-stuffed frame: header + payload + CRC, in bytes."""
        return HEADER.size + self.max_payload + CRC_SIZE

    @property
    def max_encoded(self) -> int:
        """Largest COBS-encoded frame between delimiters, in bytes."""
        return self.max_raw + self.max_raw // 254 + 1

    def enum_name(self, enum: str, value: int) -> str | None:
        """Name of an enum value, or None if the value is not defined."""
        for name, v in self.enums.get(enum, {}).items():
            if v == value:
                return name
        return None


def spec_hash(text: str) -> int:
    """First 8 bytes of SHA-256 of the spec text (LF line endings), as an integer."""
    data = text.replace("\r\n", "\n").encode()
    return int.from_bytes(hashlib.sha256(data).digest()[:8], "big")


def parse_spec(text: str) -> Spec:
    """Parse and check the spec text; raises SpecError on inconsistencies."""
    doc = tomllib.loads(text)
    enums: dict[str, dict[str, int]] = {}
    enum_docs: dict[str, dict[str, str]] = {}
    for ename, entries in doc.get("enums", {}).items():
        enums[ename] = {k: v["value"] for k, v in entries.items() if k != "doc"}
        enum_docs[ename] = {k: v["doc"] for k, v in entries.items() if k != "doc"}
        enum_docs[ename][""] = entries.get("doc", "")
    flags = {k: 1 << v["bit"] for k, v in doc["flags"].items()}
    flag_docs = {k: v["doc"] for k, v in doc["flags"].items()}
    messages = []
    seen_ids: set[int] = set()
    for m in doc["message"]:
        fields = tuple(FieldSpec(**f) for f in m["fields"])
        for i, f in enumerate(fields):
            if f.type not in SCALARS and f.type not in TAILS:
                raise SpecError(f"{m['name']}.{f.name}: unknown type {f.type}")
            if f.is_tail and i != len(fields) - 1:
                raise SpecError(f"{m['name']}.{f.name}: {f.type} must be the last field")
            if f.enum and f.enum not in enums:
                raise SpecError(f"{m['name']}.{f.name}: unknown enum {f.enum}")
        if m["id"] in seen_ids or not 0 < m["id"] < 256:
            raise SpecError(f"{m['name']}: duplicate or invalid id {m['id']:#x}")
        seen_ids.add(m["id"])
        fmt = "<" + "".join(SCALARS[f.type][0] for f in fields if not f.is_tail)
        messages.append(MessageSpec(
            name=m["name"], id=m["id"], dir=m["dir"], doc=m["doc"], fields=fields,
            reply=m.get("reply", ""), fixed=struct.Struct(fmt)))
        tail = messages[-1].tail
        if tail is not None and tail.type == "samples" and not any(
                f.name == "sample_format" for f in fields):
            raise SpecError(f"{m['name']}: samples tail needs a sample_format field")
    names = {m.name for m in messages}
    for m in messages:
        if m.reply and m.reply not in names:
            raise SpecError(f"{m.name}: reply {m.reply} is not a message")
    p = doc["protocol"]
    return Spec(version=p["version"], max_payload=p["max_payload"],
                max_command_payload=p["max_command_payload"],
                sync_quiet_ms=p["sync_quiet_ms"], flags=flags,
                flag_docs=flag_docs, enums=enums, enum_docs=enum_docs,
                messages=tuple(messages), hash=spec_hash(text), text=text)


@cache
def load_spec(path: Path = SPEC_PATH) -> Spec:
    """The protocol spec shipped with this package (parsed once)."""
    return parse_spec(path.read_text(encoding="utf-8"))
