"""ADC1 of the rehosted H743: power-up, calibration and enable rules, TIM8-paced conversions.

Conversions: each TIM8 update while ADSTART is set (EXTSEL = TIM8_TRGO, rising edge) starts
one conversion of (sampling + 8.5) ADC cycles at 16 bits (RM0433 25.4.13), whose result the
DMA stores one ADC cycle (the trigger's resynchronisation) after it ends; a trigger that
arrives while the previous conversion runs is ignored, with no overrun flag, exactly the
failure the firmware's DMA-position check must catch. Each result goes to the DMA stream
whose DMAMUX request is ADC1 (9). `miss_trigger_after(t)` injects one ignored trigger.
The sample values come from `machine.analog(k, t, grid)` (k: update index since TIM8 start).
Rules: the regulator is enabled out of deep power-down only; calibration runs with the
regulator settled, ADEN = 0 and the kernel clock (PLL2 P) running; ADEN only after a
completed calibration and never while one runs; ADSTART only when ready; ADSTP only while a
conversion sequence runs (ADSTART = 1); the configuration registers (CFGR, CFGR2, SMPR1/2,
PCSEL, SQR1..4) are written only with ADSTART = 0 (RM0433 25.4.x: "software is allowed to
write these bits only when ADSTART = 0").
"""

from __future__ import annotations

import math

import numpy as np

from .bus import Machine, Peripheral, field

VREG_START_S, CAL_S, ADRDY_S = 10e-6, 200e-6, 2e-6
DMAMUX_REQ_ADC1 = 9
RS_BITS = (1 << 31) | 0x3F  # ADC_CR bits the software can only set (RM0433 25.6.3)
CONFIG_REGS = {0x0C: "ADC_CFGR", 0x10: "ADC_CFGR2", 0x14: "ADC_SMPR1", 0x18: "ADC_SMPR2",
               0x1C: "ADC_PCSEL", 0x30: "ADC_SQR1", 0x34: "ADC_SQR2", 0x38: "ADC_SQR3",
               0x3C: "ADC_SQR4"}
MAX_BATCH = 1 << 16  # conversions materialised per catch-up (more than any DMA ring)
SAMPLING_CYCLES = (1.5, 2.5, 8.5, 16.5, 32.5, 64.5, 387.5, 810.5)


class AdcCommon(Peripheral):
    """ADC1/ADC2 common registers (CCR: clock mode and prescaler)."""

    name, base, clock = "ADC12_COMMON", 0x40022300, (0xD8, 5)

    def write(self, offset: int, value: int, size: int = 4) -> None:
        if offset == 0x08 and (field(value, 16, 2) != 0 or field(value, 18, 4) != 0):
            self.m.violation("unmodelled-clock", "ADC CKMODE/PRESC other than async /1")
        self.regs[offset] = value


