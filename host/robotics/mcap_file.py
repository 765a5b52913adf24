"""An MCAP recording of ROS 2 messages (profile ros2, CDR in ros2msg schemas) that a full
disk or a Ctrl-C leaves readable: for the scan export and the live recorder alike.

Every record goes to the OS as soon as the mcap writer makes it (no Python buffer to lose);
unchunked (the default) each message is on disk when `write` returns. The offset after the
last whole call is kept: a write that fails (ENOSPC, EDQUOT, EIO ...) or is interrupted
midway has the file cut back to it and closed with a DataEnd and a Footer without summary
(the readers then read the data section through: mcap's make_reader, rosbags), room for
which a small reserve file beside the recording, dropped at that moment, keeps free. The
failed `write` raises RecordingStopped (one line: what happened, what the file holds);
later writes raise it again. A normal finish (or a with block left by any exception, Ctrl-C
included, between writes) writes the full summary: schemas, channels, statistics, indexes.
"""

from __future__ import annotations

import contextlib
import os
import struct
from collections import deque
from collections.abc import Mapping
from pathlib import Path

from ..files import check_output, one_line, write_failed
from .messages import MESSAGE_ENCODING, PROFILE, SCHEMA_ENCODING, SCHEMAS, encode

MARKS = 64  # earlier record ends kept, to fall back to if the file's end will not fit
RESERVE_BYTES = 64 << 10  # freed on a full disk for the closing records (50 bytes)
# DataEnd (crc 0), Footer without summary (0, 0, crc 0), magic: a valid MCAP end
_TAIL = (struct.pack("<BQI", 0x0F, 4, 0) + struct.pack("<BQQQI", 0x02, 20, 0, 0, 0)
         + b"\x89MCAP0\r\n")
_write = os.write  # the tests put a full disk here
_FOREVER = "{sec: 2147483647, nsec: 4294967295}"
# rosbag2's offered_qos_profiles (Humble's YAML) of a latched topic: reliable, transient
# local, so `ros2 bag play` hands it to a subscriber that comes later (/tf_static, a model)
LATCHED_QOS = ("- history: 1\n  depth: 1\n  reliability: 1\n  durability: 1\n"
               f"  deadline: {_FOREVER}\n  lifespan: {_FOREVER}\n  liveliness: 1\n"
               f"  liveliness_lease_duration: {_FOREVER}\n"
               "  avoid_ros_namespace_conventions: false\n")


class RecordingStopped(Exception):
    """The recording stopped before its end (a full disk, a failed device); str() is one
    line saying what happened and what the file holds; `error` the OSError, if one."""

    def __init__(self, message: str, error: OSError | None = None) -> None:
        super().__init__(message)
        self.error = error


class _Sink:
    """The file under the mcap writer: every write straight to the OS, the offset counted."""

    def __init__(self, fd: int) -> None:
        self.fd, self.pos = fd, 0

    def write(self, data: bytes) -> int:
        view = memoryview(data).cast("B")
        while view:
            n = _write(self.fd, view)
            self.pos += n
            view = view[n:]
        return len(data)

    def tell(self) -> int:
        return self.pos

    def flush(self) -> None:
        pass


