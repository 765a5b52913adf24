"""ctypes binding of the PC build of the sensor firmware core (firmware/stm32/board/pc)."""

from __future__ import annotations

import ctypes
import os
import subprocess
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[3]
LIB_PATH = REPO / "firmware/stm32/build/pc/libdmdsm_core.so"
CAPTURE_OVERRUN, CAPTURE_INTEGRITY = 1, 2  # enum dmdsm_capture (firmware/stm32/core/core.h)


class FirmwareBuildError(RuntimeError):
    """The PC build of the firmware core is missing and could not be built."""


class SetConfig(ctypes.Structure):
    """struct dmdsm_set_config from protocol/c/dmdsm_spec.h."""

    _fields_ = [("n_samples", ctypes.c_uint16), ("sample_rate_div", ctypes.c_uint16),
                ("n_average", ctypes.c_uint16), ("pretrigger", ctypes.c_uint16),
                ("trigger_edge", ctypes.c_uint8), ("modality", ctypes.c_uint8),
                ("sample_format", ctypes.c_uint8), ("trigger_timeout_ms", ctypes.c_uint32)]


def _load() -> ctypes.CDLL:
    path = Path(os.environ.get("DMDSM_CORE_LIB", LIB_PATH))
    if not path.exists():
        if not (REPO / "firmware/stm32/Makefile").exists():
            raise FirmwareBuildError(f"{path} not found; set DMDSM_CORE_LIB to the library")
        r = subprocess.run(["make", "-s", "-C", str(REPO / "firmware/stm32"), "BOARD=pc"],
                           capture_output=True, text=True)
        if r.returncode or not path.exists():
            raise FirmwareBuildError(f"building the firmware core for the PC failed: "
                                     f"{r.stderr.strip().splitlines()[-1:] or r.returncode}")
    lib = ctypes.CDLL(str(path))
    p, u8, u16, u32 = ctypes.c_void_p, ctypes.c_uint8, ctypes.c_uint16, ctypes.c_uint32
    buf = ctypes.c_char_p
    lib.dmdsm_pc_new.restype = p
    lib.dmdsm_pc_new.argtypes = [ctypes.c_char_p, u32, u32, u16, u32]
    lib.dmdsm_pc_free.argtypes = [p]
    lib.dmdsm_pc_set_ticks.argtypes = [p, u32]
    lib.dmdsm_pc_rx.argtypes = [p, buf, ctypes.c_size_t]
    lib.dmdsm_pc_tx.argtypes = [p, p, ctypes.c_size_t]
    lib.dmdsm_pc_tx.restype = ctypes.c_size_t
    lib.dmdsm_pc_armed.argtypes = [p, ctypes.POINTER(SetConfig)]
    lib.dmdsm_pc_capture.argtypes = [p, p, u32, u16, ctypes.c_int]
    lib.dmdsm_pc_takes_shot.argtypes = [p, u32]
    lib.dmdsm_pc_takes_shot.restype = ctypes.c_int
    lib.dmdsm_pc_sync_edges.argtypes = [p, ctypes.c_uint, p, ctypes.c_size_t]
    lib.dmdsm_pc_poll.argtypes = [p]
    lib.dmdsm_pc_set_link_rate.argtypes = [p, u32]
    lib.dmdsm_pc_state.argtypes = [p]
    lib.dmdsm_pc_state.restype = u8
    return lib


class FirmwareCore:
    """One emulated sensor board running the real firmware core; the caller owns time, physics."""

    _lib: ctypes.CDLL | None = None

    def __init__(self, name: str = "SIL", tick_hz: int = 240_000_000,
                 adc_rate_hz: int = 3_333_333, max_samples: int = 8192) -> None:
        if FirmwareCore._lib is None:
            FirmwareCore._lib = _load()
        self._l = FirmwareCore._lib
        self.tick_hz = tick_hz
        self._dev = self._l.dmdsm_pc_new(name.encode(), tick_hz, adc_rate_hz, max_samples, 0)
        if not self._dev:
            raise MemoryError("dmdsm_pc_new failed")
        self._txbuf = ctypes.create_string_buffer(1 << 16)

    def close(self) -> None:
        """Free the device."""
        if getattr(self, "_dev", None):
            self._l.dmdsm_pc_free(self._dev)
            self._dev = None

    def __del__(self) -> None:
        self.close()

    def set_ticks(self, ticks: int) -> None:
        """Set the device's 32-bit tick counter (wraps) and run its main loop once."""
        self._l.dmdsm_pc_set_ticks(self._dev, ticks & 0xFFFFFFFF)

    def set_link_rate(self, bytes_per_s: float) -> None:
        """Tell the board the rate (bytes/s) its link drains at, as a real board knows its
        baud rate: it then times shots on a busy link so each waveform meets a free wire."""
        self._l.dmdsm_pc_set_link_rate(self._dev, max(0, min(int(bytes_per_s), 0xFFFFFFFF)))

    def rx(self, data: bytes) -> None:
        """Bytes from the host."""
        self._l.dmdsm_pc_rx(self._dev, data, len(data))

    def tx(self, max_bytes: int = 1 << 16) -> bytes:
        """Up to max_bytes the device sends (the link model decides how many per step)."""
        n = self._l.dmdsm_pc_tx(self._dev, self._txbuf, min(max_bytes, len(self._txbuf)))
        return self._txbuf.raw[:n]

    def armed(self) -> dict | None:
        """The burst configuration if the core waits for a laser edge, else None."""
        cfg = SetConfig()
        if not self._l.dmdsm_pc_armed(self._dev, ctypes.byref(cfg)):
            return None
        return {name: getattr(cfg, name) for name, _ in SetConfig._fields_}

    def takes_shot(self, edge_ticks: int) -> bool:
        """Whether a good burst at edge_ticks (the ticks now) would be averaged: False when
        the core is not armed or would skip the shot for want of a free waveform slot."""
        return bool(self._l.dmdsm_pc_takes_shot(self._dev, edge_ticks & 0xFFFFFFFF))

    def capture(self, samples: np.ndarray, edge_ticks: int, phase_ticks: int = 0,
                overrun: bool = False, integrity_fault: bool = False) -> None:
        """Deliver one burst (n_samples u16 ADC counts) for an edge at edge_ticks (ticks).

        phase_ticks: edge to first sample (ticks). overrun: the ADC/DMA overran (counted in
        adc_overruns); integrity_fault: the board found the DMA's write position disagreeing
        with its timer (counted in integrity_faults). Either way the burst is not averaged."""
        s = np.ascontiguousarray(samples, dtype=np.uint16)
        result = CAPTURE_OVERRUN if overrun else CAPTURE_INTEGRITY if integrity_fault else 0
        self._l.dmdsm_pc_capture(self._dev, s.ctypes.data, edge_ticks & 0xFFFFFFFF,
                                 phase_ticks, result)

    def sync_edges(self, ticks: np.ndarray, input: int = 0) -> None:
        """Rising edges on motion-sync input `input` (0 = X, 1 = A STEP line) at these 32-bit
        ticks, in time order."""
        t = np.ascontiguousarray(np.asarray(ticks, dtype=np.int64) & 0xFFFFFFFF,
                                 dtype=np.uint32)
        if t.size:
            self._l.dmdsm_pc_sync_edges(self._dev, input, t.ctypes.data, t.size)

    @property
    def state(self) -> int:
        """Acquisition state (enum state of the spec)."""
        return self._l.dmdsm_pc_state(self._dev)
