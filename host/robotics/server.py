"""The live Foxglove WebSocket server (and MCAP sink): LiveRecords as ROS 2 messages (CDR).

Topics (every message in the `sensor` frame, stamped with the record's host time as Unix
time; log time the same, in ns):

    /dmdsm/range/oa, /dmdsm/range/us        sensor_msgs/msg/Range (min/max: the depth gate)
    /dmdsm/distance/oa, /dmdsm/distance/us  dmdsm_msgs/msg/Distance (with sigma and SNR)
    /dmdsm/waveform                         dmdsm_msgs/msg/Waveform (the raw samples)
    /dmdsm/material                         dmdsm_msgs/msg/Material (with a model)

The foxglove SDK (foxglove-sdk) serves the Foxglove WebSocket protocol (`foxglove.websocket.v1`'s
messages; 0.30 names the subprotocol `foxglove.sdk.v1`, docs/robotics.md). A slow client
never holds up the acquisition: Channel.log only queues, into a bounded queue per client
(message_backlog_size) whose oldest data message is dropped when full; a client whose
control queue fills is disconnected by the SDK. Loopback only unless allow_remote.
"""

from __future__ import annotations

import ipaddress
import logging
import math
from collections.abc import Iterable

from . import messages as msgs
from .live import MODS, LiveRecord
from .mcap_file import RecordingStopped

log = logging.getLogger("dmdsm.live")

BACKLOG = 256           # data messages queued per client before its oldest is dropped
DEPTH_MM = (5.0, 71.0)  # the live ranger's depth gate (mm): Range.min_range, max_range
TOPICS = {**{f"/dmdsm/range/{m}": "sensor_msgs/msg/Range" for m in MODS},
          **{f"/dmdsm/distance/{m}": "dmdsm_msgs/msg/Distance" for m in MODS},
          "/dmdsm/waveform": "dmdsm_msgs/msg/Waveform",
          "/dmdsm/material": "dmdsm_msgs/msg/Material"}


class ServeError(ValueError):
    """--serve cannot listen where asked; str() says why and what to do."""


def record_messages(rec: LiveRecord, sample_rate_hz: float, model_name: str = ""
                    ) -> Iterable[tuple[str, str, dict]]:
    """(topic, datatype, message dict) of one record, in a fixed order: waveform, each
    modality's Range and Distance (when the record was ranged), the material (with one)."""
    t = rec.unix_s
    yield "/dmdsm/waveform", TOPICS["/dmdsm/waveform"], msgs.waveform_msg(
        t, rec.samples, shot_id=rec.seq, sample_rate_hz=sample_rate_hz,
        n_average=rec.n_average, timestamp_ticks=rec.device_ticks,
        trigger_phase_ticks=rec.trigger_phase)
    for m in MODS:
        if m not in rec.distance_mm:
            continue
        d = rec.distance_mm[m]
        yield f"/dmdsm/range/{m}", TOPICS[f"/dmdsm/range/{m}"], msgs.range_msg(
            t, math.nan if d is None else d, field_of_view_rad=msgs.FIELD_OF_VIEW_RAD,
            min_range_mm=DEPTH_MM[0], max_range_mm=DEPTH_MM[1])
        snr = rec.snr_db.get(m)
        yield f"/dmdsm/distance/{m}", TOPICS[f"/dmdsm/distance/{m}"], msgs.distance_msg(
            t, m, math.nan if d is None else d, rec.distance_std_mm.get(m),
            math.nan if snr is None else snr, shot_id=rec.seq)
    if rec.probabilities is not None:
        known = [v for v in rec.distance_mm.values() if v is not None]
        yield "/dmdsm/material", TOPICS["/dmdsm/material"], msgs.material_msg(
            t, list(rec.probabilities), list(rec.probabilities.values()), shot_id=rec.seq,
            model=model_name, distance_mm=known[0] if known else None)


def parse_serve(text: str, allow_remote: bool = False) -> tuple[str, int]:
    """HOST:PORT (or :PORT, or PORT: loopback) of --serve; a host that is not loopback is
    refused unless allow_remote."""
    host, _, port_s = text.rpartition(":") if ":" in text else ("", "", text)
    host = host.strip("[]") or "127.0.0.1"
    try:
        port = int(port_s)
        if not 0 <= port <= 65535:
            raise ValueError
    except ValueError:
        raise ServeError(f"--serve {text}: give HOST:PORT with a port 0..65535 (e.g. "
                         f"127.0.0.1:8765)") from None
    if not allow_remote and not is_loopback(host):
        raise ServeError(f"--serve {text}: {host} is not a loopback address; anyone on that "
                         f"network could watch the sensor: add --allow-remote to mean it")
    return host, port


