"""Clocks and power of the rehosted H743: RCC, PWR, SYSCFG, FLASH and DBGMCU, with their rules.

Ready flags rise after a settling time in simulated time (HSE bypass 10 us, PLL lock 100 us,
voltage scaling 50 us), so bounded waits are exercised. `faults` switches a part off to test
start-up diagnostics: "hse" (HSERDY never rises), "pll" (no lock), "vos" (the ODEN write is
lost, VOS0 never comes). The rules: a clock switch must wait for VOSRDY and respect the VOS
and flash-latency limits; a PLL is configured only while off; a peripheral is touched only
after its clock enable was read back (ES0392 2.2.x, ST's HAL does the same read-back).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from .bus import Peripheral, field

if TYPE_CHECKING:
    pass

HSI_HZ = 64_000_000
HSE_HZ = 8_000_000  # ST-LINK MCO, bypass mode
HSE_READY_S, PLL_LOCK_S, VOS_SETTLE_S = 10e-6, 100e-6, 50e-6
# highest CPU clock per voltage scale (RM0433 rev 8 Table 8 / DS12110): rev V reaches 480 MHz
# in VOS0; rev Y is a 400 MHz part, overdrive or not
VOS_LIMIT_HZ = {0: 480e6, 1: 400e6, 2: 300e6, 3: 200e6}
VOS_LIMIT_REV_Y_HZ = {0: 400e6, 1: 400e6, 2: 300e6, 3: 200e6}
# which bits of each PLL register belong to PLL1 / PLL2 (RCC_CR ON bit, field mask): a PLL's
# fields may change only while that PLL is off; PLLSRC only while both are
PLL_FIELDS = {0x028: ((24, 0x3 | 0x3F << 4), (26, 0x3 | 0x3F << 12)),
              0x02C: ((24, 0xF | 0x7 << 16), (26, 0xF << 4 | 0x7 << 19)),
              0x030: ((24, 0xFFFFFFFF), (26, 0)), 0x034: ((24, 0xFFFFFFFF), (26, 0)),
              0x038: ((24, 0), (26, 0xFFFFFFFF)), 0x03C: ((24, 0), (26, 0xFFFFFFFF))}
CR_READY_BITS = {0: 2, 16: 17, 24: 25, 26: 27}  # RCC_CR oscillator/PLL ON bit -> its RDY bit
CR_READ_ONLY = (1 << 2) | (1 << 17) | (1 << 25) | (1 << 27) | (1 << 29)  # RDY flags: hardware
ENABLE_REGS = (0xD4, 0xD8, 0xDC, 0xE0, 0xE4, 0xE8, 0xEC, 0xF0, 0xF4)


def _ahb_div(code: int) -> int:
    return 1 if code < 8 else (2, 4, 8, 16, 64, 128, 256, 512)[code - 8]


def _apb_div(code: int) -> int:
    return 1 if code < 4 else (2, 4, 8, 16)[code - 4]


def flash_wait_states(hclk_hz: float) -> int:
    """Wait states the AXI clock needs at VOS0/VOS1 (RM0433 Table 17)."""
    for ws, top in enumerate((70e6, 140e6, 185e6, 225e6, 240e6)):
        if hclk_hz <= top:
            return ws
    return 7


class Rcc(Peripheral):
    """Reset and clock control: oscillators, PLL1/PLL2, system switch, bus prescalers, enables."""

    name, base = "RCC", 0x58024400

    def reset(self) -> None:
        self.regs.update({0x000: 0x1, 0x010: 0, 0x018: 0, 0x01C: 0, 0x020: 0, 0x028: 0x02020200,
                          0x02C: 0x01FF0000, 0x030: 0x01010280, 0x038: 0x01010280})
        self.ready_at: dict[int, float] = {2: 0.0}  # CR ready bit -> time it rises (HSI on)
        self.unread: set[tuple[int, int]] = set()  # enables not yet read back
        self._cpu_hz: float | None = None
        self._timclk: dict[int, float] = {}

    def read(self, offset: int) -> int:
        self.unread.clear()  # any RCC read completes the enable writes before it
        v = self.regs.get(offset, 0)
        if offset == 0x000:  # a RDY flag is set while its source runs and has settled
            for bit in CR_READY_BITS.values():
                at = self.ready_at.get(bit)
                v = v | (1 << bit) if at is not None and self.m.t >= at else v & ~(1 << bit)
        elif offset == 0x010:
            v = (v & ~0x38) | ((v & 7) << 3)  # SWS follows SW (checked on write)
        return v

    def write(self, offset: int, value: int, size: int = 4) -> None:
        old = self.regs.get(offset, 0)
        self.action()
        self._cpu_hz = None
        self._timclk.clear()
        if offset == 0x000:
            value &= ~CR_READ_ONLY  # a read-modify-write stores no ready flag back
            self._oscillators(old, value)
        elif offset in PLL_FIELDS:
            changed = value ^ old
            for pll, (on_bit, mask) in enumerate(PLL_FIELDS[offset], start=1):
                if changed & mask and self.regs[0] >> on_bit & 1:
                    self.m.violation("pll-config-while-on",
                                     f"RCC+0x{offset:03x} = 0x{value:08x} written at pc "
                                     f"0x{self.m.pc():08x} changes PLL{pll}'s fields while "
                                     f"PLL{pll} is on (RM0433 8.7.11: configure it while off)")
        elif offset == 0x010:
            self.regs[offset] = value
            self._switch(value & 7)
        elif offset == 0x018:
            self.regs[offset] = value
            self.check_limits(f"RCC_D1CFGR = 0x{value:08x}")
        elif offset in ENABLE_REGS:
            for bit in range(32):
                if (value >> bit) & 1 and not (old >> bit) & 1:
                    self.unread.add((offset, bit))
        self.regs[offset] = value

    def _oscillators(self, old: int, value: int) -> None:
        t, f = self.m.t, self.m.faults
        for on, rdy, delay, fault in ((0, 2, 0.0, ""), (16, 17, HSE_READY_S, "hse"),
                                      (24, 25, PLL_LOCK_S, "pll"), (26, 27, PLL_LOCK_S, "pll")):
            if (value >> on) & 1 and not (old >> on) & 1:
                if on >= 24 and not self.source_ready():
                    self.m.violation("pll-without-source",
                                        f"PLL enabled at pc 0x{self.m.pc():08x} before its "
                                        f"input oscillator is ready")
                self.ready_at[rdy] = float("inf") if fault and fault in f else t + delay
            elif not (value >> on) & 1:
                self.ready_at.pop(rdy, None)

    def source_ready(self) -> bool:
        src = self.regs[0x028] & 3
        return src == 0 or (src == 2 and self.m.t >= self.ready_at.get(17, float("inf")))

    def _switch(self, sw: int) -> None:
        if sw == 0:
            return
        if sw != 3:
            self.m.violation("unmodelled-clock", f"SW={sw}: only HSI and PLL1 are modelled")
        if self.m.t < self.ready_at.get(25, float("inf")):
            self.m.violation("clock-switch-to-unready-pll",
                                f"SW=PLL1 at pc 0x{self.m.pc():08x} before PLL1RDY")
        if not self.m.pwr.vos_ready():
            self.m.violation("clock-switch-before-vos-ready",
                                f"SW=PLL1 at pc 0x{self.m.pc():08x} while PWR_D3CR.VOSRDY is 0")
        self.check_limits("SW=PLL1")

    def vos_limit_hz(self, vos: int) -> float:
        """Highest CPU clock (Hz) of this part at voltage scale `vos`."""
        return (VOS_LIMIT_HZ if self.m.rev_v else VOS_LIMIT_REV_Y_HZ)[vos]

    def check_limits(self, what: str) -> None:
        """The clock in force against the voltage scale and the flash wait states, after any
        write that changes one of them (the switch, D1CPRE/HPRE, FLASH_ACR, VOS)."""
        cpu = self.sysclk() / _ahb_div(field(self.regs[0x018], 8, 4))
        vos = self.m.pwr.vos()
        pc = self.m.pc()
        if cpu > self.vos_limit_hz(vos):
            rev = "rev V" if self.m.rev_v else "rev Y"
            self.m.violation("clock-above-voltage-scale",
                                f"{what} at pc 0x{pc:08x} gives {cpu / 1e6:.0f} MHz but VOS{vos} "
                                f"on a {rev} part allows {self.vos_limit_hz(vos) / 1e6:.0f} MHz")
        hclk = cpu / _ahb_div(field(self.regs[0x018], 0, 4))
        ws = self.m.flash.regs.get(0, 0) & 0xF
        if ws < flash_wait_states(hclk):
            self.m.violation("flash-latency-too-low",
                                f"{what} at pc 0x{pc:08x} gives AXI {hclk / 1e6:.0f} MHz with "
                                f"{ws} flash wait states (needs {flash_wait_states(hclk)})")

    def adc_clock_running(self) -> bool:
        """PLL2 P, the ADC's kernel clock: PLL2 on and locked, DIVM2 set and DIVP2EN."""
        return (self.m.t >= self.ready_at.get(27, float("inf"))
                and field(self.regs[0x028], 12, 6) != 0
                and bool((self.regs[0x02C] >> 19) & 1))

    def check_enabled(self, reg: int, bit: int, who: str) -> None:
        """Raise if `who` is accessed right after its enable with no read-back between."""
        if (reg, bit) in self.unread:
            self.m.violation("clock-enable-without-readback",
                                f"{who} accessed at pc 0x{self.m.pc():08x} right after its "
                                f"clock enable; read RCC back first (ES0392, HAL's delay)")

    # ---------------------------------------------------------------- derived clocks
    def pll_p(self, n: int) -> float:
        """P output of PLL n (Hz) from its source, M divider and DIVR (integer mode)."""
        sel = self.regs[0x028]
        src = (HSI_HZ, 4e6, HSE_HZ, 0)[sel & 3]
        m = field(sel, 4 if n == 1 else 12, 6)
        divr = self.regs[0x030 if n == 1 else 0x038]
        if m == 0:
            return 0.0
        return src / m * (field(divr, 0, 9) + 1) / (field(divr, 9, 7) + 1)

    def sysclk(self) -> float:
        """System clock (Hz): HSI at reset, PLL1 P after the switch."""
        return self.pll_p(1) if (self.regs[0x010] & 7) == 3 else float(HSI_HZ)

    def cpu_hz(self) -> float:
        """Cortex-M7 clock (Hz) = sysclk / D1CPRE (cached until the next RCC write)."""
        if self._cpu_hz is None:
            self._cpu_hz = self.sysclk() / _ahb_div(field(self.regs[0x018], 8, 4))
        return self._cpu_hz

    def hclk(self) -> float:
        """AXI/AHB clock (Hz)."""
        return self.cpu_hz() / _ahb_div(field(self.regs[0x018], 0, 4))

    def pclk(self, apb: int) -> float:
        """APB1 (1) or APB2 (2) clock (Hz)."""
        code = field(self.regs[0x01C], 4 if apb == 1 else 8, 3)
        return self.hclk() / _apb_div(code)

    def timclk(self, apb: int) -> float:
        """Timer kernel clock on APB1/APB2 (Hz): 2 x PCLK when the APB prescaler is > 1."""
        if apb not in self._timclk:  # cleared by every RCC write
            code = field(self.regs[0x01C], 4 if apb == 1 else 8, 3)
            self._timclk[apb] = self.pclk(apb) * (2 if _apb_div(code) > 1 else 1)
        return self._timclk[apb]

    def adc_hz(self) -> float:
        """ADC kernel clock (Hz) seen by the converter: pll2_p, halved by the ADC on rev V."""
        if field(self.regs.get(0x058, 0), 16, 2) != 0:
            self.m.violation("unmodelled-clock", "ADCSEL other than pll2_p")
        return self.pll_p(2) / (2 if self.m.rev_v else 1)


