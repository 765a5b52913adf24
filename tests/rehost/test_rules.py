"""Each hardware rule the rehost enforces catches a deliberately wrong start-up sequence."""

import numpy as np
import pytest

from dmdsm.sim.boards.sensor.rehost import H743, RuleViolation


def run(elf, seconds=0.01, **kw) -> H743:
    m = H743(elf, **kw)
    m.analog = lambda k, t, grid: (k % 4096).astype(np.uint16)
    m.run_until(seconds)
    return m


def test_the_right_sequences_pass_and_the_dma_fills_the_buffer(sequence_elf):
    m = run(sequence_elf(0))
    assert m.adc.conversions > 256  # paced, converted and written round the ring
    assert m.dma1.sreg(0, 0) & 1 and m.system.dcache_on


@pytest.mark.parametrize("case,rule", [
    (1, "adc-enable-before-calibration"),
    (2, "adc-stop-while-idle"),
    (3, "clock-switch-before-vos-ready"),
    (4, "dma-into-unreachable-memory"),
    (5, "read-of-dma-line-not-invalidated"),
    (7, "fpu-before-cpacr"),
    (8, "bus-fault"),
    (9, "clock-enable-without-readback"),
])
def test_a_wrong_sequence_fails_with_the_rule_named(sequence_elf, case, rule):
    with pytest.raises(RuleViolation) as e:
        run(sequence_elf(case))
    assert e.value.rule == rule
    assert "pc 0x08" in str(e.value)  # says where in the program


def test_a_waived_rule_is_reported_not_raised(sequence_elf):
    m = run(sequence_elf(2), waive={"adc-stop-while-idle"})
    assert len(m.waived) == 1 and m.waived[0].startswith("adc-stop-while-idle")
