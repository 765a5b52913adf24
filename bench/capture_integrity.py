"""Sample-integrity check of the NUCLEO firmware against a timing model of its capture path.

The firmware's own capture.c and integrity.c are compiled for the PC (bench/capture_model.c),
their register blocks turned into variables that a model of TIM2, TIM8, ADC1 and DMA1 keeps
up to date: sample k lands in the ring `latency` (+ up to `jitter`) ticks at 240 MHz after
its trigger. 2000 bursts per run (1024 samples, then sample_rate_div 3, then 8192 samples
with 8000 of pre-trigger); in every tenth burst one or two ADC triggers are lost or the
conversions stall. Targets: every injected fault is reported as an integrity fault, no
burst with wrong or shifted samples is reported good, no good burst is dropped.
"""

from __future__ import annotations

import itertools
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
BOARD = REPO / "firmware/stm32/board/nucleo_h743zi"
FAULTS = {0: "none", 1: "1 missed trigger", 2: "2 missed triggers", 3: "stall"}

ARMV7M = """/* bench stand-in for board/common/armv7m.h: no barriers, counted invalidations */
#ifndef DMDSM_ARMV7M_H
#define DMDSM_ARMV7M_H
#include <stdint.h>
#define DCACHE_LINE 32u
extern int fake_inval_calls;
extern uint32_t fake_inval_bytes;
static inline void irq_disable(void) {}
static inline void irq_enable(void) {}
static inline void nvic_enable(unsigned irq) { (void)irq; }
static inline void dcache_invalidate(const void *p, uint32_t n)
{
    (void)p;
    fake_inval_calls++;
    fake_inval_bytes += n;
}
#endif
"""


def fake_registers(text: str) -> str:
    """A register header with every peripheral block turned into an extern variable."""
    text = re.sub(r"#define (\w+) \(\(struct (\w+) \*\)0x[0-9A-Fa-f]+u\)",
                  lambda m: f"extern struct {m[2]} fake_{m[1].lower()};\n"
                            f"#define {m[1]} (&fake_{m[1].lower()})", text)
    text = re.sub(r"#define DMAMUX1_CCR\(ch\) .*",
                  "extern volatile uint32_t fake_dmamux[16];\n"
                  "#define DMAMUX1_CCR(ch) (fake_dmamux[ch])", text)
    return re.sub(r"#define (\w+) \(\*\(RW \*\)0x[0-9A-Fa-f]+u\)",
                  r"extern volatile uint32_t fake_\1;\n#define \1 (fake_\1)", text)


def build(work: Path) -> Path:
    """Compile the model with the firmware's capture files (ASan/UBSan); its path."""
    for name in ("h743_regs.h", "h743_capture_regs.h"):
        (work / name).write_text(fake_registers((BOARD / name).read_text()))
    for name in ("capture.c", "integrity.c"):
        shutil.copy(BOARD / name, work / name)  # so their includes find the fakes first
    (work / "armv7m.h").write_text(ARMV7M)
    shutil.copy(REPO / "bench/capture_model.c", work / "capture_model.c")
    exe = work / "capture_model"
    subprocess.run(["gcc", "-std=c11", "-O2", "-g", "-Wall", "-Wextra", "-Wno-unused-function",
                    "-fsanitize=address,undefined", "-fno-sanitize-recover=all",
                    f"-I{work}", f"-I{BOARD}", f"-I{REPO / 'firmware/stm32/core'}",
                    f"-I{REPO / 'protocol/c'}", str(work / "capture_model.c"),
                    str(REPO / "protocol/c/dmdsm_spec.c"), "-o", str(exe)], check=True)
    return exe


def main() -> int:
    """Print one line per case; exit 1 if a target is missed."""
    ok = True
    with tempfile.TemporaryDirectory() as tmp:
        exe = build(Path(tmp))
        print(f"{'latency':>7} {'jitter':>6} {'poll':>5} {'fault':>18} | {'good':>5} "
              f"{'integrity':>9} {'injected':>8} {'WRONG':>5} {'skipped':>7} "
              f"{'invalidated KiB/burst':>21}")
        for latency, jitter, poll, fault in itertools.product((0, 70, 140), (0, 30),
                                                              (50, 1000), FAULTS):
            out = subprocess.run([str(exe), str(latency), str(jitter), str(poll), str(fault),
                                  "7"], capture_output=True, text=True, check=True).stdout
            good, faults, injected, wrong, overruns, skipped, calls, nbytes = map(
                int, out.split())
            bursts = good + faults + wrong + overruns
            ok &= wrong == 0 and overruns == 0 and faults == injected
            print(f"{latency:>7} {jitter:>6} {poll:>5} {FAULTS[fault]:>18} | {good:>5} "
                  f"{faults:>9} {injected:>8} {wrong:>5} {skipped:>7} "
                  f"{nbytes / 1024 / max(bursts - faults, 1):>21.1f}")
    print("PASS" if ok else "FAIL: a fault was missed, a good burst dropped or bad data sent")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
