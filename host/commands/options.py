"""Options several commands share: the two boards' ports and the configuration file."""

from __future__ import annotations

import argparse
from pathlib import Path

SENSOR_HELP = "sensor port (default: $DMDSM_SENSOR_PORT, else [ports] sensor of the config)"
STAGE_HELP = "stage port (default: $DMDSM_STAGE_PORT, else [ports] stage of the config)"
CONFIG_HELP = ("TOML file with [ports] and [calibration] (default: ./dmdsm.toml, else "
               "~/.config/dmdsm/config.toml, if one exists)")


def add_ports(p: argparse.ArgumentParser, sensor: bool = True, stage: bool = True) -> None:
    """--sensor and/or --stage, and --config, as every board command takes them."""
    if sensor:
        p.add_argument("--sensor", help=SENSOR_HELP)
    if stage:
        p.add_argument("--stage", help=STAGE_HELP)
    p.add_argument("--config", type=Path, default=None, help=CONFIG_HELP)


def add_waveform_config(p: argparse.ArgumentParser) -> None:
    """--average and --samples: the sensor board's on-board averaging and waveform length
    (their ranges from the protocol's config fields; default: what the board has)."""
    from ..links.sensor import config_range

    avg, samples = config_range("n_average"), config_range("n_samples")
    p.add_argument("--average", type=int, default=None,
                   help=f"laser shots averaged on board per waveform, {avg[0]}..{avg[1]} "
                        "(default: the board's setting, 1 after power-up)")
    p.add_argument("--samples", type=int, default=None,
                   help=f"samples per waveform, {samples[0]}..{samples[1]} (default: the "
                        "board's setting, 1024 after power-up)")
