"""TIM2 (the device clock, laser edge capture on CH1) and TIM8 (ADC pacing) of the rehosted H743.

TIM2 counts the APB1 timer clock while CEN is set; its enable is TRGO (MMS = enable), which
starts TIM8 in trigger mode (ITR1 = TIM2 on TIM8, RM0433 Table 339), so both start on one
tick and TIM8's update k falls on TIM2 tick (k + 1) * (ARR + 1). Laser edges come from
`machine.laser` (rising time, falling time); CH1 captures the selected edge into CCR1, sets
CC1IF (CC1OF if it was still set) and raises IRQ 28 when CC1IE is on. Reading CCR1 clears
CC1IF. CH2 and CH3 capture the rising edges of `machine.sync` (the stage's X and A STEP
lines, the motion sync of docs/firmware.md: input 0 on CH2, 1 on CH3) into CCR2 and CCR3 the
same way (CCxIF, CCxOF, CCxIE; reading CCRx clears CCxIF), when their pins (PB3, PB10) are
muxed to TIM2 (AF1). The input filter's few-tick delay is not modelled.
"""

from __future__ import annotations

import math

from .bus import Peripheral

IRQ_TIM2 = 28
CCR = (0x34, 0x38, 0x3C)  # CCR1..CCR3 offsets


class Tim2(Peripheral):
    """32-bit general-purpose timer 2."""

    name, base, clock = "TIM2", 0x40000000, (0xE8, 0)

    def reset(self) -> None:
        self.regs[0x2C] = 0xFFFFFFFF
        self.t_start = 0.0  # time CNT was cnt0
        self.cnt0 = 0
        self.seen = 0.0     # edges up to this time are processed

    @property
    def running(self) -> bool:
        return bool(self.regs.get(0x00, 0) & 1)

    def hz(self) -> float:
        """Counting rate (Hz): timer clock / (PSC + 1)."""
        return self.m.rcc.timclk(1) / (self.regs.get(0x28, 0) + 1)

    def ticks_at(self, t: float) -> int:
        """CNT at time t (s), 32-bit."""
        if not self.running:
            return self.cnt0 & 0xFFFFFFFF
        return (self.cnt0 + math.floor((t - self.t_start) * self.hz() + 1e-6)) & 0xFFFFFFFF

    def read(self, offset: int) -> int:
        if offset == 0x24:
            self.m.clock_polled()
            return self.ticks_at(self.m.t)
        if offset in CCR:
            self.advance()
            self.regs[0x10] = self.regs.get(0x10, 0) & ~(1 << (CCR.index(offset) + 1))
            self.action()
        elif offset == 0x10:
            self.advance()
        return self.regs.get(offset, 0)

    def write(self, offset: int, value: int, size: int = 4) -> None:
        self.action()
        if offset == 0x00:
            was = self.running
            cnt = self.ticks_at(self.m.t)
            self.regs[0] = value
            self.cnt0, self.t_start = cnt, self.m.t
            if value & 1 and not was:
                self.seen = self.m.t
                if (self.regs.get(0x04, 0) >> 4) & 7 == 1:  # TRGO on enable
                    self.m.tim8.trigger(self.m.t)
            return
        if offset == 0x24:
            self.cnt0, self.t_start = value, self.m.t
        elif offset == 0x10:  # rc_w0
            value &= self.regs.get(0x10, 0)
        elif offset == 0x0C and value & self.regs.get(0x10, 0) & 0xE:
            self.m.system.set_pending(IRQ_TIM2)
        elif offset == 0x2C and value != 0xFFFFFFFF:
            self.m.violation("unmodelled-register", "TIM2 ARR other than 0xFFFFFFFF")
        self.regs[offset] = value

    def advance(self) -> None:
        """Capture every laser edge up to now."""
        laser = getattr(self.m, "laser", None)
        now = self.m.t
        if laser is None or now <= self.seen:
            return
        ccer, ccmr = self.regs.get(0x20, 0), self.regs.get(0x18, 0)
        events = []
        if self.running and ccer & 1 and ccmr & 3 == 1:
            events += [(fall if ccer & 2 else rise, 1) for rise, fall in
                       laser.edges(self.seen, now)]
        sync = getattr(self.m, "sync", None)
        ccmr2 = self.regs.get(0x1C, 0)
        gpiob = self.m.gpio["B"]
        for ch, on in ((2, ccer & 0x10 and (ccmr >> 8) & 3 == 1    # CC2E, CC2S = TI2, PB3
                        and gpiob.alternate(3) == 1),              # in AF1 (TIM2_CH2)
                       (3, ccer & 0x100 and ccmr2 & 3 == 1         # CC3E, CC3S = TI3, PB10
                        and gpiob.alternate(10) == 1)):            # in AF1 (TIM2_CH3)
            if sync is not None and self.running and on:
                events += [(float(t), ch) for t in sync.edges(self.seen, now, ch - 2)]
        for t, ch in sorted(events):
            self._capture(t, ch)
        self.seen = now

    def _capture(self, t: float, ch: int = 1) -> None:
        flag = 1 << ch  # CC1IF / CC2IF / CC3IF, and the same bit of DIER
        sr = self.regs.get(0x10, 0)
        if sr & flag:
            sr |= flag << 8  # CCxOF: the previous capture was not read
        self.regs[0x10] = sr | flag
        self.regs[CCR[ch - 1]] = self.ticks_at(t)
        if self.regs.get(0x0C, 0) & flag:
            self.m.system.set_pending(IRQ_TIM2)


class Tim8(Peripheral):
    """Advanced timer 8 as the ADC's pacer: update every ARR + 1 ticks after its start."""

    name, base, clock = "TIM8", 0x40010400, (0xF0, 1)

    def reset(self) -> None:
        self.t_start: float | None = None

    def hz(self) -> float:
        """Counting rate (Hz)."""
        return self.m.rcc.timclk(2) / (self.regs.get(0x28, 0) + 1)

    def period_s(self) -> float:
        """Time between update events (s)."""
        return (self.regs.get(0x2C, 0) + 1) / self.hz()

    def trigger(self, t: float) -> None:
        """TRGO of the master: start counting if in trigger mode on ITR1."""
        smcr = self.regs.get(0x08, 0)
        if smcr & 7 == 6 and (smcr >> 4) & 7 == 1:
            self.regs[0] = self.regs.get(0, 0) | 1
            self.t_start = t
            self.m.adc.restart(t)

    def write(self, offset: int, value: int, size: int = 4) -> None:
        self.action()
        if offset == 0x00:
            if value & 1 and not self.regs.get(0, 0) & 1:
                self.t_start = self.m.t
                self.m.adc.restart(self.m.t)
            elif not value & 1:
                self.m.adc.pacer_stopped()
                self.t_start = None
        elif offset in (0x28, 0x2C) and self.t_start is not None:
            self.m.violation("unmodelled-register",
                                "TIM8 PSC/ARR changed while counting (preload not modelled)")
        self.regs[offset] = value
