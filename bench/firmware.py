"""Firmware benchmark: flash/RAM footprint of each ARM build and the sustainable shot rate.

Shot rate is computed for the NUCLEO at 2 Mbaud (8N1: 200 000 B/s) from the exact frame size,
measured on the ARM build under QEMU (1 kHz emulated laser, UART over TCP) and measured on the
exact NUCLEO ELF on the rehosted H743 (hil_sim/boards/sensor/rehost: 1 kHz laser, USART3 at its BRR
rate, in simulated time), for 1024 and 8192 samples, with and without on-board averaging.
"Sustainable" = shots per second that reach the host as waveforms (averaged shots count
n_average times); skipped triggers (the link was busy: by design, not a loss) and
sample-integrity faults are the device's own counters.
"""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import serial

from dmdsm.host.links.link_rate import BITS_PER_BYTE, LINK_BAUD, waveform_wire_bytes
from dmdsm.protocol import FrameDecoder, Message, encode_frame
from dmdsm.sim.boards.sensor.qemu import QemuSensor

REPO = Path(__file__).resolve().parents[1]
FW = REPO / "firmware/stm32"
REGIONS = {"nucleo_h743zi": {"FLASH": (0x08000000, 0x08200000), "DTCM": (0x20000000, 0x20020000),
                             "AXI SRAM": (0x24000000, 0x24080000)},
           "qemu_an500": {"FLASH": (0x0, 0x400000), "RAM": (0x20000000, 0x20400000)}}
BURST_OVERHEAD_S = 50e-6  # edge ISR + copy-out + re-arm, a bound for a 480 MHz M7


def footprint(board: str) -> dict[str, int]:
    """Bytes used per memory region (flash counts loadable sections)."""
    subprocess.run(["make", "-s", "-C", str(FW), f"BOARD={board}"], check=True,
                   capture_output=True)
    out = subprocess.run(["arm-none-eabi-objdump", "-h", str(FW / f"build/{board}/firmware.elf")],
                         capture_output=True, text=True, check=True).stdout
    used = dict.fromkeys(REGIONS[board], 0)
    lines = out.splitlines()
    for i, line in enumerate(lines):
        parts = line.split()
        if len(parts) >= 7 and parts[0].isdigit():
            size, vma, lma = int(parts[2], 16), int(parts[3], 16), int(parts[4], 16)
            flags = lines[i + 1] if i + 1 < len(lines) else ""
            if "ALLOC" not in flags:
                continue  # debug sections
            for region, (lo, hi) in REGIONS[board].items():
                if lo <= vma < hi:
                    used[region] += size
                if "LOAD" in flags and lo <= lma < hi and vma != lma:
                    used[region] += size
    return used


def nucleo_rate(n_samples: int, n_average: int, adc_hz: float = 240e6 / 72) -> float:
    """Shots/s the NUCLEO sustains at 2 Mbaud: link-limited or capture-limited."""
    link = LINK_BAUD / BITS_PER_BYTE / waveform_wire_bytes(n_samples) * n_average
    capture = 1.0 / (n_samples / adc_hz + BURST_OVERHEAD_S)
    return min(link, capture)


def qemu_rate(url: str, n_samples: int, n_average: int, seconds: float) -> tuple[float, int]:
    """Measured delivered shots/s and triggers the device skipped over `seconds` of continuous
    arm."""
    port = serial.serial_for_url(url, timeout=0.05)
    dec = FrameDecoder()

    def cmd(m: Message) -> None:
        port.write(encode_frame(m))
        end = time.monotonic() + 3
        while time.monotonic() < end:
            if any(x.is_response and x.seq == m.seq for x in dec.feed(port.read(4096))):
                return
        raise TimeoutError(m.name)

    cmd(Message("disarm", seq=1))
    time.sleep(0.3)
    port.reset_input_buffer()
    cmd(Message("set_config", seq=2, n_samples=n_samples, sample_rate_div=1,
                n_average=n_average, pretrigger=0, trigger_edge=0, modality=0,
                sample_format=0, trigger_timeout_ms=0))
    cmd(Message("arm", seq=3, n_shots=0))
    waves, t_start, first_skip = [], None, None
    end = time.monotonic() + seconds + 1.0
    while time.monotonic() < end:
        for m in dec.feed(port.read(65536)):
            if m.name != "waveform":
                continue
            if t_start is None:  # timing starts at the first waveform
                t_start, first_skip = time.monotonic(), m.triggers_skipped
                end = t_start + seconds
            waves.append(m)
    cmd(Message("disarm", seq=4))
    port.close()
    dt = time.monotonic() - t_start
    return len(waves) * n_average / dt, waves[-1].triggers_skipped - first_skip


