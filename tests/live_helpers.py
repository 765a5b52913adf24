"""Shared by tests/test_live*.py and bench/live.py: the emulator's truth time of every laser
shot and waveform frame on the host's clock, and a foxglove.websocket.v1 test client."""

from __future__ import annotations

import asyncio
import json
import struct
import threading
import time

import numpy as np

from dmdsm.protocol import FrameDecoder

# foxglove-sdk 0.30 accepts only the protocol's new name, foxglove.sdk.v1 (the same
# messages as foxglove.websocket.v1, renamed; foxglove/ros-foxglove-bridge#382)
SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]


class EmulatorTimes:
    """The truth time on the host's clock of what an emulator's sensor board does. Install
    it before emu.start(). The emulator paces simulated time to the wall: sim time s is
    due at host monotonic wall0 + (s - sim0) / speed (its pacing), and the board takes the
    host's bytes a little after that (its loop's lag, measured at every receive). A board
    event at s is therefore at host time pacing(s) + the median receive lag: the instant a
    clock_sync request sent then is stamped s. `sent`: host monotonic (s) at which each
    waveform's last byte left the board (keyed by its timestamp, ticks)."""

    def __init__(self, emu: object) -> None:
        board = emu.sim.sensor
        self.tick_hz = float(board.core.tick_hz)
        self.speed = float(emu.server.speed)
        self.wall0 = self.sim0 = float("nan")
        self.lags: list[float] = []
        self.sent: dict[int, float] = {}
        serve, receive, tx, decoder = emu.server._serve, board.receive, board.core.tx, \
            FrameDecoder()

        def serving() -> None:
            self.sim0, self.wall0 = emu.sim.t, time.monotonic()
            serve()

        def receiving(data: bytes, now: float) -> None:
            self.lags.append(time.monotonic() - self.pacing(now))
            receive(data, now)

        def sending(max_bytes: int = 1 << 16) -> bytes:
            data = tx(max_bytes)
            if data:
                t = time.monotonic()
                for m in decoder.feed(data):
                    if m.name == "waveform":
                        self.sent[int(m.timestamp)] = t
            return data

        emu.server._serve, board.receive, board.core.tx = serving, receiving, sending

    def pacing(self, sim_s: float) -> float:
        """Host monotonic time (s) at which the emulator's pacing puts simulated time sim_s."""
        return self.wall0 + (sim_s - self.sim0) / self.speed

    def laser_s(self, ticks: int) -> float:
        """Host monotonic time (s) of the laser edge at device `ticks`."""
        lag = float(np.median(self.lags)) if self.lags else 0.0
        return self.pacing(int(ticks) / self.tick_hz) + lag


class WsClient:
    """A foxglove.websocket.v1 client (`websockets`; offered under both names, SUBPROTOCOLS)
    on its own thread:
    subscribes to every advertised channel, keeps (topic, log time ns, payload, host
    monotonic s of arrival) for each binary message data frame; `read=False` subscribes
    and then never reads again (a stalled client)."""

    def __init__(self, url: str, read: bool = True) -> None:
        self.url, self.read = url, read
        self.channels: dict[int, dict] = {}
        self.messages: list[tuple[str, int, bytes, float]] = []
        self.subscribed = threading.Event()
        self.changed = threading.Condition()
        self.stop = threading.Event()
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=lambda: asyncio.run(self._run()), daemon=True)
        self.thread.start()

    async def _run(self) -> None:
        import websockets

        try:
            async with websockets.connect(self.url, subprotocols=SUBPROTOCOLS,
                                          max_size=None, max_queue=4) as ws:
                assert ws.subprotocol in SUBPROTOCOLS
                subs: dict[int, str] = {}
                while not self.stop.is_set():
                    try:
                        msg = await asyncio.wait_for(ws.recv(), 0.1)
                    except TimeoutError:
                        continue
                    if isinstance(msg, str):
                        obj = json.loads(msg)
                        if obj.get("op") == "advertise":
                            new = []
                            for ch in obj["channels"]:
                                self.channels[ch["id"]] = ch
                                subs[ch["id"]] = ch["topic"]
                                new.append({"id": ch["id"], "channelId": ch["id"]})
                            await ws.send(json.dumps({"op": "subscribe",
                                                      "subscriptions": new}))
                            self.subscribed.set()
                            if not self.read:  # never read again: the server must cope
                                while not self.stop.is_set():
                                    await asyncio.sleep(0.05)
                                return
                        continue
                    now = time.monotonic()
                    if msg[0] != 0x01:
                        continue
                    sub_id, log_ns = struct.unpack_from("<IQ", msg, 1)
                    with self.changed:
                        self.messages.append((subs[sub_id], log_ns, bytes(msg[13:]), now))
                        self.changed.notify_all()
        except BaseException as e:  # noqa: BLE001 (reported to the test)
            self.error = e
            self.subscribed.set()

    def wait_for(self, topic: str, n: int, timeout_s: float) -> list[tuple[int, bytes, float]]:
        """The first n messages on topic (log time ns, payload, arrival s), waiting up to
        timeout_s for them."""
        end = time.monotonic() + timeout_s
        with self.changed:
            while True:
                got = [(t, p, a) for tp, t, p, a in self.messages if tp == topic]
                if len(got) >= n or time.monotonic() > end or self.error:
                    return got
                self.changed.wait(0.1)

    def close(self) -> None:
        """Leave and wait for the thread."""
        self.stop.set()
        self.thread.join(5)


