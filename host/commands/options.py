"""Options several commands share: the two boards' ports and the configuration file."""

from __future__ import annotations

import argparse
from pathlib import Path

SENSOR_HELP = "sensor port (or DMDSM_SENSOR_PORT, dmdsm.toml)"
STAGE_HELP = "stage port (or DMDSM_STAGE_PORT, dmdsm.toml)"
CONFIG_HELP = "TOML file with [ports] and [calibration]"


def add_ports(p: argparse.ArgumentParser, sensor: bool = True, stage: bool = True) -> None:
    """--sensor and/or --stage, and --config, as every board command takes them."""
    if sensor:
        p.add_argument("--sensor", help=SENSOR_HELP)
    if stage:
        p.add_argument("--stage", help=STAGE_HELP)
    p.add_argument("--config", type=Path, default=None, help=CONFIG_HELP)
