"""The Marlin patch for the Chiron + turntable, the machine limits it defines, and the facts of
stock Marlin's code (line checksum, lowest step rate) that host and emulator share."""

from .marlin import MINIMAL_STEP_RATE, checksum
from .settings import MachineLimits, load_machine, load_settings

__all__ = ["MINIMAL_STEP_RATE", "MachineLimits", "checksum", "load_machine", "load_settings"]