class Adc(Peripheral):
    """ADC1 (the transducer input, channel 3)."""

    name, base, size, clock = "ADC1", 0x40022000, 0x100, (0xD8, 5)

    def __init__(self, machine: Machine) -> None:
        super().__init__(machine)
        self.common = AdcCommon(machine)

    def reset(self) -> None:
        self.regs[0x08] = 1 << 29  # DEEPPWD
        self.vreg_at = math.inf
        self.cal_end = math.inf
        self.calibrated = False
        self.rdy_at = math.inf
        self.t_start: float | None = None  # TIM8 start
        self.next_k = 0                    # next update index to consider
        self.busy_until = -math.inf
        self.written = 0                   # conversions delivered since the DMA start
        self.misses: list[float] = []
        self.conversions = 0
        self.ignored = 0
        self._t_done = -1.0

    def miss_trigger_after(self, t: float) -> None:
        """Fault injection: the first trigger after t (s) is ignored (a late conversion)."""
        self.misses.append(t)

    # ---------------------------------------------------------------- registers
    def read(self, offset: int) -> int:
        v = self.regs.get(offset, 0)
        t = self.m.t
        if offset == 0x08:
            if v >> 31 and t >= self.cal_end:
                v &= ~(1 << 31)
                self.regs[0x08] = v
                self.calibrated = True
        elif offset == 0x00:
            if self.regs.get(0x08, 0) & 1 and t >= self.rdy_at:
                v |= 1
            self.advance()
            v |= self.regs.get(0x00, 0) & 0x10
        return v

    def write(self, offset: int, value: int, size: int = 4) -> None:
        self.action()
        if offset == 0x00:  # ISR: write 1 to clear
            self.regs[0] = self.regs.get(0, 0) & ~value  # ADRDY follows ADEN here
            return
        if offset == 0x08:
            self._cr(self.regs.get(0x08, 0), value)
            return
        if offset in CONFIG_REGS and self.regs.get(0x08, 0) & 4:
            self.m.violation("adc-config-while-converting",
                                f"{CONFIG_REGS[offset]} = 0x{value:08x} written at pc "
                                f"0x{self.m.pc():08x} with ADSTART = 1")
        self.regs[offset] = value

    def _cr(self, old: int, new: int) -> None:
        t, pc = self.m.t, self.m.pc()
        new |= old & RS_BITS  # ADEN, ADDIS, ADSTART, ADSTP, ADCAL: writing 0 does nothing
        if new & 2 and not old & 2:  # ADDIS
            if old & 4:
                self.m.violation("adc-disable-while-converting",
                                 f"ADDIS with ADSTART = 1 (pc 0x{pc:08x}); stop it first")
            new &= ~(1 | 2)
            self.rdy_at = math.inf
        if old >> 31 and t >= self.cal_end:
            old &= ~(1 << 31)
            self.calibrated = True
        if new & (1 << 28) and not old & (1 << 28):
            if new & (1 << 29):
                self.m.violation("adc-regulator-in-deep-power-down",
                                    f"ADVREGEN set with DEEPPWD = 1 (pc 0x{pc:08x})")
            self.vreg_at = t + VREG_START_S
        if new >> 31 and not old >> 31:
            if not self.m.rcc.adc_clock_running():
                self.m.violation("adc-without-kernel-clock",
                                 f"ADCAL at pc 0x{pc:08x} with the ADC kernel clock (PLL2 P: "
                                 f"PLL2 locked, DIVM2 > 0, DIVP2EN) stopped: it never ends")
            self.calibrated = False  # a new calibration replaces the last one
            if old & 1:
                self.m.violation("adc-calibration-while-enabled",
                                    f"ADCAL with ADEN = 1 (pc 0x{pc:08x})")
            if t < self.vreg_at:
                self.m.violation("adc-calibration-before-regulator",
                                    f"ADCAL {1e6 * (self.vreg_at - t):.1f} us before the "
                                    f"regulator settles (T_ADCVREG_STUP, pc 0x{pc:08x})")
            self.cal_end = math.inf if "adc" in self.m.faults else t + CAL_S
        if new & 1 and not old & 1:
            if old >> 31:
                self.m.violation("adc-enable-during-calibration",
                                 f"ADEN at pc 0x{pc:08x} while ADCAL = 1 (RM0433 25.4.8: wait "
                                 f"for ADCAL to clear)")
            elif not self.calibrated:
                self.m.violation("adc-enable-before-calibration",
                                    f"ADEN at pc 0x{pc:08x} before a completed ADCAL")
            self.rdy_at = t + ADRDY_S
        if new & 4 and not old & 4:
            if not old & 1 or t < self.rdy_at:
                self.m.violation("adc-start-before-ready",
                                    f"ADSTART at pc 0x{pc:08x} before ADRDY")
            self.advance()
        if new & 0x10:
            if not old & 4:
                self.m.violation("adc-stop-while-idle",
                                    f"ADSTP at pc 0x{pc:08x} while ADSTART = 0 (RM0433 "
                                    f"25.4.17: only while a conversion is ongoing)")
            self.advance()
            new &= ~(0x10 | 4)  # stops at once in the model
        self.regs[0x08] = new

    # ---------------------------------------------------------------- conversions
    def restart(self, t: float) -> None:
        """TIM8 (re)started at t: update k falls at t + (k + 1) * period."""
        self.advance()  # the results of the old pacing, if TIM8 was not stopped first
        self._t_done = -1.0
        self.t_start, self.next_k = t, 0

    def pacer_stopped(self) -> None:
        """TIM8 stopped: no more triggers (results already converting still land)."""
        self.advance()
        self.t_start = None

    def conversion_s(self) -> float:
        """Duration of one 16-bit conversion (s) at the channel's sampling time."""
        smp = SAMPLING_CYCLES[field(self.regs.get(0x14, 0), 9, 3)]  # channel 3
        return (smp + 8.5) / self.m.rcc.adc_hz()  # advance() runs only with the clock on

    def advance(self) -> None:
        """Convert every trigger up to now and hand the results to the DMA."""
        m = self.m
        if m.t == self._t_done or self.t_start is None or not m.tim8.regs.get(0, 0) & 1:
            return
        if not m.rcc.adc_clock_running():  # no kernel clock: nothing converts
            return
        self._t_done = m.t
        period = m.tim8.period_s()
        # a result reaches memory one ADC cycle (trigger resynchronisation) plus the
        # conversion after its trigger: only those are in the ring by now
        ready = m.t - self.conversion_s() - 1.0 / m.rcc.adc_hz()
        k_now = math.floor((ready - self.t_start) / period + 1e-9) - 1
        if k_now < self.next_k:
            return
        ks = np.arange(self.next_k, k_now + 1)
        self.next_k = k_now + 1
        cr, cfgr = self.regs.get(0x08, 0), self.regs.get(0x0C, 0)
        if not cr & 4 or field(cfgr, 5, 5) != 7 or field(cfgr, 10, 2) != 1:
            return
        times = self.t_start + (ks + 1) * period
        keep = times >= self.busy_until
        conv = self.conversion_s()
        if conv > period:  # triggers inside a conversion are lost
            step = math.ceil(conv / period)
            keep &= (ks - ks[keep.argmax()]) % step == 0 if keep.any() else keep
        for t_miss in list(self.misses):
            late = np.nonzero(keep & (times > t_miss))[0]
            if late.size:
                keep[late[0]] = False
                self.misses.remove(t_miss)
        self.ignored += int((~keep).sum())
        ks, times = ks[keep], times[keep]
        if not ks.size:
            return
        self.busy_until = times[-1] + conv
        self.conversions += ks.size
        if field(cfgr, 0, 2) == 3:
            old = ks.size - MAX_BATCH  # overwritten in the ring before anyone could read them
            if old > 0:
                m.dma1.from_peripheral(DMAMUX_REQ_ADC1, None, skip=old)
                ks, times = ks[old:], times[old:]
            m.dma1.from_peripheral(DMAMUX_REQ_ADC1, m.analog(ks, times, (self.t_start, period)))
        else:
            self.m.violation("unmodelled-register", "ADC DMNGT other than DMA circular")
