"""Peripheral plumbing of the rehosted H743: register files behind unicorn MMIO and the rule checks.

Every model is a `Peripheral` owning a block of the address map. Reads and writes arrive as
(offset, size, value); a model overrides `read`/`write` for registers with behaviour and keeps
plain storage for the rest. A firmware sequence that RM0433 forbids raises `RuleViolation`,
which stops the CPU and fails the test that ran it with the rule's name.
"""

from __future__ import annotations

from typing import Any, Protocol


class Machine(Protocol):
    """What a peripheral sees of its chip (`h743.H743`, which imports the peripherals, so they
    name it by this protocol, not by an import back): time, CPU, rule checks and, as
    attributes, the other peripherals."""

    t: float
    actions: int
    faults: set[str]
    irq_soon: bool
    rev_id: int
    rev_v: bool

    def pc(self) -> int: ...

    def violation(self, rule: str, detail: str) -> None: ...

    def __getattr__(self, name: str) -> Any: ...  # uc, cpu_hz, rcc, adc, dma1, usart3, ...


class RuleViolation(AssertionError):
    """The firmware broke a rule of the reference manual; `rule` names it, str() says where."""

    def __init__(self, rule: str, detail: str) -> None:
        super().__init__(f"{rule}: {detail}")
        self.rule = rule


def field(value: int, shift: int, width: int) -> int:
    """Bits [shift, shift+width) of value."""
    return (value >> shift) & ((1 << width) - 1)


class Peripheral:
    """A block of registers at `base` (`size` bytes); unmodelled registers keep what is written."""

    name = "peripheral"
    base = 0
    size = 0x400
    # RCC enable register (offset) and bit that clocks this block; None: always clocked
    clock: tuple[int, int] | None = None

    def __init__(self, machine: Machine) -> None:
        self.m = machine
        self.regs: dict[int, int] = {}
        self.reset()

    def reset(self) -> None:
        """Reset values (override to set non-zero ones)."""

    # -- access from the CPU (size 1, 2 or 4; unaligned sub-word accesses are merged)
    def access_read(self, offset: int, size: int) -> int:
        self.check_clock("read", offset)
        word = self.read(offset & ~3)
        return (word >> (8 * (offset & 3))) & ((1 << (8 * size)) - 1)

    def access_write(self, offset: int, size: int, value: int) -> None:
        self.check_clock("write", offset)
        if size == 4:
            self.write(offset, value & 0xFFFFFFFF, size)
            return
        shift = 8 * (offset & 3)
        mask = ((1 << (8 * size)) - 1) << shift
        old = self.regs.get(offset & ~3, 0)
        self.write(offset & ~3, (old & ~mask) | ((value << shift) & mask), size)

    def check_clock(self, what: str, offset: int) -> None:
        """RM0433 8.5.11: a peripheral whose kernel/bus clock is off ignores writes, reads 0."""
        if self.clock is None:
            return
        reg, bit = self.clock
        if not (self.m.rcc.regs.get(reg, 0) >> bit) & 1:
            self.m.violation("peripheral-clock-off",
                                f"{what} of {self.name}+0x{offset:03x} at pc 0x{self.m.pc():08x} "
                                f"before its clock is enabled in RCC+0x{reg:03x} bit {bit}")
        self.m.rcc.check_enabled(reg, bit, f"{self.name}+0x{offset:03x} ({what})")

    def read(self, offset: int) -> int:
        """Value of the 32-bit register at offset."""
        return self.regs.get(offset, 0)

    def write(self, offset: int, value: int, size: int = 4) -> None:
        """The CPU writes value to the register at offset."""
        self.regs[offset] = value

    def action(self) -> None:
        """Note an access with a side effect: the CPU is not idle-polling."""
        self.m.actions += 1


class Plain(Peripheral):
    """Registers that only store what the firmware writes (pin multiplexing, MPU-free blocks)."""

    def __init__(self, machine: Machine, name: str, base: int, size: int = 0x400,
                 clock: tuple[int, int] | None = None) -> None:
        self.name, self.base, self.size, self.clock = name, base, size, clock
        super().__init__(machine)
