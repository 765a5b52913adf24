"""The rehosted STM32H743: unicorn's Cortex-M7 running a firmware ELF among Python peripherals.

Time is simulated. A slice runs at most `slice_instructions` instructions; every peripheral
access costs `mmio_cycles` CPU cycles, a full slice costs its instruction count. When the
firmware only polls the clock (the main loop with nothing to do), the slice stops and time
jumps to the next peripheral event, at most `idle_quantum_s` ahead, so an idle board costs
little host time and a busy one gets every instruction it would on silicon at one
instruction per cycle. Interrupts are taken between slices.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Iterable
from pathlib import Path

from unicorn import (
    UC_ARCH_ARM,
    UC_HOOK_CODE,
    UC_HOOK_INTR,
    UC_MODE_MCLASS,
    UC_MODE_THUMB,
    Uc,
    UcError,
)
from unicorn.arm_const import (
    UC_ARM_REG_PC,
    UC_ARM_REG_PRIMASK,
    UC_ARM_REG_SP,
    UC_ARM_REG_XPSR,
    UC_CPU_ARM_CORTEX_M7,
)

from .adc import Adc
from .bus import Peripheral, Plain, RuleViolation
from .dma import Dma, DmaMux
from .gpio import Crc, Gpio
from .rcc import Dbgmcu, Flash, Pwr, Rcc, Syscfg
from .system import EXC_RETURN_PAGE, System
from .timers import Tim2, Tim8
from .usart import Usart3

MAX_ELF_BYTES = 64 << 20
EXCP_EXCEPTION_EXIT = 8  # QEMU's ARM exception number for an M-profile exception return
REV_ID = {"V": 0x2003, "Y": 0x1003}
# memory of the H743ZI (RM0433 2.3.2): ITCM, flash bank 1+2, DTCM, AXI SRAM, SRAM1-4, backup
MEMORY = ((0x00000000, 64 << 10), (0x08000000, 2 << 20), (0x1FF00000, 128 << 10),
          (0x20000000, 128 << 10), (0x24000000, 512 << 10), (0x30000000, 288 << 10),
          (0x38000000, 64 << 10), (0x38800000, 4 << 10))
DMA_UNREACHABLE = ((0x00000000, 64 << 10, "ITCM"), (0x20000000, 128 << 10, "DTCM"))


def load_elf(path: Path) -> list[tuple[int, bytes]]:
    """(load address, bytes) of every PT_LOAD segment with file contents (ELF32 little-endian)."""
    path = Path(path)
    if path.stat().st_size > MAX_ELF_BYTES:
        raise ValueError(f"{path} is larger than {MAX_ELF_BYTES >> 20} MiB: not an H743 image")
    data = path.read_bytes()
    if data[:4] != b"\x7fELF" or data[4:6] != b"\x01\x01" or data[18:20] != b"\x28\x00":
        raise ValueError(f"{path} is not a 32-bit little-endian ARM ELF")
    out = []
    try:
        phoff, = struct.unpack_from("<I", data, 28)
        phentsize, phnum = struct.unpack_from("<HH", data, 42)
        for i in range(phnum):
            kind, off, _va, pa, filesz, _memsz, _fl, _al = struct.unpack_from(
                "<8I", data, phoff + i * phentsize)
            if kind == 1 and filesz:
                if off + filesz > len(data):
                    raise ValueError
                out.append((pa, data[off:off + filesz]))
    except (struct.error, ValueError):
        raise ValueError(f"{path} is a truncated or damaged ELF: rebuild it") from None
    if not any(pa == 0x08000000 for pa, _ in out):
        raise ValueError(f"{path} has nothing to load at 0x08000000 (flash): not an H743 image")
    return out


class H743:
    """One STM32H743ZI with its firmware loaded; `run_until(t)` advances simulated time (s)."""

    def __init__(self, elf: Path, rev: str = "V", faults: Iterable[str] = (),
                 slice_instructions: int = 20_000, mmio_cycles: int = 20,
                 idle_quantum_s: float = 100e-6, waive: Iterable[str] = ()) -> None:
        self.rev_id = REV_ID[rev]
        self.rev_v = rev == "V"
        self.faults = set(faults)
        self.waive = set(waive)  # rule names reported in `waived` instead of raised
        self.waived: list[str] = []
        self.slice_instructions = slice_instructions
        self.mmio_cycles = mmio_cycles
        self.idle_quantum_s = idle_quantum_s
        self.image = load_elf(elf)
        for base, data in self.image:
            if not any(b <= base and base + len(data) <= b + n for b, n in MEMORY):
                raise ValueError(f"{elf}: a segment at 0x{base:08x} ({len(data)} B) lies "
                                 f"outside the H743's memory")
        self.t = 0.0
        self.actions = 0
        self.instructions = 0  # executed in full slices (a lower bound of the total)
        self.event_sources: list[Callable[[], float]] = []
        self.uc = Uc(UC_ARCH_ARM, UC_MODE_THUMB | UC_MODE_MCLASS)
        self.uc.ctl_set_cpu_model(UC_CPU_ARM_CORTEX_M7)
        for base, size in MEMORY:
            self.uc.mem_map(base, size)
        self.uc.mem_map(EXC_RETURN_PAGE, 0x1000)
        self.uc.mem_write(EXC_RETURN_PAGE, b"\xfe\xe7" * 0x800)  # b . (never really run)
        self.uc.hook_add(UC_HOOK_CODE, self._exc_return, begin=EXC_RETURN_PAGE,
                         end=0xFFFFFFFF)
        self.uc.hook_add(UC_HOOK_INTR, self._cpu_exception)
        self.rcc, self.pwr, self.flash = Rcc(self), Pwr(self), Flash(self)
        self.system = System(self)
        self.tim2, self.tim8 = Tim2(self), Tim8(self)
        self.dma1, self.dmamux = Dma(self), DmaMux(self)
        self.adc = Adc(self)
        self.usart3, self.crc = Usart3(self), Crc(self)
        self.gpio = {p: Gpio(self, p) for p in "ABCDE"}
        self.blocks: dict[int, Peripheral] = {}
        for p in (self.rcc, self.pwr, self.flash, Syscfg(self), Dbgmcu(self), self.tim2,
                  self.tim8, self.dma1, self.dmamux, self.adc, self.adc.common, self.usart3,
                  self.crc, *self.gpio.values(),
                  Plain(self, "AXI GPV", 0x51008000)):
            for b in range(p.base & ~0xFF, p.base + p.size, 0x100):
                self.blocks[b] = p
        self.uc.mmio_map(0x40000000, 0x20000000, self._read, 0x40000000, self._write,
                         0x40000000)
        self.uc.mmio_map(0xE0000000, 0x100000, self._read, 0xE0000000, self._write,
                         0xE0000000)
        self.stopped = False
        self.irq_soon = False  # an interrupt became pending during the slice
        self._reset_reason: str | None = None
        self._fpu_hook: int | None = None
        self._error: BaseException | None = None
        self.reset(power_on=True)

    # ---------------------------------------------------------------- CPU
    def pc(self) -> int:
        """Program counter of the instruction being executed."""
        return self.uc.reg_read(UC_ARM_REG_PC)

    def reset(self, power_on: bool = False) -> None:
        """Power-on or system reset: memories keep their contents on a system reset."""
        if power_on:
            for base, data in self.image:
                self.uc.mem_write(base, data)
        for p in set(self.blocks.values()) | {self.system}:
            p.regs.clear()
            p.reset()
        sp, pc = struct.unpack("<II", self.uc.mem_read(0x08000000, 8))
        self.uc.reg_write(UC_ARM_REG_SP, sp)
        self.uc.reg_write(UC_ARM_REG_PC, pc | 1)
        self.fpu_enabled(False)

    def request_reset(self, reason: str) -> None:
        """The firmware asked for a system reset (AIRCR.SYSRESETREQ)."""
        self._reset_reason = reason
        self.stop_slice()

    def fpu_enabled(self, on: bool) -> None:
        """CPACR changed: watch for FP instructions only while CP10/CP11 are off."""
        if on and self._fpu_hook is not None:
            self.uc.hook_del(self._fpu_hook)
            self._fpu_hook = None
        elif not on and self._fpu_hook is None:
            self._fpu_hook = self.uc.hook_add(UC_HOOK_CODE, self._fpu_check, begin=0x08000000,
                                              end=0x081FFFFF)

    def _fpu_check(self, uc: Uc, address: int, size: int, _data: object) -> None:
        if size != 4:
            return
        hw1, hw2 = struct.unpack("<HH", uc.mem_read(address, 4))
        if (hw1 & 0xEC00) == 0xEC00 and (hw2 & 0x0E00) == 0x0A00:  # coprocessor 10/11
            try:
                self.violation("fpu-before-cpacr",
                               f"FP instruction at pc 0x{address:08x} before SCB_CPACR grants "
                               f"CP10/CP11 (a UsageFault on silicon)")
            except RuleViolation as e:
                self._fail(e)

    def _cpu_exception(self, uc: Uc, intno: int, _data: object) -> None:
        if intno == EXCP_EXCEPTION_EXIT:  # a branch to EXC_RETURN in handler mode
            self._exc_return(uc, self.pc(), 2, None)
            return
        self._fail(RuleViolation("cpu-exception",
                                 f"CPU exception {intno} at pc 0x{self.pc():08x} "
                                 f"(UsageFault/BusFault on silicon)"))

    def _exc_return(self, uc: Uc, address: int, size: int, _data: object) -> None:
        try:
            self.system.exception_return()
        except BaseException as e:  # noqa: BLE001 - reported after emu_start returns
            self._fail(e)

    def violation(self, rule: str, detail: str) -> None:
        """A rule was broken: raise RuleViolation, or note it if the rule is waived; the
        message always says where (the pc), added here when the model's text lacks it."""
        if "pc 0x" not in detail:
            detail = f"{detail} (pc 0x{self.pc():08x})"
        if rule in self.waive:
            self.waived.append(f"{rule}: {detail}")
            return
        raise RuleViolation(rule, detail)

    def _fail(self, e: BaseException) -> None:
        if self._error is None:
            self._error = e
        self.uc.emu_stop()

    def stop_slice(self) -> None:
        """End the running slice early (an interrupt became pending, a reset was asked)."""
        self.stopped = True
        self.uc.emu_stop()

    # ---------------------------------------------------------------- bus
    def _peripheral(self, addr: int) -> Peripheral:
        if addr >= 0xE0000000:
            if 0xE000E000 <= addr < 0xE000F000:
                return self.system
        else:
            p = self.blocks.get(addr & ~0xFF)
            if p is not None:
                return p
        raise RuleViolation("bus-fault", f"access to 0x{addr:08x} at pc 0x{self.pc():08x}: "
                            f"no peripheral there (or not modelled)")

    def _read(self, uc: Uc, offset: int, size: int, base: int) -> int:
        try:
            self.t += self.mmio_cycles / self.cpu_hz
            p = self._peripheral(base + offset)
            return p.access_read(base + offset - p.base, size)
        except BaseException as e:  # noqa: BLE001 - unicorn cannot raise through C
            self._fail(e)
            return 0

    def _write(self, uc: Uc, offset: int, size: int, value: int, base: int) -> None:
        try:
            self.t += self.mmio_cycles / self.cpu_hz
            p = self._peripheral(base + offset)
            p.access_write(base + offset - p.base, size, value)
        except BaseException as e:  # noqa: BLE001
            self._fail(e)

    def check_dma_address(self, addr: int, n: int, who: str) -> None:
        """RM0433 2.1: DMA1/DMA2 reach AXI SRAM, SRAM1-4 and flash, never the TCMs."""
        for base, size, name in DMA_UNREACHABLE:
            if addr < base + size and addr + n > base:
                self.violation("dma-into-unreachable-memory",
                                    f"{who} = 0x{addr:08x} ({name}) enabled at pc "
                                    f"0x{self.pc():08x}: the DMA cannot reach it")

    # ---------------------------------------------------------------- time
    @property
    def cpu_hz(self) -> float:
        """Current CPU clock (Hz)."""
        return self.rcc.cpu_hz()

    def clock_polled(self) -> None:
        """The firmware read its clock; with no other action since the last reads, it idles.
        A pending interrupt the CPU may take also ends the slice here."""
        if self.irq_soon and not self.uc.reg_read(UC_ARM_REG_PRIMASK) & 1:
            self.irq_soon = False
            self.stop_slice()
            return
        if self.actions == self._actions_seen:
            self._quiet += 1
            if self._quiet >= 3:
                self.idle = True
                self.uc.emu_stop()
        else:
            self._quiet = 0
            self._actions_seen = self.actions

    def next_event(self) -> float:
        """Earliest time some peripheral or the outside world changes something."""
        return min([self.t + self.idle_quantum_s] + [f() for f in self.event_sources])

    def run_until(self, t_end: float) -> None:
        """Run the firmware until simulated time t_end (s)."""
        uc = self.uc
        while self.t < t_end:
            self.advance_peripherals()
            xpsr = uc.reg_read(UC_ARM_REG_XPSR)
            in_it = ((xpsr >> 25) & 3) | ((xpsr >> 8) & 0xFC)
            if not in_it:
                self.system.take_pending()
            self.idle = self.stopped = False
            self._quiet, self._actions_seen = 0, self.actions
            start = self.t
            count = 8 if in_it else self.slice_instructions
            try:
                uc.emu_start(self.pc() | 1, 0xFFFFFFFF, count=count)
            except UcError as e:
                err = self._error or RuleViolation(
                    "bus-fault", f"{e} at pc 0x{self.pc():08x} (a HardFault on silicon)")
                self._error = None
                raise err from None
            if self._error is not None:
                err, self._error = self._error, None
                raise err
            if self._reset_reason:
                self._reset_reason = None
                self.reset()
            elif self.idle:
                self.t = max(self.t, min(self.next_event(), t_end))
            elif not self.stopped:
                self.instructions += count
                self.t = max(self.t, start + count / self.cpu_hz)
            else:
                self.t += 16 / self.cpu_hz

    def advance_peripherals(self) -> None:
        """Bring every time-driven peripheral up to self.t."""
        self.tim2.advance()
        self.usart3.advance()