class McapRecorder:
    """`with McapRecorder(path) as rec: rec.write(topic, datatype, msg, t_ns)`.

    path: the file, written in place (a new file, or an existing regular one with force;
    check_output refuses folders, devices, FIFOs). chunk_size: None writes every message as
    its own record (nothing is held back: the live recorder); bytes per zstd chunk otherwise
    (smaller, indexed files: the export, whose output is a temporary file anyway, so a failure
    there loses the chunk in hand). Times are nanoseconds (ROS time: since the Unix epoch or
    whatever epoch the stamps use)."""

    def __init__(self, path: Path | str, *, force: bool = True, flag: str = "--mcap",
                 chunk_size: int | None = None, reserve_bytes: int = RESERVE_BYTES,
                 metadata: Mapping[str, str] | None = None) -> None:
        from mcap.writer import CompressionType, Writer

        self.path = Path(path)
        check_output(self.path, force, flag)
        self.reserve = self.path.with_name(f".{self.path.name}-reserve")
        try:
            self.fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o666)
        except OSError as e:
            raise write_failed(self.path, e, flag) from None
        self.sink = _Sink(self.fd)
        self.good = 0           # file offset after the last call that completed
        self.marks: deque[tuple[int, int]] = deque(maxlen=MARKS)  # earlier (good, on_disk)
        self.busy = False       # a writer call is under way (an exception there: cut back)
        self.stopped: str | None = None
        self.error: OSError | None = None   # the failed write's
        self.finished = False
        self.messages = 0       # messages written (complete calls)
        self.on_disk = 0        # of which in the file (chunked: not those of the open chunk)
        self.schemas: dict[str, int] = {}
        self.channels: dict[str, tuple[int, str]] = {}
        try:
            try:
                self._reserve(reserve_bytes)
            except OSError as e:  # no room even for the reserve: refused before it starts
                raise write_failed(self.path, e, flag) from None
            self.writer = Writer(self.sink, chunk_size=chunk_size or 1 << 20,
                                 compression=CompressionType.ZSTD if chunk_size
                                 else CompressionType.NONE, use_chunking=bool(chunk_size))
            self._call(self.writer.start, PROFILE, "dmdsm")
            if metadata:
                self._call(self.writer.add_metadata, "dmdsm", dict(metadata))
        except BaseException:
            with contextlib.suppress(OSError):
                if os.fstat(self.fd).st_size == 0:  # nothing worth keeping: no file
                    self.path.unlink()
            self._close_fd()
            raise

    def _reserve(self, size: int) -> None:
        if size <= 0:
            return
        fd = os.open(self.reserve, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        try:
            _Sink(fd).write(bytes(size))
            os.fsync(fd)
        finally:
            os.close(fd)

    def __enter__(self) -> McapRecorder:
        return self

    def __exit__(self, kind: type[BaseException] | None, error: BaseException | None,
                 tb: object) -> None:
        """finish(); RecordingStopped if the end did not fit, unless an exception is already
        on its way (Ctrl-C, a failed write: that one is the news; the file is closed anyway)."""
        stopped = self.stopped
        self.finish()
        if kind is None and self.stopped and not stopped:  # the end did not fit
            raise RecordingStopped(self.stopped, self.error)

    def channel(self, topic: str, datatype: str, latched: bool = False) -> int:
        """The channel id of topic (registered, with datatype's schema, on first use; latched:
        with rosbag2's transient-local QoS); ValueError if the topic has another datatype."""
        if topic in self.channels:
            cid, known = self.channels[topic]
            if known != datatype:
                raise ValueError(f"topic {topic} carries {known}, not {datatype}")
            return cid
        if datatype not in SCHEMAS:
            raise ValueError(f"no schema for {datatype!r} (known: {', '.join(SCHEMAS)})")
        if datatype not in self.schemas:
            self.schemas[datatype] = self._call(self.writer.register_schema, datatype,
                                                SCHEMA_ENCODING, SCHEMAS[datatype].encode())
        cid = self._call(self.writer.register_channel, topic, MESSAGE_ENCODING,
                         self.schemas[datatype],
                         {"offered_qos_profiles": LATCHED_QOS} if latched else {})
        self.channels[topic] = (cid, datatype)
        return cid

    def write(self, topic: str, datatype: str, msg: Mapping | bytes, log_time_ns: int,
              publish_time_ns: int | None = None, sequence: int = 0) -> None:
        """Record one message (a dict of datatype's fields, or its CDR bytes) at log_time_ns
        (ns; publish_time_ns defaults to it). RecordingStopped once the recording stopped."""
        if self.stopped:
            raise RecordingStopped(self.stopped, self.error)
        cid = self.channel(topic, datatype)
        data = msg if isinstance(msg, (bytes, bytearray, memoryview)) else encode(datatype, msg)
        t, before = int(log_time_ns), self.sink.pos
        self._call(self.writer.add_message, cid, t, bytes(data),
                   t if publish_time_ns is None else int(publish_time_ns), sequence)
        self.messages += 1
        if self.sink.pos > before:  # a record or a chunk (holding every message so far)
            self.on_disk = self.messages

    def _call(self, fn: object, *args: object) -> object:
        """Run one writer call; a failed write stops the recording (RecordingStopped)."""
        if self.stopped:
            raise RecordingStopped(self.stopped, self.error)
        self.busy = True
        try:
            out = fn(*args)
        except OSError as e:
            self.error = e
            self._stop(f"{e.strerror or one_line(str(e), 80)}")
            raise RecordingStopped(self.stopped, e) from None
        self.busy = False
        if self.sink.pos != self.good and self.good > 0:  # 0: not even the header yet
            self.marks.append((self.good, self.on_disk))
        self.good = self.sink.pos
        return out

    def _stop(self, why: str) -> None:
        """Cut the file back to its last whole record and close it with a plain end; if even
        that end does not fit (the freed room taken meanwhile), give up messages from the
        end, one call at a time, until it does: a file every reader opens."""
        with contextlib.suppress(OSError):
            self.reserve.unlink()
        ended = False
        for off, n in [(self.good, self.on_disk), *reversed(self.marks)] if self.good else []:
            with contextlib.suppress(OSError):
                os.ftruncate(self.fd, off)
                os.lseek(self.fd, off, os.SEEK_SET)
                self.sink.pos = off
                self.sink.write(_TAIL)
                ended, self.on_disk = True, n
                break
        if not ended:  # not even 50 bytes (or not even the header): what was whole stays
            with contextlib.suppress(OSError):
                os.ftruncate(self.fd, self.good)
        held = (f"the {self.on_disk} messages before it" if self.on_disk == self.messages
                else f"{self.on_disk} of the {self.messages} messages before it (the last "
                     f"{self.messages - self.on_disk} did not fit)")
        self.stopped = one_line(
            f"recording to {self.path} stopped: {why}; the file holds {held}, readable"
            + ("" if ended else " only by a reader that scans the data (it has no footer)"),
            300)
        self._close_fd()

    def finish(self) -> None:
        """Close the recording: the summary when every call completed, else the plain end
        after the last whole record. Idempotent; the reserve file is removed. Never raises:
        if the summary does not fit, `stopped` says so (the file then ends plainly after its
        last whole record); a `with` block raises RecordingStopped for it."""
        if self.finished:
            return
        self.finished = True
        if self.stopped:
            return
        if self.busy:  # interrupted inside a writer call (Ctrl-C): its record may be partial
            self._stop("interrupted while writing")
            return
        try:
            self._call(self.writer.finish)
        except RecordingStopped:
            return  # self.stopped says why; the file ends plainly after its last record
        self.on_disk = self.messages
        with contextlib.suppress(OSError):
            os.fsync(self.fd)
        self._close_fd()

    def _close_fd(self) -> None:
        with contextlib.suppress(OSError):
            self.reserve.unlink()
        if self.fd >= 0:
            with contextlib.suppress(OSError):
                os.close(self.fd)
            self.fd = -1
