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


def done(m: H743) -> bool:
    """The program reached its DONE() (GPIOK's clock enable, which nothing else sets)."""
    return bool(m.rcc.regs.get(0xE0, 0) >> 10 & 1)


WRONG = [
    (1, "adc-enable-before-calibration"),
    (2, "adc-stop-while-idle"),
    (3, "clock-switch-before-vos-ready"),
    (4, "dma-into-unreachable-memory"),
    (5, "read-of-dma-line-not-invalidated"),
    (7, "fpu-before-cpacr"),
    (8, "bus-fault"),
    (9, "clock-enable-without-readback"),
    (10, "dcache-enable-without-invalidate"),
    (13, "adc-without-kernel-clock"),
    (14, "adc-enable-during-calibration"),
    (15, "clock-above-voltage-scale"),
    (16, "flash-latency-too-low"),
    (18, "dma-into-unreachable-memory"),
    (19, "dma-config-while-enabled"),
    (20, "dma-config-while-enabled"),
    (21, "adc-config-while-converting"),
    (22, "clock-enable-without-readback"),
    (23, "clock-switch-to-unready-pll"),
    (24, "usart-brr-while-enabled"),
    (25, "pll-config-while-on"),
    (27, "adc-calibration-before-regulator"),
    (28, "adc-calibration-while-enabled"),
    (29, "adc-disable-while-converting"),
    (30, "adc-regulator-in-deep-power-down"),
    (31, "adc-start-before-ready"),
    (32, "overdrive-outside-vos1"),
    (33, "peripheral-clock-off"),
    (34, "pll-without-source"),
    (35, "voltage-scale-below-clock"),
    (36, "write-only-register"),
    (37, "cpu-exception"),  # thread mode: EXC_RETURN is an XN address, a HardFault
    (38, "usart-dma-not-enabled"),
]


@pytest.mark.parametrize("case,rule", WRONG)
def test_a_wrong_sequence_fails_with_the_rule_named(sequence_elf, case, rule):
    with pytest.raises(RuleViolation) as e:
        run(sequence_elf(case))
    assert e.value.rule == rule
    assert "pc 0x08" in str(e.value) or case == 37  # where in the program (37: the bad branch's
    assert "pc 0x" in str(e.value)                  # target, the pc the fault was taken at)


@pytest.mark.parametrize("case", [11, 12, 17, 26])
def test_a_correct_sequence_runs_to_its_end(sequence_elf, case):
    """HAL's PLL and HSE off-and-on (RDY flags clear: no hang), DIVM2 = 0 with the ADC unused
    (no crash), 480 MHz on VOS0 on rev V, PLL1 set up while PLL2 runs."""
    assert done(run(sequence_elf(case)))


def test_480_mhz_is_beyond_a_rev_y_part(sequence_elf):
    with pytest.raises(RuleViolation) as e:
        run(sequence_elf(17), rev="Y")
    assert e.value.rule == "clock-above-voltage-scale" and "rev Y" in str(e.value)


def test_the_idle_buffer_of_a_double_buffered_stream_may_change(sequence_elf):
    """Case 20 rewrites M1AR while CT = 0 (legal) and then M0AR (the buffer in use): only the
    second is the violation, after DONE()."""
    m = H743(sequence_elf(20))
    m.analog = lambda k, t, grid: (k % 4096).astype(np.uint16)
    with pytest.raises(RuleViolation) as e:
        m.run_until(0.01)
    assert done(m) and "+0x0c" in str(e.value)


def test_every_rule_of_the_models_has_a_wrong_program_and_a_row_in_the_docs():
    import re
    from pathlib import Path

    src = Path(__file__).resolve().parents[2] / "hil_sim/boards/sensor/rehost"
    rules = set()
    for f in src.glob("*.py"):
        rules |= set(re.findall(r'violation\(\s*"([a-z0-9-]+)"', f.read_text()))
    docs = (Path(__file__).resolve().parents[2] / "docs/firmware.md").read_text()
    tested = {r for _, r in WRONG} | {"clock-above-voltage-scale"}
    untested = sorted(r for r in rules - tested if f"`{r}`" not in docs.split(
        "not caught by a test program")[-1])
    assert not untested, f"rules with neither a wrong program nor a documented reason: {untested}"
    missing = sorted(r for r in rules if f"`{r}`" not in docs)
    assert not missing, f"rules not in docs/firmware.md: {missing}"


def test_a_waived_rule_is_reported_not_raised(sequence_elf):
    m = run(sequence_elf(2), waive={"adc-stop-while-idle"})
    assert len(m.waived) == 1 and m.waived[0].startswith("adc-stop-while-idle")
