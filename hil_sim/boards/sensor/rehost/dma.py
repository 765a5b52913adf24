"""DMA1 (8 streams) and DMAMUX1 of the rehosted H743: the ADC ring writer and the USART3 sender.

A stream is wired through DMAMUX1 channel n (= stream n of DMA1) to a request: ADC1 (9)
writes each conversion to memory at M0AR + 2 x index, NDTR counting down and reloading in
circular mode (TCIF at each wrap); USART3_TX (46) reads NDTR bytes from memory for the UART.
Rules: stream registers are written only while EN = 0, memory addresses must be reachable
by DMA1 (not the TCMs), and the buffer a peripheral-to-memory stream fills is watched by
the D-cache model so a stale CPU read is caught.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from .bus import Peripheral

if TYPE_CHECKING:
    pass

TCIF = (5, 11, 21, 27)  # LISR/HISR transfer-complete bit of stream n % 4


class DmaMux(Peripheral):
    """DMAMUX1: request line of each DMA1/DMA2 stream."""

    name, base, clock = "DMAMUX1", 0x40020800, (0xD8, 0)

    def request(self, channel: int) -> int:
        """Request id routed to channel (= DMA1 stream)."""
        return self.regs.get(4 * channel, 0) & 0x7F


class Dma(Peripheral):
    """DMA1: streams 0..7; each keeps its live NDTR and position."""

    name, base, clock = "DMA1", 0x40020000, (0xD8, 0)

    def reset(self) -> None:
        self.reload = [0] * 8  # NDTR written before enable
        self.done = [0] * 8    # items transferred since enable (mod reload when circular)

    @staticmethod
    def _stream(offset: int) -> tuple[int, int]:
        return (offset - 0x10) // 0x18, (offset - 0x10) % 0x18

    def sreg(self, n: int, reg: int) -> int:
        """Stream n register (0 CR, 4 NDTR, 8 PAR, 0xC M0AR)."""
        return self.regs.get(0x10 + 0x18 * n + reg, 0)

    def enabled(self, n: int) -> bool:
        return bool(self.sreg(n, 0) & 1)

    def read(self, offset: int) -> int:
        if offset >= 0x10:
            n, reg = self._stream(offset)
            if reg == 4 and self.enabled(n):
                self.m.adc.advance()
                self.m.usart3.advance()
        return self.regs.get(offset, 0)

    def write(self, offset: int, value: int, size: int = 4) -> None:
        self.action()
        if offset in (0x08, 0x0C):  # LIFCR/HIFCR: clear flags
            flag = 0x00 if offset == 0x08 else 0x04
            self.regs[flag] = self.regs.get(flag, 0) & ~value
            return
        if offset < 0x10:
            return  # LISR/HISR are read-only
        n, reg = self._stream(offset)
        if n >= 8:
            self.m.violation("bus-fault", f"DMA1+0x{offset:03x} is reserved")
        was = self.enabled(n)
        if was:
            self._check_while_enabled(n, reg, value)
        self.regs[offset] = value
        if was and reg in (0x0C, 0x10):  # the idle buffer of a double-buffered stream
            self._check_buffer(n, reg)
        if reg == 0:
            if value & 1 and not was:
                self._start(n)
            elif not value & 1 and was:
                self._stop(n)

    def _check_while_enabled(self, n: int, reg: int, value: int) -> None:
        """RM0433 15.3.19: with EN = 1 only EN may change in CR (a write clearing EN stops the
        stream, whatever else it holds), and only the buffer not in
        use (M1AR while CT = 0, M0AR while CT = 1) may be rewritten, in double-buffer mode."""
        cr = self.sreg(n, 0)
        dbm, ct = (cr >> 18) & 1, (cr >> 19) & 1
        if reg == 0:
            changed = (cr ^ value) & ~1
            if not changed or not value & 1:  # EN = 0 disables: the usual way to stop it
                return
            what = f"CR bits 0x{changed:08x}"
        elif reg in (0x0C, 0x10) and dbm and ct == (1 if reg == 0x0C else 0):
            return  # the idle buffer: legal
        else:
            what = f"register +0x{reg:02x}"
        self.m.violation("dma-config-while-enabled",
                         f"DMA1 stream {n} {what} written at pc 0x{self.m.pc():08x} while "
                         f"EN = 1 (RM0433 15.3.19)")

    def _check_buffer(self, n: int, reg: int) -> None:
        cr, ndtr = self.sreg(n, 0), self.sreg(n, 4)
        name = "M0AR" if reg == 0x0C else "M1AR"
        self.m.check_dma_address(self.sreg(n, reg), ndtr * (1 << ((cr >> 13) & 3)),
                                 f"DMA1 stream {n} {name}")

    def _start(self, n: int) -> None:
        cr, ndtr = self.sreg(n, 0), self.sreg(n, 4)
        m0ar = self.sreg(n, 0xC)
        width = 1 << ((cr >> 13) & 3)
        self.m.check_dma_address(m0ar, ndtr * width, f"DMA1 stream {n} M0AR")
        if (cr >> 18) & 1:  # double buffer: memory 1 must be reachable too
            self._check_buffer(n, 0x10)
        self.reload[n], self.done[n] = ndtr, 0
        req = self.m.dmamux.request(n)
        if (cr >> 6) & 3 == 0:
            self.m.system.watch(m0ar, ndtr * width)
        elif req == 46:
            self.m.usart3.dma_start(n, m0ar, ndtr)

    def _stop(self, n: int) -> None:
        if self.m.dmamux.request(n) == 46:
            self.m.usart3.dma_stop()

    def _flag(self, n: int, bit: int) -> None:
        reg = 0x00 if n < 4 else 0x04
        self.regs[reg] = self.regs.get(reg, 0) | (1 << bit)

    def from_peripheral(self, request: int, values: np.ndarray | None, skip: int = 0) -> None:
        """The peripheral with `request` produced items: write them where its stream points.

        `skip` items are counted without being written (a circular stream overwrote them).
        """
        stream = next((n for n in range(8) if self.enabled(n)
                       and self.m.dmamux.request(n) == request), None)
        if stream is None:
            return  # no DMA: the data register is overwritten (OVRMOD = 1)
        n = stream
        cr, m0ar = self.sreg(n, 0), self.sreg(n, 0xC)
        circular = bool(cr & (1 << 8))
        size = self.reload[n]
        if values is None:
            if not circular:
                raise ValueError("only a circular stream skips items")
            self.done[n] += skip
            left = size - self.done[n] % size
            self.regs[0x10 + 0x18 * n + 4] = left
            self._flag(n, TCIF[n % 4])
            return
        data = values.astype("<u2").view(np.uint8)
        items = values.size
        while items:
            pos = self.done[n] % size if circular else self.done[n]
            room = size - pos
            if room <= 0:
                self.regs[0x10 + 0x18 * n] = cr & ~1
                return
            k = min(room, items)
            chunk = data[:2 * k]
            addr = m0ar + 2 * pos
            self.m.uc.mem_write(addr, chunk.tobytes())
            self.m.system.dma_wrote(addr, 2 * k)
            data, items = data[2 * k:], items - k
            self.done[n] += k
            if pos + k == size:
                self._flag(n, TCIF[n % 4])
        left = size - (self.done[n] % size if circular else self.done[n])
        self.regs[0x10 + 0x18 * n + 4] = size if circular and left == 0 else left
        if not circular and left == 0:
            self.regs[0x10 + 0x18 * n] = cr & ~1

    def set_remaining(self, n: int, left: int) -> None:
        """A memory-to-peripheral stream moved on: NDTR = left; EN and TCIF when done."""
        self.regs[0x10 + 0x18 * n + 4] = left
        if left == 0 and self.enabled(n):
            self.regs[0x10 + 0x18 * n] &= ~1
            self._flag(n, TCIF[n % 4])
