"""A minimal command/response link for the conformance suite (the real client is dmdsm.host's)."""

from __future__ import annotations

import serial

from dmdsm.host.links.board_clock import BoardClock, Deadline
from dmdsm.protocol import FrameDecoder, Message, encode_frame


class Link:
    """Sends commands with fresh sequence numbers and collects responses and unsolicited frames."""

    def __init__(self, url: str, baudrate: int = 2_000_000) -> None:
        self.port = serial.serial_for_url(url, baudrate=baudrate, timeout=0.05)
        # waits count the board's time too: a rehosted board on a loaded machine runs at a
        # few % of real time (host/links/board_clock.py); a real board keeps wall time
        self.clock = BoardClock(url)
        self.dec = FrameDecoder(report_errors=True)
        self.seq = 100
        self.unsolicited: list[Message] = []
        self.port.write(b"\x00")

    def close(self) -> None:
        """Close the port."""
        self.port.close()

    def pump(self, seconds: float = 0.0) -> list:
        """Read for up to `seconds` (at least once) and return what was decoded."""
        out = []
        end = Deadline(seconds, self.clock)
        while True:
            out += self.dec.feed(self.port.read(65536))
            if end.passed():
                return out

    def send_raw(self, data: bytes) -> None:
        """Write bytes as they are (for fault injection)."""
        self.port.write(data)

    def request(self, name: str, timeout: float = 3.0, seq: int | None = None,
                flags: int = 0, **fields: object) -> Message:
        """Send one command and return its response; unsolicited frames are kept."""
        if seq is None:
            self.seq = (self.seq + 1) & 0xFFFF
            seq = self.seq
        self.port.write(encode_frame(Message(name, seq=seq, flags=flags, **fields)))
        end = Deadline(timeout, self.clock)
        response = None
        while response is None and not end.passed():
            for item in self.pump():
                if not isinstance(item, Message):
                    continue
                if response is None and item.is_response and item.seq == seq:
                    response = item
                else:
                    self.unsolicited.append(item)
        if response is not None:
            return response
        raise TimeoutError(f"no response to {name} seq={seq} within {timeout} s")

    def waveforms(self, n: int, timeout: float = 10.0) -> list[Message]:
        """Collect n waveform messages (including any already received), waiting until
        `timeout` seconds pass without a new one: a slow but steady target (a rehost on a
        loaded machine) is not cut short, a stalled one is."""
        end = Deadline(timeout, self.clock)
        count = 0
        while (now := len([m for m in self.unsolicited if m.name == "waveform"])) < n:
            if now > count:
                count, end = now, Deadline(timeout, self.clock)
            if end.passed():
                break
            self.unsolicited += [m for m in self.pump() if isinstance(m, Message)]
        got = [m for m in self.unsolicited if m.name == "waveform"]
        self.unsolicited = [m for m in self.unsolicited if m.name != "waveform"]
        return got
