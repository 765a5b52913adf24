"""The Marlin patch for the Chiron + turntable, the machine limits it defines, and the facts of
stock Marlin's code (line checksum, lowest step rate) that host and emulator share."""

from .dialect import MINIMAL_STEP_RATE, MINKILL_S, QUICK_STOP_CLEAN_S, checksum, numbered
from .settings import MachineLimits, load_machine, load_settings

__all__ = ["MINIMAL_STEP_RATE", "MINKILL_S", "QUICK_STOP_CLEAN_S", "MachineLimits", "checksum",
           "load_machine", "load_settings", "numbered"]