class Pwr(Peripheral):
    """Power control: supply configuration and the voltage scale (VOS1..3, VOS0 via ODEN)."""

    name, base = "PWR", 0x58024800

    def reset(self) -> None:
        self.regs.update({0x0C: 0x6, 0x18: 1 << 14, 0x04: (1 << 13) | (3 << 14)})
        self.settle_at = 0.0
        self.od = False

    def vos(self) -> int:
        """Voltage scale in force: 0 (overdrive) .. 3."""
        code = field(self.regs[0x18], 14, 2)
        scale = {3: 1, 2: 2, 1: 3, 0: 3}[code]
        return 0 if scale == 1 and self.od else scale

    def vos_ready(self) -> bool:
        return self.m.t >= self.settle_at

    def read(self, offset: int) -> int:
        v = self.regs.get(offset, 0)
        if offset == 0x18:
            v = v | (1 << 13) if self.vos_ready() else v & ~(1 << 13)
        elif offset == 0x04:  # ACTVOS: the scale in force, ACTVOSRDY
            act = {0: 3, 1: 3, 2: 2, 3: 1}[self.vos()]
            v = (v & ~(3 << 14)) | (act << 14)
        return v

    def write(self, offset: int, value: int, size: int = 4) -> None:
        self.action()
        if offset == 0x18 and field(value, 14, 2) != field(self.regs[0x18], 14, 2):
            if self.m.rcc.sysclk() > self.m.rcc.vos_limit_hz({3: 1, 2: 2, 1: 3, 0: 3}[
                    field(value, 14, 2)]):
                self.m.violation("voltage-scale-below-clock",
                                    f"PWR_D3CR = 0x{value:08x} at pc 0x{self.m.pc():08x} "
                                    f"lowers VOS below what the running clock needs")
            self.settle_at = self.m.t + VOS_SETTLE_S
        self.regs[offset] = value

    def overdrive(self, on: bool) -> None:
        """SYSCFG_PWRCR.ODEN changed (RM0433 6.6.2: only from VOS1)."""
        if on and field(self.regs[0x18], 14, 2) != 3:
            self.m.violation("overdrive-outside-vos1",
                             f"SYSCFG_PWRCR.ODEN set at pc 0x{self.m.pc():08x} while VOS is "
                             f"not VOS1")
        if on != self.od and "vos" not in self.m.faults:
            self.od = on
            self.settle_at = self.m.t + VOS_SETTLE_S


