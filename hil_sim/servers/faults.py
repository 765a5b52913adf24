"""Fault injection on the serial links: flipped, dropped, inserted bytes; stalls; disconnects."""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np


@dataclass
class LinkFaults:
    """Per-byte probabilities and per-second rates of one direction of a link."""

    flip: float = 0.0        # a byte has one bit flipped
    drop: float = 0.0        # a byte is lost
    insert: float = 0.0      # a random byte appears before this one
    stall: float = 0.0       # stalls per second: delivery pauses for stall_s
    stall_s: float = 0.05
    disconnect: float = 0.0  # disconnects per second (the port goes away, then comes back)
    reconnect_s: float = 0.5

    @property
    def active(self) -> bool:
        """True if any fault is enabled."""
        return any(getattr(self, f.name) for f in fields(self)
                   if f.name not in ("stall_s", "reconnect_s"))


class FaultyChannel:
    """Applies LinkFaults to a byte stream; deterministic for a given seed."""

    def __init__(self, faults: LinkFaults, seed: int) -> None:
        self.f = faults
        self.rng = np.random.default_rng(seed)
        self.stalled_until = 0.0
        self.held = bytearray()
        self.tap: bytearray | None = None  # a copy of what went in, before any fault (tests)
        self.flipped = self.dropped = self.inserted = self.stalls = 0

    def corrupt(self, data: bytes) -> bytes:
        """The bytes as the far end receives them."""
        if not data or not (self.f.flip or self.f.drop or self.f.insert):
            return data
        a = np.frombuffer(data, dtype=np.uint8).copy()
        n = len(a)
        flips = np.nonzero(self.rng.random(n) < self.f.flip)[0]
        a[flips] ^= (1 << self.rng.integers(0, 8, len(flips))).astype(np.uint8)
        keep = self.rng.random(n) >= self.f.drop
        ins = np.nonzero(self.rng.random(n) < self.f.insert)[0]
        self.flipped += len(flips)
        self.dropped += int(n - keep.sum())
        self.inserted += len(ins)
        out = bytearray()
        ins_set = set(ins.tolist())
        for i in range(n):
            if i in ins_set:
                out.append(int(self.rng.integers(0, 256)))
            if keep[i]:
                out.append(int(a[i]))
        return bytes(out)

    def deliver(self, data: bytes, now: float, dt: float) -> bytes:
        """Corrupt `data` and hold it back during stalls; returns what passes at `now` (s)."""
        if self.tap is not None:
            self.tap += data
        self.held += self.corrupt(data)
        if self.f.stall and self.rng.random() < self.f.stall * dt:
            self.stalled_until = now + self.f.stall_s
            self.stalls += 1
        if now < self.stalled_until:
            return b""
        out = bytes(self.held)
        self.held.clear()
        return out

    def disconnects(self, dt: float) -> bool:
        """True if the link drops during the next dt seconds."""
        return bool(self.f.disconnect) and self.rng.random() < self.f.disconnect * dt


def parse_faults(text: str) -> dict[str, dict[str, float]]:
    """'sensor.flip=1e-5,stage.lost_ok=0.01' -> {'sensor': {'flip': 1e-5}, 'stage': {...}}."""
    out: dict[str, dict[str, float]] = {"sensor": {}, "stage": {}}
    for item in filter(None, (s.strip() for s in text.split(","))):
        key, sep, value = item.partition("=")
        link, dot, name = key.partition(".")
        if not sep or not dot or link not in out:
            raise ValueError(f"bad fault {item!r}: use sensor.NAME=VALUE or stage.NAME=VALUE")
        try:
            out[link][name] = float(value)
        except ValueError:
            raise ValueError(f"bad fault value in {item!r}: not a number") from None
    return out
