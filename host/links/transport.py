"""Opening serial ports by name or URL, with one-line errors that say what to fix."""

from __future__ import annotations

import errno
import os
import stat

import serial


class LinkError(Exception):
    """A link problem the user can act on; str() is one line."""


def open_port(name: str, baudrate: int, timeout: float = 0.05) -> serial.SerialBase:
    """Open a device path (/dev/ttyACM0, /dev/pts/3), a by-id link or a pySerial URL
    (socket://host:port, loop://) exclusively."""
    try:
        mode = None if "://" in name else os.stat(name).st_mode
    except OSError:  # missing, or gone between two looks (a board re-enumerating)
        raise LinkError(f"{name} does not exist: check the cable, or list ports with "
                        f"`dmdsm ports`") from None
    if mode is not None and not stat.S_ISCHR(mode):
        kind = "a folder" if os.path.isdir(name) else "a plain file"
        raise LinkError(f"{name} is {kind}, not a serial port: give the board's port "
                        f"(e.g. /dev/ttyACM0; `dmdsm ports` lists them)")
    if "://" in name:
        _check_url(name)
    try:
        if "://" in name:
            return serial.serial_for_url(name, baudrate=baudrate, timeout=timeout)
        return serial.Serial(name, baudrate=baudrate, timeout=timeout, exclusive=True)
    except serial.SerialException as e:
        text = str(e).lower()
        err = getattr(e, "errno", None)
        if err == errno.EACCES or "permission denied" in text:
            raise LinkError(f"no permission to open {name}: add yourself to the dialout "
                            f"group (sudo usermod -aG dialout $USER) and log in again") from None
        if "exclusively lock" in text or err == errno.EBUSY or "busy" in text:
            raise LinkError(f"{name} is in use by another program (OctoPrint, a terminal, "
                            f"another dmdsm): close it and retry") from None
        if err == errno.ENOTTY or "inappropriate ioctl" in text:
            raise LinkError(f"{name} is a device but not a serial port (it takes no line "
                            f"settings): give the board's port (e.g. /dev/ttyACM0; "
                            f"`dmdsm ports` lists them)") from None
        if "connection refused" in text:
            raise LinkError(f"nothing listens at {name}: is the emulator or QEMU "
                            f"running?") from None
        raise LinkError(f"cannot open {name}: {e}") from None


URL_SCHEMES = ("socket", "rfc2217", "loop", "spy", "hwgrep", "alt")  # pySerial's, as used here


def _check_url(name: str) -> None:
    """A port URL pySerial can open: a known scheme, and HOST:PORT for the network ones
    (pySerial says "'<=' not supported" for a missing port, and raises on a scheme)."""
    scheme, _, rest = name.partition("://")
    if scheme not in URL_SCHEMES:
        raise LinkError(f"{name}: unknown port URL scheme {scheme!r}: give a device path "
                        f"(/dev/ttyACM0) or socket://HOST:PORT, rfc2217://HOST:PORT, loop://")
    if scheme in ("socket", "rfc2217"):
        hostport = rest.split("?", 1)[0].split("/", 1)[0]
        host, _, port = hostport.rpartition(":")
        if not host or not port.isdigit() or not 0 < int(port) < 65536:
            raise LinkError(f"{name}: give the host and the TCP port, e.g. "
                            f"{scheme}://localhost:5000")
