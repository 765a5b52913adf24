"""USART3 of the rehosted H743 (the ST-LINK virtual COM port): RX FIFO with interrupt, DMA TX.

Bytes from the host arrive one frame time (10 bits at the BRR rate) apart; with FIFOEN the
RX FIFO holds 16, a byte arriving into a full FIFO sets ORE and is lost, as on silicon.
RXFNE (ISR bit 5) raises IRQ 39 when RXFNEIE is set. Transmission is by DMA (CR3.DMAT,
DMAMUX request 46): the bytes leave at the line rate and the stream's NDTR counts what is
still in memory; TC rises when the last stop bit is out. `hold(dt)` pauses the line (the
host side cannot take more, as the SIL models USB flow control).
"""

from __future__ import annotations

import math
from collections import deque

from .bus import Peripheral

IRQ_USART3 = 39
FIFO = 16


class Usart3(Peripheral):
    """USART3 with its wire to the host: `receive()` in, `take_tx()` out."""

    name, base, clock = "USART3", 0x40004800, (0xE8, 18)

    def reset(self) -> None:
        self.regs[0x1C] = (1 << 6) | (1 << 7)  # TC, TXFNF
        self.wire: deque[tuple[float, int]] = deque()  # (arrival time, byte)
        self.fifo: deque[int] = deque()
        self.wire_free_at = 0.0
        self.tx: bytes = b""
        self.tx_stream = -1
        self.tx_t0 = 0.0
        self.tx_sent = 0      # bytes handed to the host so far
        self.tx_out = bytearray()
        self.overruns = 0

    def frame_s(self) -> float:
        """Time of one 8N1 character (s) at the programmed baud rate."""
        brr = self.regs.get(0x0C, 0)
        if not brr:
            return math.inf
        return 10 * brr / self.m.rcc.pclk(1)

    # ---------------------------------------------------------------- host side
    def receive(self, data: bytes, t: float) -> None:
        """Bytes the host sends, starting at time t (s)."""
        frame = self.frame_s() if math.isfinite(self.frame_s()) else 5e-6
        at = max(t, self.wire_free_at)
        for b in data:
            at += frame
            self.wire.append((at, b))
        self.wire_free_at = at

    def take_tx(self) -> bytes:
        """Bytes that have left the TX pin since the last call."""
        self.advance()
        out = bytes(self.tx_out)
        self.tx_out.clear()
        return out

    def hold(self, dt: float) -> None:
        """The line stalled for dt (s): the transfer in progress moves later."""
        if self.tx_stream >= 0:
            self.tx_t0 += dt

    def next_event(self) -> float:
        """Next time the CPU may see a change: a byte arriving, the transfer ending."""
        t = math.inf
        if self.wire:
            t = self.wire[0][0]
        if self.tx_stream >= 0:
            t = min(t, self.tx_t0 + len(self.tx) * self.frame_s())
        return t

    # ---------------------------------------------------------------- time
    def advance(self) -> None:
        """Deliver arrived bytes to the FIFO and move the transmitter on."""
        now = self.m.t
        cr1 = self.regs.get(0, 0)
        ready = cr1 & 1 and cr1 & 4
        while self.wire and self.wire[0][0] <= now:
            _, b = self.wire.popleft()
            if not ready:
                continue
            if len(self.fifo) >= (FIFO if cr1 & (1 << 29) else 1):
                self.regs[0x1C] |= 1 << 3  # ORE
                self.overruns += 1
            else:
                self.fifo.append(b)
        if self.fifo or self.regs[0x1C] & 8:
            if cr1 & (1 << 5):
                self.m.system.set_pending(IRQ_USART3)
        if self.tx_stream >= 0:
            sent = min(len(self.tx), math.floor((now - self.tx_t0) / self.frame_s() + 1e-9))
            if sent > self.tx_sent:
                self.tx_out += self.tx[self.tx_sent:sent]
                self.tx_sent = sent
            pulled = min(len(self.tx), sent + FIFO + 1)
            self.m.dma1.set_remaining(self.tx_stream, len(self.tx) - pulled)
            if sent == len(self.tx):
                self.tx_stream = -1
                self.regs[0x1C] |= 1 << 6

    def dma_start(self, stream: int, addr: int, n: int) -> None:
        """DMA stream `stream` starts feeding n bytes from addr."""
        cr1 = self.regs.get(0, 0)
        if not (cr1 & 1 and cr1 & 8 and self.regs.get(0x08, 0) & (1 << 7)):
            self.m.violation("usart-dma-not-enabled",
                                "USART3 TX DMA started without UE, TE and CR3.DMAT")
        self.advance()
        self.tx = bytes(self.m.uc.mem_read(addr, n))
        self.tx_stream, self.tx_t0, self.tx_sent = stream, self.m.t, 0
        self.regs[0x1C] &= ~(1 << 6)

    def dma_stop(self) -> None:
        """The stream was disabled: what is not yet out is dropped."""
        self.advance()
        self.tx_stream = -1
        self.regs[0x1C] |= 1 << 6

    # ---------------------------------------------------------------- registers
    def read(self, offset: int) -> int:
        if offset == 0x1C:
            self.advance()
            isr = self.regs[0x1C] & ~(1 << 5)
            return isr | ((1 << 5) if self.fifo else 0)
        if offset == 0x24:
            self.action()
            return self.fifo.popleft() if self.fifo else 0
        return self.regs.get(offset, 0)

    def write(self, offset: int, value: int, size: int = 4) -> None:
        self.action()
        if offset == 0x20:  # ICR: write 1 to clear PE FE NF ORE ... TC (bit 6)
            self.regs[0x1C] &= ~(value & 0x1F5F)
            return
        if offset == 0x0C and self.regs.get(0, 0) & 1:
            self.m.violation("usart-brr-while-enabled",
                             f"USART3_BRR = 0x{value:08x} written at pc 0x{self.m.pc():08x} "
                             f"with UE = 1 (RM0433 53.5.7: disable the USART first)")
        if offset == 0x28:
            self.tx_out.append(value & 0xFF)
            return
        self.regs[offset] = value
