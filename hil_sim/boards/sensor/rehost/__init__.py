"""The NUCLEO-H743ZI firmware ELF, unchanged, on the unicorn CPU with Python peripherals."""

from .bus import RuleViolation
from .h743 import H743

__all__ = ["H743", "RuleViolation"]