def is_loopback(host: str) -> bool:
    """True if host names only this machine (127.0.0.0/8, ::1, localhost)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


class _Listener:
    """Logs one line per client when it leaves (unsubscribes, disconnects or is dropped
    by the SDK for not reading)."""

    def __init__(self) -> None:
        self.subscribed: dict[int, int] = {}

    def on_subscribe(self, client: object, channel: object) -> None:
        cid = int(getattr(client, "id", 0))
        self.subscribed[cid] = self.subscribed.get(cid, 0) + 1

    def on_unsubscribe(self, client: object, channel: object) -> None:
        cid = int(getattr(client, "id", 0))
        self.subscribed[cid] = self.subscribed.get(cid, 1) - 1
        if self.subscribed[cid] == 0:
            del self.subscribed[cid]
            log.warning("live: client %d left (unsubscribed, disconnected or dropped as "
                        "too slow)", cid)


class LiveServer:
    """The Foxglove WebSocket server on host:port (loopback unless allow_remote) and/or
    an MCAP recording (`recorder`: a mcap_file.McapRecorder, or any object with
    write(topic, datatype, cdr_bytes, log_time_ns)); host None: the recording alone.
    publish() never blocks on a client; a recording that stops (a full disk) is dropped
    with one line in the log and `recording_stopped` saying why, the stream goes on."""

    def __init__(self, host: str | None = "127.0.0.1", port: int = 8765, *,
                 allow_remote: bool = False, sample_rate_hz: float = 0.0,
                 model_name: str = "", backlog: int = BACKLOG,
                 recorder: object | None = None) -> None:
        import foxglove

        self.sample_rate_hz, self.model_name, self.recorder = sample_rate_hz, model_name, \
            recorder
        self.server = None
        self.recording_stopped: str | None = None  # why the recording stopped early
        self.channels: dict[str, object] = {}
        self.published = 0
        if host is None:
            return
        if not allow_remote and not is_loopback(host):
            raise ServeError(f"{host} is not a loopback address: pass allow_remote=True")
        self.context = foxglove.Context()
        for topic, dt in TOPICS.items():
            schema = foxglove.Schema(name=dt, encoding=msgs.SCHEMA_ENCODING,
                                     data=msgs.SCHEMAS[dt].encode())
            self.channels[topic] = foxglove.Channel(topic, schema=schema,
                                                    message_encoding=msgs.MESSAGE_ENCODING,
                                                    context=self.context)
        try:
            self.server = foxglove.start_server(
                name="dmdsm live", host=host, port=port, context=self.context,
                server_listener=_Listener(), message_backlog_size=backlog)
        except Exception as e:  # the SDK raises its own RuntimeError/OSError kinds
            raise ServeError(f"cannot serve on {host}:{port} ({_why(e)}): pick another port "
                             f"with --serve HOST:PORT") from None

    @property
    def port(self) -> int:
        """The port the server listens on (useful with port 0)."""
        return self.server.port if self.server is not None else 0

    def publish(self, rec: LiveRecord) -> None:
        """Encode the record's messages and hand them to the server's clients and the
        recording (queued: returns at once however slow a client is)."""
        ns = msgs.to_ns(rec.unix_s)  # the log time equals the header stamp, to the ns
        for topic, dt, msg in record_messages(rec, self.sample_rate_hz, self.model_name):
            data = msgs.encode(dt, msg)
            ch = self.channels.get(topic)
            if ch is not None:
                ch.log(data, log_time=ns)
            if self.recorder is not None:
                try:
                    self.recorder.write(topic, dt, data, ns)
                except RecordingStopped as e:  # a full disk: the file is closed, readable
                    self.recording_stopped = str(e)
                    self.recorder = None
                    log.warning("live: %s", e)
        self.published += 1

    def close(self) -> None:
        """Stop the server (clients see the connection close)."""
        if self.server is not None:
            self.server.stop()
            self.server = None
        for ch in self.channels.values():
            ch.close()
        self.channels = {}


def _why(e: BaseException) -> str:
    """A one-line reason from the SDK's error."""
    text = str(e) or type(e).__name__
    if "in use" in text.lower() or "os error 98" in text.lower():
        return "the port is in use"
    return text.splitlines()[0][:160]
