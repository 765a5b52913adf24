"""A minimal line-numbered G-code link for the stage conformance suite (real Marlin or hil_sim)."""

from __future__ import annotations

import time

import serial

from dmdsm.marlin_patch import checksum


class StageLink:
    """Sends numbered, checksummed lines and collects replies up to the matching ok."""

    def __init__(self, url: str, baudrate: int = 250000) -> None:
        self.port = serial.serial_for_url(url, baudrate=baudrate, timeout=0.05)
        self.n = 0
        self.buf = b""
        self.speed = 1.0             # stage seconds per wall second (the emulator runs faster)
        self.clock = time.monotonic  # the stage's time in seconds (the fixture sets it)

    def close(self) -> None:
        """Close the port."""
        self.port.close()

    def lines(self, seconds: float) -> list[str]:
        """Every line received within `seconds`."""
        end = time.monotonic() + seconds
        out = []
        while time.monotonic() < end:
            self.buf += self._read()
            while b"\n" in self.buf:
                line, self.buf = self.buf.split(b"\n", 1)
                out.append(line.decode(errors="replace").strip())
        return out

    def run_for(self, stage_s: float) -> list[str]:
        """Every line received while the stage's own clock advances by stage_s seconds: a
        loaded machine runs the emulator behind the wall clock, so a wall-clock wait can end
        before the stage has moved at all (a real Marlin's clock is the wall clock)."""
        t0, out = self.clock(), []
        budget_s = 120 + stage_s / self.speed
        end = time.monotonic() + budget_s
        while self.clock() - t0 < stage_s:
            if time.monotonic() > end:
                raise TimeoutError(f"the stage's clock did not advance {stage_s} s within "
                                   f"{budget_s:.0f} s of wall time")
            out += self.lines(0.01)
        return out + self.lines(0.05)  # what it sent up to then, still on its way

    def _read(self) -> bytes:
        """What has arrived, or the next byte within the port timeout: read(4096) would wait
        out the whole timeout for a short reply (1 s of the emulator's time at 20x)."""
        return self.port.read(max(self.port.in_waiting, 1))

    def raw(self, text: str) -> None:
        """Write text as it is."""
        self.port.write(text.encode())

    def numbered(self, cmd: str, n: int | None = None, good_checksum: bool = True) -> str:
        """The line `N<n> cmd*<checksum>` (next number by default)."""
        if n is None:
            self.n += 1
            n = self.n
        body = f"N{n} {cmd}"
        cs = checksum(body) ^ (0 if good_checksum else 0x55)
        return f"{body}*{cs}\n"

    def until_ok(self, timeout: float = 20.0) -> list[str]:
        """Lines up to and including the next line starting with 'ok'."""
        end = time.monotonic() + timeout
        out: list[str] = []
        while time.monotonic() < end:
            self.buf += self._read()
            while b"\n" in self.buf:
                line, self.buf = self.buf.split(b"\n", 1)
                text = line.decode(errors="replace").strip()
                out.append(text)
                if text.startswith("ok"):
                    return out
        raise TimeoutError(f"no ok within {timeout} s; got {out[-5:]}")

    def send(self, cmd: str, timeout: float = 20.0) -> list[str]:
        """Send a numbered command and return the replies through its ok."""
        self.raw(self.numbered(cmd))
        return self.until_ok(timeout)

    def reset_numbers(self) -> None:
        """M110 N0: start line numbers again."""
        self.raw(f"N0 M110 N0*{checksum('N0 M110 N0')}\n")
        self.until_ok()
        self.n = 0
