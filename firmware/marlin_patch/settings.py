"""Stage-board settings (chiron_turntable.toml): machine limits shared by patch, emulator, host."""

from __future__ import annotations

import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

SETTINGS_PATH = Path(__file__).with_name("chiron_turntable.toml")


@dataclass(frozen=True)
class MachineLimits:
    """Per-axis limits of the Chiron + turntable, axes X Y Z in mm and A in degrees."""

    axes: tuple[str, ...]
    steps_per_unit: tuple[float, ...]
    max_feedrate: tuple[float, ...]       # mm/s (A: deg/s)
    max_acceleration: tuple[float, ...]   # mm/s^2 (A: deg/s^2)
    homing_feedrate_mm_m: tuple[float, ...]
    default_acceleration: float           # mm/s^2
    min_pos: tuple[float, ...]            # soft limits, mm (A: deg)
    max_pos: tuple[float, ...]
    baudrate: int
    bufsize: int
    block_buffer_size: int
    rx_buffer_size: int
    max_cmd_size: int
    keepalive_interval_s: float
    junction_deviation_mm: float = 0.013  # JUNCTION_DEVIATION_MM: corner speed limit (mm)
    min_segment_time_us: int = 20000  # DEFAULT_MINSEGMENTTIME: SLOWDOWN's floor (us)
    slowdown_divisor: int = 2  # SLOWDOWN_DIVISOR: slow down below buffer / divisor blocks

    def axis(self, name: str) -> int:
        """Index of an axis letter (X, Y, Z, A)."""
        return self.axes.index(name.upper())


def load_settings(path: Path = SETTINGS_PATH) -> dict[str, Any]:
    """The whole settings file as a dict."""
    with open(path, "rb") as f:
        return tomllib.load(f)


def load_machine(path: Path = SETTINGS_PATH) -> MachineLimits:
    """The [machine] table as MachineLimits."""
    m = load_settings(path)["machine"]
    tuples = {k: tuple(v) for k, v in m.items() if isinstance(v, list)}
    scalars = {k: v for k, v in m.items() if not isinstance(v, list)}
    return MachineLimits(**tuples, **scalars)


def marlin_value(value: Any) -> str:
    """A settings value as Marlin writes it: lists as `{ a, b, c }`, numbers plainly."""
    if isinstance(value, list):
        return "{ " + ", ".join(marlin_value(v) for v in value) + " }"
    if isinstance(value, float) and value.is_integer():
        return str(int(value))
    return str(value)
