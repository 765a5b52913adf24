"""Sensor client: handshake, commands with retries, shots streamed into numpy on a reader thread.

Every command carries a sequence number and waits for its one response; on a timeout the same
bytes go out again with the retransmit flag (the firmware answers a repeat from its cache and
does not run it twice). Waveforms land in preallocated arrays by shot id; gaps in the ids and
the device's counters account for every lost shot. Nothing that failed its CRC is delivered.
"""

from __future__ import annotations

import logging
import math
import os
import random
import select
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import serial

from dmdsm.protocol import FrameDecoder, Message, encode_frame, load_spec
from dmdsm.protocol.spec import SAMPLE_DTYPES

from .board_clock import BoardClock, Deadline
from .shots import Shots
from .transport import LinkError, open_port

log = logging.getLogger("dmdsm.sensor")

SPEC = load_spec()
ERRORS = {v: k for k, v in SPEC.enums["error"].items()}
BOOT_FAILURES = ("clock_failure", "power_failure", "adc_failure")  # arm NAKs: docs/firmware.md
CONFIG_FIELDS = [f.name for f in SPEC.by_name["set_config"].fields]
QUIET_S = 0.5  # no shot for this long (board time): ask whether the board has finished


def config_range(name: str) -> tuple[int, int]:
    """The values the spec allows for set_config field `name`."""
    return next(f for f in SPEC.by_name["set_config"].fields if f.name == name).allowed()


def check_shots_fit(n_shots: int, n_samples: int, itemsize: int) -> None:
    """Refuse, before arming, an acquisition whose shots (kept in memory until written)
    would take more than half of the memory free now, or more than arm can count."""
    hi = next(f for f in SPEC.by_name["arm"].fields if f.name == "n_shots").allowed()[1]
    if not 0 < n_shots <= hi:
        raise SensorError(f"{n_shots} shots: give 1..{hi} per acquisition")
    need = n_shots * n_samples * itemsize * 1.25  # samples, and the rows kept per shot
    try:
        free = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError):  # not reported here: no bound but the type's
        return
    if need > free / 2:
        raise SensorError(f"{n_shots} shots of {n_samples} samples need {need / 2**30:.1f} "
                          f"GiB of memory and {free / 2**30:.1f} GiB is free: record at most "
                          f"{int(free / 2 / (n_samples * itemsize * 1.25))} shots per file")


class AcquisitionInterrupted(KeyboardInterrupt):
    """Ctrl-C (or SIGTERM) during acquire(): the board was disarmed; `shots` holds what had
    arrived (received marks them), so the caller can keep it."""

    def __init__(self, shots: Shots) -> None:
        super().__init__("acquisition interrupted")
        self.shots = shots


CLOCK_SPACING_S = 0.025  # between clock_sync exchanges of one fit: 16 span 0.4 s
HELD_WRITE_S = 0.5e-3  # a clock_sync written this long after its send stamp is made again


class SensorError(LinkError):
    """The sensor board refused or failed; str() says what to do."""


class AcquisitionLost(SensorError):
    """The link to the board was lost during acquire(); `shots` holds what had arrived
    (received marks them), so the caller can keep it. str() says what to do."""

    def __init__(self, message: str, shots: Shots) -> None:
        super().__init__(message)
        self.shots = shots


@dataclass
class ClockSync:
    """Device ticks = offset + rate * host monotonic seconds, from clock_sync exchanges."""

    offset_ticks: float
    ticks_per_s: float
    residual_s: float      # rms of the fit (s)
    rtt_s: float           # median round trip (s)
    rate_std: float = float("inf")  # std of ticks_per_s from the fit (ticks/s)
    n: int = 0             # exchanges the line went through
    x_mean_s: float = 0.0  # their mean host time (s)
    sxx_s2: float = 0.0    # their host times' sum of squared deviations from the mean (s^2)

    def to_host_s(self, ticks: np.ndarray | float) -> np.ndarray | float:
        """Host monotonic time (s) of device ticks."""
        return (np.asarray(ticks, dtype=float) - self.offset_ticks) / self.ticks_per_s

    def line_std_s(self, ticks: float) -> float:
        """1-sigma (s) of the fitted line itself at device ticks: least squares' error of
        the mean prediction (offset, and the drift times the distance from the exchanges'
        mean), the scatter estimated from the residuals with n - 2 degrees of freedom and
        widened by Student's t (variance (n-2)/(n-4)), so that error/sigma has an RMS of 1
        however few the exchanges. Not one exchange's scatter, nor the round trip's unknown
        split (the caller's terms). Infinite through 4 exchanges or fewer."""
        if self.n <= 4:
            return float("inf")
        s2 = self.residual_s ** 2 * self.n / (self.n - 4)  # n/(n-2) x (n-2)/(n-4)
        dx = float(self.to_host_s(ticks)) - self.x_mean_s
        return math.sqrt(s2 * (1.0 / self.n + (dx * dx / self.sxx_s2 if self.sxx_s2 > 0
                                               else 0.0)))