def rosbags_decoder(schema_name: str, schema_text: str):
    """A CDR decoder for one advertised channel, from its ros2msg schema text alone
    (rosbags' own parser and deserializer: nothing of dmdsm's)."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    ts = get_typestore(Stores.EMPTY)
    types: dict = {}
    parts = schema_text.split("=" * 80 + "\n")
    types.update(get_types_from_msg(parts[0], schema_name))
    for part in parts[1:]:
        head, _, body = part.partition("\n")
        name = head.removeprefix("MSG: ").strip()
        if "/msg/" not in name:
            name = name.replace("/", "/msg/")
        types.update(get_types_from_msg(body, name))
    ts.register(types)
    return lambda data: ts.deserialize_cdr(data, schema_name)


class SocketWsClient:
    """A foxglove.websocket.v1 subscriber for timing (bench/live.py): one blocking socket in
    the caller's thread, framed by websockets' sans-I/O ClientProtocol (no event loop, no
    hand-over between threads), so a message's arrival (host monotonic s) is stamped right
    after the recv() that completed it: when it left the server's WebSocket, plus loopback.
    WsClient's asyncio loop adds its own scheduling to every arrival (side by side on the
    same records at the averaging rate: ~0.2 ms p50, ~0.4 ms p99)."""

    def __init__(self, url: str, timeout_s: float = 10.0) -> None:
        import socket

        from websockets.client import ClientProtocol
        from websockets.http11 import Response
        from websockets.uri import parse_uri

        uri = parse_uri(url)
        self.proto = ClientProtocol(uri, subprotocols=SUBPROTOCOLS, max_size=None)
        self.sock = socket.create_connection((uri.host, uri.port), timeout=timeout_s)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.proto.send_request(self.proto.connect())
        self._flush()
        self.subs: dict[int, str] = {}
        end = time.monotonic() + timeout_s
        while not self.subs:  # the handshake's response, then the server's advertise
            if time.monotonic() > end:
                raise TimeoutError(f"no advertise from {url} within {timeout_s} s")
            for ev in self._events()[0]:
                if isinstance(ev, Response) and ev.status_code != 101:
                    raise ConnectionError(f"{url} refused the WebSocket ({ev.status_code})")
                if getattr(ev, "opcode", None) is not None and ev.opcode.name == "TEXT":
                    obj = json.loads(ev.data)
                    if obj.get("op") == "advertise":
                        subs = [{"id": c["id"], "channelId": c["id"]} for c in obj["channels"]]
                        self.subs.update({c["id"]: c["topic"] for c in obj["channels"]})
                        self.proto.send_text(json.dumps({"op": "subscribe",
                                                         "subscriptions": subs}).encode())
                        self._flush()

    def _flush(self) -> None:
        for data in self.proto.data_to_send():
            if data:
                self.sock.sendall(data)

    def _events(self) -> tuple[list, float]:
        """(the events one recv() completed, host monotonic s when it returned)."""
        data = self.sock.recv(1 << 20)
        now = time.monotonic()
        if not data:
            raise ConnectionError("the server closed the connection")
        self.proto.receive_data(data)
        self._flush()  # pongs
        return self.proto.events_received(), now

    def read(self, topic: str, timeout_s: float) -> list[float] | None:
        """Arrival times (host monotonic s) of the messages on topic that one recv()
        completed (maybe none); None if no byte came within timeout_s."""
        self.sock.settimeout(timeout_s)
        try:
            events, now = self._events()
        except TimeoutError:
            return None
        return [now for ev in events if ev.opcode.name == "BINARY" and ev.data[:1] == b"\x01"
                and self.subs.get(struct.unpack_from("<I", ev.data, 1)[0]) == topic]

    def close(self) -> None:
        """Leave with the closing handshake (the server logs a reset otherwise)."""
        from websockets.exceptions import InvalidState

        try:
            self.proto.send_close()
            self._flush()
            self.sock.settimeout(1.0)
            while self.sock.recv(1 << 16):  # the server's close frame, then its FIN
                pass
        except (OSError, InvalidState):  # already closed by the server, or the socket gone
            pass
        self.sock.close()
