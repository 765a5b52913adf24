"""The dmdsm host: device links, ranging, calibration, scanning and the `dmdsm` command."""

__version__ = "0.1.0"