class SensorClient:
    """The STM32 sensor board on a port name or URL (device, pty, socket:// for QEMU).

    Satisfies links.interfaces.Sensor (shots and stream)."""

    port_name: str                   # the port name or URL given
    identity: Message | None         # the handshake reply (None only while it is made)
    motion_syncs: deque[Message]     # the stage's X and A STEP burst reports, the last 256

    def __init__(self, port: str, baudrate: int = 2_000_000, timeout_s: float = 0.5,
                 retries: int = 4, expected_hash: int = SPEC.hash) -> None:
        self.port_name = port
        self.baudrate = baudrate
        self.timeout_s = timeout_s
        self.retries = retries
        self.expected_hash = expected_hash
        # a random first sequence number: a board still holding an earlier client's last
        # answer (or a firmware that answers repeats from its cache) never hands it to us
        self.seq = random.randrange(0x10000)
        self.cond = threading.Condition()
        self.responses: dict[int, Message] = {}
        self.arrived_ns: dict[int, int] = {}  # seq -> host monotonic ns its bytes were read
        self._chunk_ns = 0  # when the reader took in the bytes it is decoding (ns)
        self.logs: list[Message] = []
        self.decoder = FrameDecoder()
        self.link_error: str | None = None
        self.shots: Shots | None = None
        self.identity: Message | None = None
        # what this client set and last read, so acquire() needs 2 round trips, not 4;
        # forgotten on reconnect and when a waveform does not match the cached config
        self._config: dict | None = None
        self._counters: dict | None = None
        # continuous acquisition (stream_start/stream_stop): waveform messages in arrival
        # order; motion_sync reports (the stage's X and A STEP bursts) as they come, the last 256
        self.stream: list[Message] | None = None
        self._stream_before: dict = {}  # device counters when the stream was armed
        self.motion_syncs: deque[Message] = deque(maxlen=256)
        self._open()
        self.identity = self.handshake()
        self.took_over = self._take_over()

    def _take_over(self) -> bool:
        """Disarm a board that an earlier client left armed (killed with kill -9, or its
        cable pulled mid-acquisition); the port is opened exclusively, so no live client
        owns it. True if it had to."""
        if self.status()["state"] == SPEC.enums["state"]["idle"]:
            return False
        log.warning("the sensor board on %s was still acquiring for an earlier client; "
                    "disarmed it", self.port_name)
        self.disarm()
        return True

    # ------------------------------------------------------------------ link
    def _open(self) -> None:
        self.ser = open_port(self.port_name, self.baudrate, timeout=0.02)
        self.board_clock = BoardClock(self.port_name)  # an emulated board's own time, if published
        self.link_error = None
        self._stop = False
        self.reader = threading.Thread(target=self._read_loop, daemon=True)
        self.reader.start()
        self._write(b"\x00")  # end any partial frame in the firmware's receiver

    def __enter__(self) -> SensorClient:
        return self

    def __exit__(self, exc_type: type | None, exc: BaseException | None, tb: object) -> None:
        """Left by an error or Ctrl-C: disarm the board (unless the link itself failed), then
        close the port, as StageClient quick-stops the stage."""
        if exc_type is not None and not issubclass(exc_type, LinkError):
            try:
                self.disarm()
            except LinkError:
                pass
        self.close()

    def close(self) -> None:
        """Stop the reader and close the port."""
        self._stop = True
        self.reader.join(1.0)
        try:
            self.ser.close()
        except OSError:
            pass

    def reconnect(self, wait_s: float = 10.0) -> None:
        """Reopen the port (after a USB re-enumeration) and repeat the handshake; a port
        that drops again during the handshake is reopened too, until wait_s (s)."""
        self.close()
        self._config = self._counters = None
        end = time.monotonic() + wait_s
        while True:
            try:
                self._open()
            except LinkError:
                if time.monotonic() > end:
                    raise SensorError(f"the sensor board did not come back on "
                                      f"{self.port_name} within {wait_s:.0f} s") from None
                time.sleep(0.2)
                continue
            try:
                self.identity = self.handshake()
                return
            except SensorError:
                if not self.link_error or time.monotonic() > end:
                    raise  # an answer that is wrong, not a link that went away
                self.close()

    def _write(self, data: bytes) -> None:
        try:
            self.ser.write(data)
        except (OSError, serial.SerialException) as e:
            self.link_error = str(e)

    def _chunk_reader(self) -> Callable[[], bytes]:
        """What has arrived, or b"" after waiting up to the port's timeout for a byte
        (read(65536) would wait that timeout for bytes that are not coming, on every reply).
        A POSIX serial port (a board's USB CDC, the emulator's pty) is read on its file
        descriptor: pySerial's read() and in_waiting cost ~0.7 ms of interpreter time a
        waveform at 95/s, the reader waking for every few hundred bytes. Other transports
        (loop://, socket://, a wrapper) through pySerial."""
        ser = self.ser
        if type(ser) is not serial.Serial or getattr(ser, "fd", None) is None:
            return lambda: ser.read(ser.in_waiting or 1)
        fd, wait_s = ser.fd, ser.timeout

        def read() -> bytes:
            if not select.select([fd], [], [], wait_s)[0]:
                return b""
            try:
                data = os.read(fd, 65536)
            except BlockingIOError:  # the descriptor is non-blocking; nothing after all
                return b""
            if not data:  # readable with nothing to read: the device went away
                raise serial.SerialException("the device reports data but returns none "
                                             "(disconnected?)")
            return data
        return read

    def _read_loop(self) -> None:
        read = self._chunk_reader()
        while not self._stop:
            try:
                data = read()
            except (OSError, serial.SerialException, TypeError, ValueError) as e:
                with self.cond:
                    self.link_error = str(e) or "port closed"
                    self.cond.notify_all()
                return
            if not data:
                continue
            self._chunk_ns = time.monotonic_ns()
            s = self.shots
            if s is not None and s.armed_s is not None and s.first_byte_s is None:
                s.first_byte_s = time.monotonic()
            for m in self.decoder.feed(data):
                self._route(m)

    def _route(self, m: Message) -> None:
        if m.name == "waveform" and self.stream is not None:
            with self.cond:
                self.stream.append(m)
                self.cond.notify_all()
            return
        if m.name == "motion_sync":
            with self.cond:
                self.motion_syncs.append(m)
                self.cond.notify_all()
            return
        if m.name == "waveform":
            s = self.shots
            if s is not None and m.samples.size != s.samples.shape[1]:
                self._config = None  # the board's config changed under us (a reset?)
            if s is not None and m.shot_id < len(s.received) and not s.received[m.shot_id]:
                i = m.shot_id
                n = min(m.samples.size, s.samples.shape[1])
                s.samples[i, :n] = m.samples[:n]
                s.timestamp[i] = m.timestamp
                s.trigger_phase[i] = m.trigger_phase
                s.n_average[i] = m.n_average
                s.received[i] = True
            with self.cond:
                self.cond.notify_all()
            return
        with self.cond:
            if m.is_response:
                self.responses[m.seq] = m
                self.arrived_ns[m.seq] = self._chunk_ns
            elif m.name == "log":
                self.logs.append(m)
            self.cond.notify_all()

    # ------------------------------------------------------------------ commands
    def request(self, name: str, sent_ns: list[int] | None = None,
                written_ns: list[int] | None = None, received_ns: list[int] | None = None,
                **fields: object) -> Message:
        """Send a command and return its response; retried with the same seq on timeout.
        sent_ns / written_ns: the host monotonic ns just before / after each write of it are
        appended there; received_ns: the ns at which the reader took in the reply's bytes
        (before this thread woke to it)."""
        if self.link_error:
            raise SensorError(f"lost the sensor board on {self.port_name} ({self.link_error}): "
                              f"check its USB cable, then run the command again")
        self.seq = (self.seq + 1) & 0xFFFF
        seq = self.seq
        frame = encode_frame(Message(name, seq=seq, **fields))
        retry = encode_frame(Message(name, seq=seq, flags=SPEC.flags["retransmit"], **fields))
        for attempt in range(self.retries + 1):
            if sent_ns is not None:
                sent_ns.append(time.monotonic_ns())
            self._write(frame if attempt == 0 else retry)
            if written_ns is not None:
                written_ns.append(time.monotonic_ns())
            deadline = Deadline(self.timeout_s, self.board_clock)
            with self.cond:
                while seq not in self.responses and not self.link_error:
                    left = deadline.left()
                    if left <= 0:
                        break
                    self.cond.wait(left)
                if seq in self.responses:
                    arrived = self.arrived_ns.pop(seq, 0)
                    if received_ns is not None:
                        received_ns.append(arrived or time.monotonic_ns())
                    return self.responses.pop(seq)
                if self.link_error:
                    raise SensorError(f"lost the sensor board on {self.port_name} "
                                      f"({self.link_error}): check its USB cable, then run "
                                      f"the command again")
        raise SensorError(f"no reply to {name} from {self.port_name} after "
                          f"{self.retries + 1} tries: is the sensor board powered and flashed?")

    def _expect_ack(self, r: Message, name: str) -> None:
        if r.name == "nak":
            err = ERRORS.get(r.error, str(r.error))
            what = ""
            if err == "out_of_range" and name == "set_config" and 0 < r.detail <= len(
                    CONFIG_FIELDS):
                field = CONFIG_FIELDS[r.detail - 1]
                lo, hi = config_range(field)
                what = f": {field} is outside {lo}..{hi}, or does not suit the other settings"
            elif err in BOOT_FAILURES:  # the board cannot acquire since its start-up
                what = (f": {SPEC.enum_docs['error'][err]}; its boot log and `dmdsm info` "
                        f"(board name) say which step failed")
            raise SensorError(f"the sensor board refused {name} ({err}{what})")

    def handshake(self) -> Message:
        """identify; refuses another protocol version or spec and recognises a Marlin."""
        try:
            r = self.request("identify")
        except SensorError:
            if self._looks_like_marlin():
                raise SensorError(f"{self.port_name} is the stage board (Marlin), not the "
                                  f"sensor: swap the two port names") from None
            raise SensorError(f"no dmdsm sensor firmware answers on {self.port_name}: flash "
                              f"it with `dmdsm flash stm32`, or check the port") from None
        if r.protocol_version != SPEC.version or r.spec_hash != self.expected_hash:
            raise SensorError(
                f"incompatible sensor firmware on {self.port_name}: protocol "
                f"{r.protocol_version}, spec {r.spec_hash:016x}; this host needs protocol "
                f"{SPEC.version}, spec {self.expected_hash:016x}: flash the firmware built "
                f"from this checkout with `dmdsm flash stm32`")
        return r

    def _looks_like_marlin(self) -> bool:
        self._write(b"\nM115\n")
        time.sleep(0.5)
        text = bytes(self.decoder._buf).decode(errors="replace")
        return any(w in text for w in ("FIRMWARE_NAME", "echo:", "ok", "start"))

    def configure(self, **cfg: int) -> dict:
        """set_config with the current values for anything not given; returns the config."""
        current = self.request("get_config").fields
        new = {**current, **cfg}
        unknown = set(cfg) - set(CONFIG_FIELDS)
        if unknown:
            raise SensorError(f"unknown setting {sorted(unknown)[0]}; known: "
                              f"{', '.join(CONFIG_FIELDS)}")
        for k, v in cfg.items():  # checked here: a value the wire cannot carry never goes out
            lo, hi = config_range(k)
            if not lo <= v <= hi:
                raise SensorError(f"{k} {v} is outside {lo}..{hi}")
        self._expect_ack(self.request("set_config", **new), "set_config")
        self._config = dict(new)
        return new

    def status(self) -> dict:
        """get_status as a dict."""
        return dict(self.request("get_status").fields)

    def disarm(self) -> None:
        """Stop acquiring."""
        self._expect_ack(self.request("disarm"), "disarm")

    def acquire(self, n_shots: int, timeout_s: float | None = None,
                progress: object | None = None) -> Shots:
        """Arm for n_shots waveforms and collect them; lost ones are reported, not waited for."""
        cfg = self._config or dict(self.request("get_config").fields)
        self._config = cfg
        dtype = np.dtype(SAMPLE_DTYPES[cfg["sample_format"]])
        check_shots_fit(n_shots, cfg["n_samples"], dtype.itemsize)
        shots = Shots(np.zeros((n_shots, cfg["n_samples"]), dtype), np.zeros(n_shots, bool),
                      np.zeros(n_shots, np.uint64), np.zeros(n_shots, np.uint16),
                      np.zeros(n_shots, np.uint16), dict(cfg))
        before = self._counters or self.status()
        rejected0 = self.decoder.stats.errors
        self.shots = shots
        try:
            self._expect_ack(self.request("arm", n_shots=n_shots), "arm")
            shots.armed_s = time.monotonic()
            self._collect(shots, n_shots, cfg, timeout_s, progress)
            shots.done_s = time.monotonic()
        except KeyboardInterrupt as e:
            self.shots = None
            try:  # never leave the board armed: the next acquire would be refused (busy)
                self.disarm()
            except LinkError:
                pass
            raise AcquisitionInterrupted(shots) from e  # the cause: Ctrl-C or SIGTERM
        finally:
            self.shots = None
        after = self.status()
        self._counters = after
        shots.triggers_skipped = after["triggers_skipped"] - before["triggers_skipped"]
        shots.adc_overruns = after["adc_overruns"] - before["adc_overruns"]
        shots.integrity_faults = after["integrity_faults"] - before["integrity_faults"]
        shots.link_rejected = self.decoder.stats.errors - rejected0
        return shots

    def stream_start(self) -> None:
        """Arm continuously: every averaged waveform is kept, in order, until stream_stop."""
        self._stream_before = self._counters or self.status()
        self.stream = []
        try:
            self._expect_ack(self.request("arm", n_shots=0), "arm")
        except BaseException:
            self.stream = None
            raise

    def stream_take(self, wait_s: float = 0.0) -> list[Message]:
        """The streamed waveforms that arrived since the last take, in order, waiting up to
        wait_s (s) for one; taken out of self.stream, so a long stream holds only what has
        not been taken (stream_stop returns the rest)."""
        with self.cond:
            if not self.stream and wait_s > 0 and not self.link_error:
                self.cond.wait(wait_s)
            got = self.stream or []
            if self.stream is not None:
                self.stream = []
        return got

    def stream_stop(self) -> tuple[list[Message], dict]:
        """Disarm, wait for the link to go quiet, and return the streamed waveforms and
        the device counters' change over the stream (skipped triggers, overruns, integrity
        faults; only the last two are losses: shots.LOSS_COUNTERS)."""
        before = self._stream_before
        try:
            self.disarm()
            idle = SPEC.enums["state"]["idle"]
            deadline = Deadline(2.0, self.board_clock)
            after = self.status()  # idle: every waveform's bytes went out before this reply
            while after["state"] != idle and not deadline.passed():
                time.sleep(0.005)
                after = self.status()
        finally:
            with self.cond:
                got, self.stream = self.stream or [], None
        self._counters = after
        change = {k: after[k] - before[k]
                  for k in ("triggers_skipped", "adc_overruns", "integrity_faults")}
        return got, change

    def _collect(self, shots: Shots, n: int, cfg: dict, timeout_s: float | None,
                 progress: object | None) -> None:
        """Wait for the shots; stop early once the device is idle and the link is quiet."""
        quiet = Deadline(QUIET_S, self.board_clock)
        last_count = 0
        deadline = Deadline(timeout_s or 30.0 + n * 0.05, self.board_clock)
        while True:
            count = int(shots.received.sum())
            if progress is not None and count != last_count:
                progress(count)
            if count != last_count:
                quiet = Deadline(QUIET_S, self.board_clock)
                last_count = count
            if count == n:
                return
            if self.link_error:
                raise AcquisitionLost(f"lost the sensor board on {self.port_name} "
                                      f"mid-acquisition ({self.link_error}); {count} of {n} "
                                      f"shots arrived", shots)
            if deadline.passed():
                self.disarm()
                return
            if quiet.passed():
                if self.status()["state"] == SPEC.enums["state"]["idle"]:
                    return  # the device finished; the rest were lost
                quiet = Deadline(QUIET_S, self.board_clock)
            with self.cond:
                self.cond.wait(0.05)

    def clock_exchanges(self, n: int = 16, spacing_s: float = 0.0
                        ) -> list[tuple[float, float, float]]:
        """n clock_sync exchanges, started at least spacing_s apart: (host monotonic mid-time
        s, device ticks, round trip s), the round trip from the request's write to the reader
        taking in the reply's bytes (not from before its encoding, nor to this thread's wake-up
        after the reader: that leg is the host's alone and only on the way back). A rate
        needs a baseline: 16 back-to-back exchanges span 10 ms, where 1 ms of USB jitter is a
        10 % error. One that had to be sent again is left out (the board may have answered
        the first), and one whose write came more than HELD_WRITE_S after its send stamp
        (this thread held off the interpreter between the two: up to 8 ms under a live
        stream's load) is made again, as many again as n at most; the last attempt is kept
        as it is."""
        out: list[tuple[float, float, float]] = []
        for attempt in range(2 * n):
            if len(out) == n:
                break
            if out and spacing_s > 0:
                time.sleep(max(0.0, out[-1][0] + spacing_s - time.monotonic()))
            sent: list[int] = []
            written: list[int] = []
            received: list[int] = []
            r = self.request("clock_sync", sent_ns=sent, written_ns=written,
                             received_ns=received, host_time_ns=time.monotonic_ns())
            t1 = received[0]  # the reply's bytes read, not this thread's wake-up after
            held = (written[-1] - sent[-1]) / 1e9 > HELD_WRITE_S
            if len(sent) == 1 and not (held and attempt < 2 * n - 1):
                out.append(((sent[0] + t1) / 2e9, float(r.device_ticks), (t1 - sent[0]) / 1e9))
        return out

    def sync_clock(self, exchanges: int = 16, spacing_s: float = CLOCK_SPACING_S) -> ClockSync:
        """Fit device ticks against host time over clock_sync exchanges (Klipper's way),
        spread over exchanges x spacing_s seconds (0.4 s by default)."""
        return fit_clock(self.clock_exchanges(exchanges, spacing_s))


