"""The Cortex-M7 system block of the rehosted H743: SCB, NVIC, SysTick, MPU, FPU access, L1 caches.

unicorn runs the instructions; exceptions are taken here. Entry pushes the basic frame
(R0-R3, R12, LR, PC, xPSR, 8-byte aligned) on the main stack, saves S0-S15/FPSCR aside (the
lazy FP frame is not modelled, the restore is exact), sets LR to EXC_RETURN 0xFFFFFFF9 and
jumps to the vector. A branch to EXC_RETURN lands on a guard page whose code hook pops the
frame. Priorities are by exception number and handlers do not nest (this firmware has two).
The D-cache model tracks lines a DMA wrote, so a CPU read of a line filled before the DMA
wrote it (no invalidate between) is caught.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from unicorn import UC_HOOK_MEM_READ
from unicorn.arm_const import (
    UC_ARM_REG_FPSCR,
    UC_ARM_REG_LR,
    UC_ARM_REG_PC,
    UC_ARM_REG_PRIMASK,
    UC_ARM_REG_R0,
    UC_ARM_REG_R1,
    UC_ARM_REG_R2,
    UC_ARM_REG_R3,
    UC_ARM_REG_R12,
    UC_ARM_REG_S0,
    UC_ARM_REG_SP,
    UC_ARM_REG_XPSR,
)

from .bus import Peripheral

if TYPE_CHECKING:
    pass

EXC_RETURN_PAGE = 0xFFFFF000
LINE = 32
DCACHE_SETS, DCACHE_WAYS = 128, 4  # 16 KiB, 4-way, 32-byte lines
FRAME_REGS = (UC_ARM_REG_R0, UC_ARM_REG_R1, UC_ARM_REG_R2, UC_ARM_REG_R3, UC_ARM_REG_R12,
              UC_ARM_REG_LR, UC_ARM_REG_PC, UC_ARM_REG_XPSR)
FP_REGS = tuple(UC_ARM_REG_S0 + i for i in range(16)) + (UC_ARM_REG_FPSCR,)


class DmaWatch:
    """D-cache state of one DMA-written buffer: per-byte write generation, per-line fill."""

    def __init__(self, base: int, size: int) -> None:
        self.base, self.size = base, size
        self.written = np.zeros(size, np.int64)  # generation of the last DMA write, per byte
        lines = size // LINE + 1
        self.line_written = [0] * lines          # the same, per cache line (the fast check)
        self.fill = [-1] * lines                 # generation at the CPU's fill; -1: invalid


class System(Peripheral):
    """0xE000E000..0xE000EFFF: NVIC, SysTick, SCB, MPU, FPU and cache maintenance."""

    name, base, size = "SCS", 0xE000E000, 0x1000

    def reset(self) -> None:
        self.regs.update({0xD00: 0x411FC272, 0xD08: 0x08000000, 0xD14: 0x200,
                          0xD90: 16 << 8, 0xD78: 0x09000003, 0xD7C: 0x8303C003})
        self.enabled: set[int] = set()
        self.pending: set[int] = set()
        self.swept: set[tuple[int, int]] = set()  # (set, way) invalidated since reset
        self.active = 0
        self.saved: list[tuple[list[int], list[int], int]] = []
        self.watches: list[DmaWatch] = []
        self.gen = 0
        self.fpu_on = False
        self.st_counts, self.st_t, self.st_seen_wraps = 0.0, 0.0, 1

    # ---------------------------------------------------------------- SysTick
    def _systick(self) -> int:
        """Counts since the last write of CVR, at the CPU clock (CLKSOURCE = 1) or / 8."""
        csr = self.regs.get(0x010, 0)
        now = self.m.t
        if csr & 1:
            hz = self.m.cpu_hz / (1 if csr & 4 else 8)
            self.st_counts += (now - self.st_t) * hz
        self.st_t = now
        return int(self.st_counts)

    def _systick_read(self, offset: int) -> int:
        reload = self.regs.get(0x014, 0) & 0xFFFFFF
        counts = self._systick()
        if offset == 0x018:
            self.m.clock_polled()
            return 0 if counts == 0 or reload == 0 else reload - (counts - 1) % (reload + 1)
        wrapped = reload and counts > self.st_seen_wraps * (reload + 1)
        if wrapped:  # COUNTFLAG: counted to 0 since the last read
            self.st_seen_wraps = counts // (reload + 1) + 1
        return self.regs.get(0x010, 0) | ((1 << 16) if wrapped else 0)

    # ---------------------------------------------------------------- registers
    def read(self, offset: int) -> int:
        if offset in (0x010, 0x018):
            return self._systick_read(offset)
        if 0x100 <= offset < 0x120:
            return sum(1 << b for b in range(32) if 32 * ((offset - 0x100) // 4) + b in
                       self.enabled)
        if 0x200 <= offset < 0x220:
            return sum(1 << b for b in range(32) if 16 + 32 * ((offset - 0x200) // 4) + b in
                       self.pending)
        if offset == 0xD04:  # ICSR: VECTACTIVE, VECTPENDING
            return self.active | ((min(self.pending) if self.pending else 0) << 12)
        if offset == 0xD80:  # CCSIDR of the L1 D-cache (CSSELR = 0) or I-cache
            if self.regs.get(0xD84, 0) & 1:
                return (1 << 28) | (255 << 13) | (1 << 3) | 1  # I: 16 KiB 2-way
            return (0xF << 28) | ((DCACHE_SETS - 1) << 13) | ((DCACHE_WAYS - 1) << 3) | 1
        if offset in (0xF50, 0xF58, 0xF5C, 0xF60, 0xF64, 0xF68, 0xF6C, 0xF70, 0xF74):
            self.m.violation("write-only-register",
                                f"cache maintenance register 0xE000E{offset:03X} read")
        return self.regs.get(offset, 0)

    def write(self, offset: int, value: int, size: int = 4) -> None:
        if 0x100 <= offset < 0x120:
            base = 32 * ((offset - 0x100) // 4)
            self.enabled |= {base + b for b in range(32) if (value >> b) & 1}
            self._maybe_take()
        elif 0x180 <= offset < 0x1A0:
            base = 32 * ((offset - 0x180) // 4)
            self.enabled -= {base + b for b in range(32) if (value >> b) & 1}
        elif offset == 0xD0C:
            if value >> 16 == 0x05FA and value & 4:
                self.m.request_reset("SYSRESETREQ")
        elif offset == 0xD14:
            self._ccr(value)
        elif offset == 0xD88:
            self.fpu_on = (value >> 20) & 0xF == 0xF
            self.m.fpu_enabled(self.fpu_on)
        elif offset in (0xF5C, 0xF70):  # DCIMVAC, DCCIMVAC
            self._invalidate_line(value)
        elif offset == 0xF60 or offset == 0xF74:  # DCISW, DCCISW
            self._invalidate_set((value >> 5) & (DCACHE_SETS - 1))
            self.swept.add(((value >> 5) & (DCACHE_SETS - 1), value >> 30))
        elif 0xF00 <= offset < 0xF80 or offset in (0xD84,):
            pass  # I-cache, clean-only operations, CSSELR: no state the model needs
        elif offset in (0x010, 0x018):  # SysTick enable / any write of CVR clears it
            self._systick()
            if offset == 0x018 or not self.regs.get(0x010, 0) & 1:
                self.st_counts, self.st_seen_wraps = 0.0, 1
        elif 0xD90 <= offset <= 0xDA0 or offset in (0xF34, 0xF38, 0x014):
            pass  # MPU, FPCCR/FPCAR, SysTick reload: stored
        elif 0x400 <= offset < 0x4F0 or offset in (0xD08, 0xD20, 0xD24, 0xD28, 0xD2C):
            pass  # priorities, VTOR, SHPR, fault status: stored
        else:
            self.m.violation("unmodelled-register",
                                f"write of 0x{value:08x} to 0xE000E{offset:03X} "
                                f"(pc 0x{self.m.pc():08x})")
        self.regs[offset] = value

    def _ccr(self, value: int) -> None:
        if (value >> 16) & 1 and not (self.regs.get(0xD14, 0) >> 16) & 1:
            missing = DCACHE_SETS * DCACHE_WAYS - len(self.swept)
            if missing:  # after reset the D-cache holds garbage marked valid (ARM DDI0489)
                self.m.violation("dcache-enable-without-invalidate",
                                 f"SCB_CCR.DC set at pc 0x{self.m.pc():08x} with {missing} of "
                                 f"{DCACHE_SETS * DCACHE_WAYS} set/ways never invalidated "
                                 f"(DCISW): invalidate all first, as SCB_EnableDCache does")
            for w in self.watches:
                w.fill = [-1] * len(w.fill)  # enabled after an invalidate-all

    @property
    def dcache_on(self) -> bool:
        return bool((self.regs.get(0xD14, 0) >> 16) & 1)

    # ---------------------------------------------------------------- D-cache vs DMA
    def watch(self, base: int, size: int) -> None:
        """Start tracking a buffer a DMA writes (called when a P2M stream is enabled)."""
        if any(w.base == base and w.size >= size for w in self.watches):
            return
        w = DmaWatch(base, size)
        self.watches.append(w)
        self.m.uc.hook_add(UC_HOOK_MEM_READ, self._cpu_read, w, begin=base,
                           end=base + size - 1)

    def dma_wrote(self, addr: int, n: int) -> None:
        """A DMA stream wrote bytes [addr, addr+n)."""
        self.gen += 1
        for w in self.watches:
            lo, hi = max(addr, w.base), min(addr + n, w.base + w.size)
            if lo < hi:
                w.written[lo - w.base:hi - w.base] = self.gen
                for line in range((lo - w.base) // LINE, (hi - 1 - w.base) // LINE + 1):
                    w.line_written[line] = self.gen

    def _cpu_read(self, uc: object, access: int, addr: int, size: int, value: int,
                  w: DmaWatch) -> None:
        self.m.adc.advance()  # the ring holds every sample taken until now
        if not self.dcache_on:
            return
        i = addr - w.base
        line = i // LINE
        fill = w.fill[line]
        if fill < 0:
            w.fill[line] = self.gen  # a miss: the line is filled from memory now
        elif w.line_written[line] > fill and w.written[i:i + size].max() > fill:
            self.m.violation("read-of-dma-line-not-invalidated",
                                f"CPU read 0x{addr:08x} at pc 0x{self.m.pc():08x}: the DMA "
                                f"wrote it after the cache line was filled (invalidate first)")

    def _invalidate_line(self, addr: int) -> None:
        for w in self.watches:
            if w.base <= addr < w.base + w.size:
                w.fill[(addr - w.base) // LINE] = -1

    def _invalidate_set(self, s: int) -> None:
        for w in self.watches:
            first = (s - w.base // LINE) % DCACHE_SETS
            for line in range(first, len(w.fill), DCACHE_SETS):
                w.fill[line] = -1

    # ---------------------------------------------------------------- exceptions
    def set_pending(self, irq: int) -> None:
        """A device interrupt line (IRQ number) is raised."""
        self.pending.add(16 + irq)
        self._maybe_take()

    def _maybe_take(self) -> None:
        """An enabled interrupt is pending: the slice ends at the firmware's next clock read
        (a load with no side effect, safe to repeat: unicorn re-runs the load that stops it)
        unless PRIMASK holds it off; in any case it is taken at the next slice boundary."""
        if self.active == 0 and any(e - 16 in self.enabled for e in self.pending):
            self.m.irq_soon = True

    def take_pending(self) -> None:
        """Enter the highest-priority pending, enabled exception, if the CPU may take it."""
        uc = self.m.uc
        if self.active or uc.reg_read(UC_ARM_REG_PRIMASK) & 1:
            return
        ready = sorted(e for e in self.pending if e - 16 in self.enabled)
        if not ready:
            return
        exc = ready[0]
        self.pending.discard(exc)
        regs = [uc.reg_read(r) for r in FRAME_REGS]
        fp = [uc.reg_read(r) for r in FP_REGS]
        sp = uc.reg_read(UC_ARM_REG_SP)
        align = sp & 4
        sp = (sp - align) - 32
        regs[7] = (regs[7] & ~(1 << 9)) | ((1 << 9) if align else 0)
        regs[6] &= ~1
        uc.mem_write(sp, b"".join(r.to_bytes(4, "little") for r in regs))
        self.saved.append((regs, fp, align))
        vector = int.from_bytes(uc.mem_read(self.regs[0xD08] + 4 * exc, 4), "little")
        uc.reg_write(UC_ARM_REG_SP, sp)
        uc.reg_write(UC_ARM_REG_LR, 0xFFFFFFF9)
        uc.reg_write(UC_ARM_REG_PC, vector | 1)
        self.active = exc

    def exception_return(self) -> None:
        """The handler branched to EXC_RETURN: pop the frame and resume the thread."""
        uc = self.m.uc
        if not self.saved:
            self.m.violation("bad-exception-return",
                                "branch to EXC_RETURN outside an exception handler")
        regs_saved, fp, align = self.saved.pop()
        sp = uc.reg_read(UC_ARM_REG_SP)
        frame = uc.mem_read(sp, 32)
        regs = [int.from_bytes(frame[4 * i:4 * i + 4], "little") for i in range(8)]
        for r, v in zip(FRAME_REGS, regs):
            if r != UC_ARM_REG_XPSR:
                uc.reg_write(r, v)
        uc.reg_write(UC_ARM_REG_XPSR, (regs[7] & ~0x3FF) | (1 << 24))  # flags, IT, thumb
        for r, v in zip(FP_REGS, fp):
            uc.reg_write(r, v)
        uc.reg_write(UC_ARM_REG_SP, sp + 32 + (4 if regs[7] & (1 << 9) else 0))
        uc.reg_write(UC_ARM_REG_PC, regs[6] | 1)
        self.active = 0
        self._maybe_take()
