"""The Marlin patch for the Chiron + turntable, and the machine limits it defines."""

from .settings import MachineLimits, load_machine, load_settings

__all__ = ["MachineLimits", "load_machine", "load_settings"]
