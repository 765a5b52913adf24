"""Protocol benchmark: host decode/encode throughput of 8 KiB waveform frames and link efficiency.

Targets (DESIGN.md §8): decode >= 120 MB/s of frames (100x USB full speed) with the cobs C
extension loaded; >= 99 % of wire bytes are waveform samples. Exits 1 if a target is missed.
"""

from __future__ import annotations

import sys
import time

import numpy as np

from dmdsm.protocol import FrameDecoder, Message, cobs_extension_loaded, encode_frame

N_FRAMES = 2000
N_SAMPLES = 4096  # 8 KiB of u16 samples
CHUNK = 64 * 1024
USB_FS = 1.2e6  # B/s, USB full-speed bulk ceiling


def waveform(i: int, samples: np.ndarray) -> Message:
    """A waveform message like the firmware sends."""
    return Message("waveform", seq=i & 0xFFFF, shot_id=i, timestamp=i * 2_400_000,
                   trigger_phase=i % 72, n_average=16, pretrigger=64, sample_rate_div=1,
                   sample_format=0, modality=0, triggers_skipped=0, adc_overruns=0,
                   integrity_faults=0, sync_steps=0, sync_steps_a=0, samples=samples)


def best_of(n: int, fn) -> float:
    """Smallest wall time of n runs of fn (s)."""
    times = []
    for _ in range(n):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def main() -> int:
    """Run the benchmark and print its figures."""
    ok = True
    ext = cobs_extension_loaded()
    print(f"cobs C extension loaded: {ext}")
    ok &= ext
    rng = np.random.default_rng(0)
    t = np.arange(N_SAMPLES)
    # 16-bit ADC trace: mid-scale offset, an echo burst and noise
    trace = 32768 + 8000 * np.exp(-((t - 1500) / 40.0) ** 2) * np.sin(t / 3) \
        + rng.normal(0, 30, N_SAMPLES)
    samples = trace.astype("<u2")
    msgs = [waveform(i, samples) for i in range(N_FRAMES)]

    frames: list[bytes] = []
    t_enc = best_of(3, lambda: frames.__setitem__(slice(None), [encode_frame(m) for m in msgs]))
    stream = b"".join(frames)
    chunks = [stream[i:i + CHUNK] for i in range(0, len(stream), CHUNK)]

    def decode() -> None:
        dec = FrameDecoder()
        n = 0
        for c in chunks:
            n += len(dec.feed(c))
        assert n == N_FRAMES and dec.stats.errors == 0

    t_dec = best_of(5, decode)
    dec_rate = len(stream) / t_dec
    enc_rate = len(stream) / t_enc
    print(f"frames: {N_FRAMES} x {len(frames[0])} B ({N_SAMPLES} u16 samples), "
          f"fed in {CHUNK // 1024} KiB chunks")
    print(f"decode: {dec_rate / 1e6:8.1f} MB/s  ({N_FRAMES / t_dec:,.0f} frames/s, "
          f"{dec_rate / USB_FS:.0f}x USB full speed)   target >= 120 MB/s")
    print(f"encode: {enc_rate / 1e6:8.1f} MB/s  ({N_FRAMES / t_enc:,.0f} frames/s)")
    ok &= dec_rate >= 120e6

    worst = encode_frame(waveform(0, np.full(N_SAMPLES, 0x0101, "<u2")))
    for label, frame in (("ADC trace", frames[0]), ("worst case, no zero byte", worst)):
        eff_samples = 2 * N_SAMPLES / len(frame)
        eff_payload = (2 * N_SAMPLES + 30) / len(frame)
        print(f"link efficiency ({label}): {eff_samples:.2%} samples/wire, "
              f"{eff_payload:.2%} payload/wire, {len(frame)} wire bytes   target >= 99 %")
        ok &= eff_samples >= 0.99
    print("PASS" if ok else "FAIL: a target was missed")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
