"""The installed dmdsm's version, from its package metadata (pyproject.toml's `version`)."""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("dmdsm")
except PackageNotFoundError:  # a source tree on sys.path that pip never installed
    __version__ = "0+unknown"
