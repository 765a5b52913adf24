"""GPIO ports (LED pins are logged with their times) and the CRC unit of the rehosted H743."""

from __future__ import annotations

from .bus import Machine, Peripheral, field


class Gpio(Peripheral):
    """One GPIO port: MODER/AFR store, BSRR sets and resets ODR, `log` keeps output changes."""

    name = "GPIO"

    def __init__(self, machine: Machine, port: str) -> None:
        index = "ABCDEFGHIJK".index(port)
        self.name = f"GPIO{port}"
        self.base = 0x58020000 + 0x400 * index
        self.clock = (0xE0, index)
        self.log: list[tuple[float, int, int]] = []  # (time s, pin, level)
        super().__init__(machine)

    def read(self, offset: int) -> int:
        if offset == 0x10:  # IDR: outputs read back, inputs low
            return self.regs.get(0x14, 0)
        return self.regs.get(offset, 0)

    def write(self, offset: int, value: int, size: int = 4) -> None:
        if offset == 0x18:
            odr = self.regs.get(0x14, 0)
            self._set((odr | (value & 0xFFFF)) & ~(value >> 16))
            return
        if offset == 0x14:
            self._set(value & 0xFFFF)
            return
        if offset not in (0x00, 0x04, 0x08, 0x0C, 0x1C, 0x20, 0x24):
            self.action()
        self.regs[offset] = value

    def _set(self, odr: int) -> None:
        old = self.regs.get(0x14, 0)
        for pin in range(16):
            if (old ^ odr) >> pin & 1 and field(self.regs.get(0, 0), 2 * pin, 2) == 1:
                self.log.append((self.m.t, pin, (odr >> pin) & 1))
        self.regs[0x14] = odr

    def alternate(self, pin: int) -> int | None:
        """The alternate function (AFR) a pin is muxed to, or None unless MODER says AF: a
        timer input wired to a pin not set up so sees nothing."""
        if field(self.regs.get(0, 0), 2 * pin, 2) != 2:
            return None
        return field(self.regs.get(0x20 if pin < 8 else 0x24, 0), 4 * (pin % 8), 4)

    def level(self, pin: int) -> int:
        """Output level of pin now."""
        return (self.regs.get(0x14, 0) >> pin) & 1


class Crc(Peripheral):
    """CRC calculation unit: 32-bit polynomial, byte/word input reversal, output reversal."""

    name, base, clock = "CRC", 0x58024C00, (0xE0, 19)

    def reset(self) -> None:
        self.regs.update({0x10: 0xFFFFFFFF, 0x14: 0x04C11DB7})
        self.state = 0xFFFFFFFF
        self._table: tuple[int, list[int]] | None = None

    def _lut(self) -> list[int]:
        poly = self.regs[0x14]
        if self._table is None or self._table[0] != poly:
            lut = []
            for b in range(256):
                c = b << 24
                for _ in range(8):
                    c = ((c << 1) ^ poly if c & 0x80000000 else c << 1) & 0xFFFFFFFF
                lut.append(c)
            self._table = (poly, lut)
        return self._table[1]

    def read(self, offset: int) -> int:
        if offset == 0x00:
            v = self.state
            if self.regs.get(0x08, 0) & 0x80:
                v = int(f"{v:032b}"[::-1], 2)
            return v
        return self.regs.get(offset, 0)

    def write(self, offset: int, value: int, size: int = 4) -> None:
        if offset == 0x00:
            cr = self.regs.get(0x08, 0)
            rev = field(cr, 5, 2)
            if field(cr, 3, 2) != 0 or rev >= 2:  # the firmware uses 32 bits, REV_IN by byte
                self.m.violation("unmodelled-register",
                                 f"CRC_CR 0x{cr:02x}: only a 32-bit polynomial with input "
                                 f"reversed by byte or not at all is modelled")
                return
            data = (value & ((1 << (8 * size)) - 1)).to_bytes(size, "big")
            lut, c = self._lut(), self.state
            for b in data:
                if rev == 1:
                    b = int(f"{b:08b}"[::-1], 2)
                c = ((c << 8) & 0xFFFFFFFF) ^ lut[(c >> 24) ^ b]
            self.state = c
            return
        if offset == 0x08 and value & 1:
            self.state = self.regs.get(0x10, 0xFFFFFFFF)
            value &= ~1
        self.action()
        self.regs[offset] = value
