"""What the procedures need of the two boards: typing.Protocols that StageClient, SensorClient
and the in-process fakes satisfy, split by capability (move / stage; shots / stream / sensor).

A procedure names the smallest Protocol it uses, so a reader (and a test fake) sees exactly
which methods it calls: the calibration and ranging procedures move and take shots, the step
executor also asks where the stage is and dwells, the fly executor streams, and a scan session
homes the stage and configures and disarms the sensor. tests/test_client_interfaces.py checks
the real clients and every fake against these by member names and parameter names.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import TYPE_CHECKING, Protocol

if TYPE_CHECKING:  # types only: importing this module must not import the clients
    from dmdsm.protocol import Message

    from .shots import Shots


class StageMotion(Protocol):
    """A stage that moves: enough for the calibration and ranging procedures."""

    def move(self, x: float | None = None, y: float | None = None, z: float | None = None,
             a: float | None = None, feed_mm_min: float | None = None, *,
             wait: bool = False) -> None:
        """G1 to X Y Z (mm) and A (deg) at feed_mm_min (mm/min); queued unless wait."""

    def wait(self) -> None:
        """M400: return when every queued move has finished."""


class Stage(StageMotion, Protocol):
    """The stage a scan drives: moves, position, dwell, quick stop and homing."""

    def where(self) -> dict[str, float]:
        """M114: position of the last queued move, {"X", "Y", "Z" (mm), "A" (deg)}."""

    def send(self, cmd: str) -> list[str]:
        """One G-code line (e.g. `G4 P<ms>`); the lines it printed before its ok."""

    def stop(self) -> None:
        """M410: stop now and drop queued moves; the link stays usable."""

    def home(self) -> dict[str, float]:
        """G28 X Y Z; the position after homing (mm, deg)."""


class Identity(Protocol):
    """The sensor board's handshake reply, as far as the procedures read it."""

    @property
    def tick_hz(self) -> int:
        """Rate of the device clock of time stamps and trigger phases (ticks/s)."""

    @property
    def adc_rate_hz(self) -> float:
        """ADC sample rate at sample_rate_div 1 (samples/s)."""


class DeviceIdentity(Identity, Protocol):
    """The whole handshake reply, kept in a scan file's sensor attributes."""

    @property
    def fields(self) -> dict:
        """Every field of the handshake reply by name (spec_hash, firmware version, ...)."""


class ShotSensor(Protocol):
    """A sensor that takes shots on request: calibration, ranging, step-and-shoot."""

    @property
    def identity(self) -> Identity:
        """The board's clock and ADC rates (from the handshake)."""

    def configure(self, **cfg: int) -> dict:
        """set_config (n_samples, n_average, pretrigger, ...); returns the whole config."""

    def acquire(self, n_shots: int) -> Shots:
        """Arm for n_shots waveforms and collect them; lost ones are flagged, not waited for."""


class StreamSensor(Protocol):
    """A sensor that streams while the stage sweeps: the fly scan."""

    @property
    def identity(self) -> Identity:
        """The board's clock and ADC rates (from the handshake)."""

    @property
    def motion_syncs(self) -> Iterable[Message]:
        """The stage's X and A STEP burst reports (burst_id, first/last_edge ticks, edges,
        input), latest."""

    def clock_exchanges(self, n: int = 16, spacing_s: float = 0.0
                        ) -> list[tuple[float, float, float]]:
        """n clock_sync exchanges spacing_s (s) apart: (host monotonic s, device ticks, RTT s)."""

    def stream_start(self) -> None:
        """Arm continuously: every averaged waveform is kept, in order, until stream_stop."""

    def stream_take(self, wait_s: float = 0.0) -> list[Message]:
        """The streamed waveforms that arrived since the last take, waiting up to wait_s (s)."""

    def stream_stop(self) -> tuple[list[Message], dict]:
        """Disarm; the streamed waveform messages and the device counters' change (counts)."""


class Sensor(ShotSensor, StreamSensor, Protocol):
    """The sensor a scan session uses: shots or stream, its identity and port, disarm."""

    @property
    def identity(self) -> DeviceIdentity:
        """The whole handshake reply (rates in ticks/s and samples/s, fields by name)."""

    @property
    def port_name(self) -> str:
        """The port name or URL the client opened."""

    def disarm(self) -> None:
        """Stop acquiring (after Ctrl-C: never leave the board armed)."""
