"""Device links (the only I/O with the boards): transports by port name or URL, the sensor
and stage clients, port configuration and the stage's safe envelope. Knows nothing of scans."""

from .config import ConfigError, load_config, resolve_port
from .interfaces import Sensor, ShotSensor, Stage, StageMotion, StreamSensor
from .safety import TABLE_I, KeepOut, UnsafeMove, check_move
from .sensor import SensorClient
from .stage import StageClient
from .transport import LinkError, open_port

__all__ = [
    "check_move", "ConfigError", "KeepOut", "LinkError", "load_config", "open_port",
    "resolve_port", "Sensor", "SensorClient", "ShotSensor", "Stage", "StageClient",
    "StageMotion", "StreamSensor", "TABLE_I", "UnsafeMove",
]