class Syscfg(Peripheral):
    """System configuration: PWRCR.ODEN (the overdrive for VOS0); the rest stores."""

    name, base, clock = "SYSCFG", 0x58000400, (0xF4, 1)

    def read(self, offset: int) -> int:
        v = self.regs.get(offset, 0)
        if offset == 0x2C and "vos" in self.m.faults:
            v &= ~1  # the write was lost: the read-back shows it
        return v

    def write(self, offset: int, value: int, size: int = 4) -> None:
        self.action()
        self.regs[offset] = value
        if offset == 0x2C:
            self.m.pwr.overdrive(bool(value & 1))


class Flash(Peripheral):
    """Flash interface: ACR.LATENCY (checked against the clock whenever either changes);
    reads back what was written."""

    name, base = "FLASH", 0x52002000

    def reset(self) -> None:
        self.regs[0] = 0x37  # 7 wait states, WRHIGHFREQ 3 at reset

    def write(self, offset: int, value: int, size: int = 4) -> None:
        self.action()
        self.regs[offset] = value
        if offset == 0:
            self.m.rcc.check_limits(f"FLASH_ACR = 0x{value:08x}")


class Dbgmcu(Peripheral):
    """Debug MCU: IDCODE gives the silicon revision the model was built for."""

    name, base = "DBGMCU", 0x5C001000

    def read(self, offset: int) -> int:
        return (self.m.rev_id << 16) | 0x450 if offset == 0 else self.regs.get(offset, 0)
