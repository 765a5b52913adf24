"""The command layer's error: one line shown to the user, no traceback."""

from __future__ import annotations


class CliError(Exception):
    """An error shown to the user as one line, without a traceback."""
