"""Reaching the process that holds a stage port: a stop request from any terminal, and the
note that the board was halted (M112), kept per port beside the port lock.

The port is opened exclusively, so a second `dmdsm` cannot write M410 to it. The owner
therefore listens on a Unix socket named after the port (`<runtime dir>/dmdsm-<uid>/
stage-<hash of the port's real path>.sock`, mode 0700 folder): `stop` asks it to quick-stop
and answers once the stage is proven standing. A socket left by a killed owner refuses the
connection, so a caller then opens the port itself.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import socket
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path

STOP_REPLY_S = 30.0  # the owner's proof of standing takes ~1 s per line Marlin had not run


def state_dir() -> Path:
    """The per-user folder (mode 0700) of the files kept per port."""
    base = os.environ.get("XDG_RUNTIME_DIR") or tempfile.gettempdir()
    d = Path(base) / f"dmdsm-{os.getuid()}"
    d.mkdir(mode=0o700, exist_ok=True)
    return d


def port_key(port: str) -> str:
    """A port's name for those files: a hash of its real path (a symlink and its pty agree)."""
    real = port if "://" in port else os.path.realpath(port)
    return hashlib.sha256(real.encode()).hexdigest()[:16]


def socket_path(port: str) -> Path:
    """Where the process holding `port` listens for stop requests."""
    return state_dir() / f"stage-{port_key(port)}.sock"


def halt_path(port: str) -> Path:
    """The note left when the board on `port` was sent M112."""
    return state_dir() / f"stage-{port_key(port)}.halted"


def note_halted(port: str, how: str) -> None:
    """Remember that the board on `port` is halted (until a client hears it answer)."""
    with contextlib.suppress(OSError):
        halt_path(port).write_text(json.dumps({"pid": os.getpid(), "how": how,
                                               "at": time.strftime("%H:%M:%S")}))


def halted_note(port: str) -> dict | None:
    """The halt note of `port`, if a client halted it and nobody has heard it answer since."""
    try:
        note = json.loads(halt_path(port).read_text())
        return note if isinstance(note, dict) else None
    except (OSError, ValueError):
        return None


def clear_halted(port: str) -> None:
    """The board answered: it was reset, the halt note is stale."""
    with contextlib.suppress(OSError):
        halt_path(port).unlink()


class StopServer:
    """The owner's side: a thread that takes `stop` requests for one port."""

    def __init__(self, port: str, on_stop: Callable[[], str]) -> None:
        self.path = socket_path(port)
        self.on_stop = on_stop
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        with contextlib.suppress(OSError):
            self.path.unlink()  # a socket of a killed owner (we hold the port lock now)
        self.sock.bind(str(self.path))
        self.sock.listen(4)
        self.sock.settimeout(0.2)
        self.closed = threading.Event()
        self.thread = threading.Thread(target=self._serve, name="stage-stop-server",
                                       daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        while not self.closed.is_set():
            try:
                conn, _ = self.sock.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            with conn:
                conn.settimeout(2.0)
                try:
                    request = conn.recv(64).decode(errors="replace").strip()
                except OSError:
                    continue
                if request != "stop":
                    with contextlib.suppress(OSError):
                        conn.sendall(b"error unknown request\n")
                    continue
                with contextlib.suppress(OSError):
                    conn.sendall(f"stopping pid {os.getpid()}\n".encode())
                try:
                    reply = "ok " + self.on_stop()
                except Exception as e:  # noqa: BLE001 - the requester gets the one line
                    reply = f"error {e}"
                with contextlib.suppress(OSError):
                    conn.sendall((reply.replace("\n", " ") + "\n").encode())

    def close(self) -> None:
        """Stop listening and remove the socket."""
        self.closed.set()
        with contextlib.suppress(OSError):
            self.sock.close()
        self.thread.join(timeout=1.0)
        with contextlib.suppress(OSError):
            self.path.unlink()


class NoOwner(Exception):
    """Nothing answers stop requests for this port (no dmdsm holds it)."""


def request_stop(port: str, timeout_s: float = STOP_REPLY_S) -> tuple[int, str]:
    """Ask the dmdsm process holding `port` to quick-stop; (its pid, the standing position
    line) once it proved the stage still. Raises NoOwner, or RuntimeError with its error."""
    path = socket_path(port)
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        s.settimeout(2.0)
        try:
            s.connect(str(path))
        except OSError:
            raise NoOwner(port) from None
        s.sendall(b"stop\n")
        s.settimeout(timeout_s)
        data = b""
        while data.count(b"\n") < 2:
            chunk = s.recv(512)
            if not chunk:
                break
            data += chunk
    except TimeoutError:
        raise RuntimeError(f"the process holding {port} did not confirm the stop within "
                           f"{timeout_s:.0f} s") from None
    finally:
        s.close()
    lines = data.decode(errors="replace").splitlines()
    if not lines or not lines[0].startswith("stopping pid "):
        raise NoOwner(port)
    pid = int(lines[0].split()[-1])
    if len(lines) < 2:
        raise RuntimeError(f"the process holding {port} (pid {pid}) ended before it "
                           f"confirmed the stop")
    if lines[1].startswith("error "):
        raise RuntimeError(lines[1][6:])
    return pid, lines[1][3:]
