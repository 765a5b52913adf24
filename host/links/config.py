"""Where port names come from: the command line, then DMDSM_*_PORT, then dmdsm.toml."""

from __future__ import annotations

import os
import tomllib
from pathlib import Path

from ..files import not_utf8, one_line, vector3

CONFIG_PATHS = (Path("dmdsm.toml"), Path.home() / ".config/dmdsm/config.toml")


class ConfigError(Exception):
    """A missing or malformed setting; str() says where to set it."""


def load_config(path: Path | None = None) -> dict:
    """The first config file that exists (or `path`), as a dict; {} if none. [ports] and
    [calibration] are checked here, so a typing error is named before a board is touched."""
    for p in ([path] if path else list(CONFIG_PATHS)):
        if p.exists():
            try:
                with open(p, "rb") as f:
                    doc = tomllib.load(f)
            except tomllib.TOMLDecodeError as e:
                raise ConfigError(f"{p}: not valid TOML ({e})") from None
            except UnicodeDecodeError:
                raise ConfigError(not_utf8(p, "config file")) from None
            except OSError as e:
                raise ConfigError(f"cannot read config {p}: {e.strerror}") from None
            _check(doc, p)
            return doc
    if path:
        raise ConfigError(f"config file {path} not found")
    return {}


def _check(doc: dict, p: Path) -> None:
    """ConfigError naming the file and key of a [ports] or [calibration] value of the wrong
    kind."""
    for section in ("ports", "calibration"):
        if not isinstance(doc.get(section, {}), dict):
            raise ConfigError(f"{p}: [{section}] must be a table of settings")
    for role, port in doc.get("ports", {}).items():
        if role not in ("sensor", "stage") or not isinstance(port, str) or not port:
            raise ConfigError(f"{p}: [ports] takes sensor = \"/dev/...\" and stage = "
                              f"\"/dev/...\" (got {one_line(role, 20)} = "
                              f"{one_line(repr(port), 40)})")
    cal = doc.get("calibration", {})
    try:
        for key in ("v", "n", "X_R"):
            if key in cal:
                vector3(cal[key], f"[calibration] {key}", nonzero=key != "X_R")
    except ValueError as e:
        raise ConfigError(f"{p}: {e}") from None


def resolve_port(role: str, given: str | None, config: dict) -> str:
    """The port for 'sensor' or 'stage': --ROLE, DMDSM_ROLE_PORT, or [ports] ROLE in the config."""
    port = given or os.environ.get(f"DMDSM_{role.upper()}_PORT") or \
        config.get("ports", {}).get(role)
    if not port:
        raise ConfigError(f"no {role} port: give --{role} PORT, set DMDSM_{role.upper()}_PORT, "
                          f"or put [ports] {role} = \"/dev/...\" in dmdsm.toml "
                          f"(`dmdsm ports` lists them)")
    return port
