"""Where port names come from: the command line, then DMDSM_*_PORT, then dmdsm.toml."""

from __future__ import annotations

import os
import tomllib
from pathlib import Path

CONFIG_PATHS = (Path("dmdsm.toml"), Path.home() / ".config/dmdsm/config.toml")


class ConfigError(Exception):
    """A missing or malformed setting; str() says where to set it."""


def load_config(path: Path | None = None) -> dict:
    """The first config file that exists (or `path`), as a dict; {} if none."""
    for p in ([path] if path else list(CONFIG_PATHS)):
        if p.exists():
            try:
                with open(p, "rb") as f:
                    return tomllib.load(f)
            except tomllib.TOMLDecodeError as e:
                raise ConfigError(f"{p}: not valid TOML ({e})") from None
    if path:
        raise ConfigError(f"config file {path} not found")
    return {}


def resolve_port(role: str, given: str | None, config: dict) -> str:
    """The port for 'sensor' or 'stage': --ROLE, DMDSM_ROLE_PORT, or [ports] ROLE in the config."""
    port = given or os.environ.get(f"DMDSM_{role.upper()}_PORT") or \
        config.get("ports", {}).get(role)
    if not port:
        raise ConfigError(f"no {role} port: give --{role} PORT, set DMDSM_{role.upper()}_PORT, "
                          f"or put [ports] {role} = \"/dev/...\" in dmdsm.toml "
                          f"(`dmdsm ports` lists them)")
    return port