def rehost_rate(n_samples: int, n_average: int, seconds: float) -> dict:
    """The NUCLEO ELF on the rehosted H743, armed continuously for `seconds` of simulated time."""
    from dmdsm.sim.servers.runner import SimConfig, Simulation

    sim = Simulation(SimConfig(sensor_firmware="nucleo"))
    dec = FrameDecoder()
    got: list[Message] = []

    def cmd(m: Message, dt: float = 0.02) -> Message:
        sim.write("sensor", encode_frame(m))
        for _ in range(50):
            sim.advance(dt)
            for x in dec.feed(sim.read("sensor")):
                if x.is_response and x.seq == m.seq:
                    return x
                got.append(x)
        raise TimeoutError(m.name)

    for seq in range(100, 120):  # booted once it answers (bytes before USART3 is up are lost)
        try:
            cmd(Message("get_status", seq=seq), dt=0.005)
            break
        except TimeoutError:
            continue
    cmd(Message("set_config", seq=1, n_samples=n_samples, sample_rate_div=1,
                n_average=n_average, pretrigger=0, trigger_edge=0, modality=0,
                sample_format=0, trigger_timeout_ms=0))
    before = cmd(Message("get_status", seq=2))
    wall = time.monotonic()
    cmd(Message("arm", seq=3, n_shots=0))
    t0 = sim.t
    sim.advance(seconds)
    got += dec.feed(sim.read("sensor"))
    dt = sim.t - t0
    after = cmd(Message("disarm", seq=4)) and cmd(Message("get_status", seq=5))
    waves = [m for m in got if m.name == "waveform"]
    return {"rate": len(waves) * n_average / dt,
            "skipped": after.triggers_skipped - before.triggers_skipped,
            "integrity": after.integrity_faults - before.integrity_faults,
            "overruns": after.adc_overruns - before.adc_overruns,
            "violation": sim.sensor.violation, "wall_per_sim": (time.monotonic() - wall) / dt}


def main() -> int:
    """Print footprints and shot rates."""
    for board in ("nucleo_h743zi", "qemu_an500"):
        used = footprint(board)
        print(f"{board:14s} " + ", ".join(f"{k} {v / 1024:.1f} KiB" for k, v in used.items()))
    print("\nsustainable shot rate (shots/s reaching the host, u16 samples):")
    print(f"{'samples':>8} {'n_avg':>6} {'frame B':>8} {'NUCLEO 2 Mbaud':>15} "
          f"{'QEMU measured':>14} {'QEMU skips':>10} {'rehost':>8} {'skips':>6} "
          f"{'integrity':>9} {'overruns':>8} {'wall/sim':>8}")
    with QemuSensor() as q:
        for n in (1024, 8192):
            for avg in (1, 16):
                rate, skips = qemu_rate(q.url, n, avg, seconds=3.0)
                r = rehost_rate(n, avg, seconds=1.0)
                if r["violation"] is not None:
                    print(f"rehosted NUCLEO halted: {r['violation']}")
                    return 1
                print(f"{n:>8} {avg:>6} {waveform_wire_bytes(n):>8} {nucleo_rate(n, avg):>15.1f} "
                      f"{rate:>14.1f} {skips:>10} {r['rate']:>8.1f} {r['skipped']:>6} "
                      f"{r['integrity']:>9} {r['overruns']:>8} {r['wall_per_sim']:>8.1f}")
    print("\nQEMU and the rehost: 1 kHz emulated laser, so 1000 shots/s is the ceiling there; "
          "skipped triggers mean the link, not the capture, is the limit (counted in every "
          "waveform, no shot id lost). The rehost's rate is in simulated time over 1 s; "
          "wall/sim is the host seconds it took per simulated second.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