def fit_line(host_s: np.ndarray, ticks: np.ndarray, rtt_s: float) -> ClockSync:
    """Device ticks = offset + rate * host s by least squares through these (host s, ticks)
    pairs (at least 2), with what the line's own error needs: residual, drift's std, count,
    mean host time and spread. rtt_s: the round trip reported with it (s)."""
    x, y = np.asarray(host_s, dtype=float), np.asarray(ticks, dtype=float)
    xk = x - x[0]  # host seconds since the first: the fit stays well conditioned
    xm, ym = float(xk.mean()), float(y.mean())
    dx = xk - xm
    sxx = float(dx @ dx)
    if sxx > 0:  # the normal equations on centred data (polyfit's SVD: 4x the time)
        rate = float(dx @ (y - ym)) / sxx
        offset = ym - rate * xm
    else:
        rate, offset = np.polyfit(xk, y, 1)
    resid = y - (offset + rate * xk)
    res_s = float(np.sqrt(np.mean(resid ** 2)) / rate)
    rate_std = res_s * rate / math.sqrt(sxx) if sxx > 0 and len(xk) > 2 else float("inf")
    return ClockSync(offset - rate * x[0], rate, res_s, float(rtt_s), rate_std=rate_std,
                     n=len(x), x_mean_s=float(x.mean()), sxx_s2=sxx)


def fit_clock(samples: list[tuple[float, float, float]]) -> ClockSync:
    """Device ticks = offset + rate * host s, least squares over the exchanges that did not
    wait (round trip within 1.5x the median); residual and the drift's std from the fit."""
    x, y, rtts = (np.asarray(v, dtype=float) for v in zip(*samples))
    keep = rtts <= np.median(rtts) * 1.5
    if keep.sum() < 2:
        keep[:] = True
    return fit_line(x[keep], y[keep], float(np.median(rtts)))
