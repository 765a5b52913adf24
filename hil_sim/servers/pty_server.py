"""Both emulated boards behind pseudo-terminals, simulated time tied to the wall clock."""

from __future__ import annotations

import os
import select
import sys
import threading
import time
import tty
from pathlib import Path

from dmdsm.host.links.board_clock import ClockPublisher

from ..physics.objects import SCENES
from .runner import Simulation

MAX_PENDING = 1 << 20  # bytes kept for a host that does not read; older output is dropped
# a host behind (the sensor's pty full: it has not read ~64 kB the board sent) holds the
# simulation up to this long (s, wall clock) before the board's link backs up and it skips
# laser shots: the emulator's time is its own (it runs behind the wall clock whenever its
# CPU is short), so a host starved of CPU beside it (a busy machine; the test's host shares
# its process) is not taken for a host too slow for the board. A host that stopped reading
# for good gets the board's back-pressure after this wait, as on hardware.
HOST_HOLD_S = 5.0


class Port:
    """One pseudo-terminal; the emulator keeps the slave open so a host may come and go."""

    def __init__(self, name: str, link_dir: Path | None) -> None:
        self.name = name
        self.link = link_dir / name if link_dir else None
        self.pending = bytearray()
        self.down_until = 0.0
        self.clock: ClockPublisher | None = None
        self.open()

    def open(self) -> None:
        """Create the pty (and point the stable symlink at it)."""
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        os.set_blocking(self.master, False)
        self.path = os.ttyname(self.slave)
        # the board's time for the host's timeouts: this board runs as fast as the CPU lets it
        self.clock = ClockPublisher(self.path)
        if self.link is not None:
            tmp = self.link.with_suffix(".tmp")
            tmp.unlink(missing_ok=True)
            tmp.symlink_to(self.path)
            tmp.replace(self.link)

    def close(self) -> None:
        """Close both ends: an open host connection sees the port vanish, and so does its
        stable name (as a udev /dev/serial/by-id link does on unplugging): the kernel gives
        the freed /dev/pts/N to the next pty opened anywhere, so a host reopening the old
        path meanwhile would open (and take bytes from) another program's port."""
        if self.link is not None:
            self.link.unlink(missing_ok=True)
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass
        self.master = self.slave = -1
        if self.clock is not None:
            self.clock.close()
            self.clock = None

    @property
    def name_for_host(self) -> str:
        """What the host opens: the stable symlink if any, else /dev/pts/N."""
        return str(self.link) if self.link else self.path


class PtyServer:
    """Serves a Simulation on two ptys until stop() (or Ctrl-C in `dmdsm sim`)."""

    def __init__(self, sim: Simulation, speed: float = 1.0, link_dir: str | None = None) -> None:
        self.sim = sim
        self.speed = speed
        d = Path(link_dir) if link_dir else None
        if d:
            d.mkdir(parents=True, exist_ok=True)
        self.ports = {name: Port(name, d) for name in ("sensor", "stage")}
        self._stop = threading.Event()
        self._behind_since: float | None = None  # wall clock (s) the host fell behind
        self.lock = threading.Lock()  # held while the simulation steps (truth() readers)
        # what a user does by hand on the real machine: `echo rig_vertical > DIR/scene`
        self.scene_file = d / "scene" if d else None
        self._scene_mtime: tuple[int, int] = (0, 0)
        self._scene_check = 0.0
        if self.scene_file is not None:  # the file names what is mounted now
            self.scene_file.write_text(sim.cfg.scene + "\n")
            st = self.scene_file.stat()
            self._scene_mtime = (st.st_mtime_ns, st.st_ino)

    def mount(self, objects: list) -> None:
        """Put other objects on the turntable (the user re-mounting the rig or an object)."""
        with self.lock:
            self.sim.scene.objects = list(objects)
            self.sim.sensor._hit_cache = None

    def _watch_scene(self, host_spoke: bool = False) -> None:
        """Mount the scene named in DIR/scene when the file changes (checked every 0.2 s, and
        whenever the host sends bytes: a command typed after `echo NAME > DIR/scene` sees the
        new scene from its first byte, however busy the machine)."""
        now = time.monotonic()
        if self.scene_file is None or (now - self._scene_check < 0.2 and not host_spoke):
            return
        self._scene_check = now
        try:
            st = self.scene_file.stat()
            mtime = (st.st_mtime_ns, st.st_ino)  # a file renamed over it is a change too
        except OSError:
            return
        if mtime == self._scene_mtime:
            return
        self._scene_mtime = mtime
        name = self.scene_file.read_text().strip()
        if name not in SCENES:
            print(f"dmdsm sim: unknown scene {name!r} in {self.scene_file}; known: "
                  f"{', '.join(SCENES)}", file=sys.stderr)
            return
        self.mount(SCENES[name]())
        print(f"dmdsm sim: mounted {name}", file=sys.stderr)

    def stop(self) -> None:
        """Ask serve_forever to return."""
        self._stop.set()

    def serve_forever(self) -> None:
        """Pump bytes between the ptys and the simulation in (scaled) real time."""
        try:
            self._serve()
        finally:
            for p in self.ports.values():
                if p.clock is not None:
                    p.clock.close()
                    p.clock = None

    def _serve(self) -> None:
        wall0, sim0 = time.monotonic(), self.sim.t
        while not self._stop.is_set():
            self._watch_scene()
            fds = [p.master for p in self.ports.values() if p.master >= 0]
            try:
                readable, _, _ = select.select(fds, [], [], 0.001)
            except (OSError, ValueError):  # a port closed (a pulled cable) since fds was read
                continue
            if readable:
                self._watch_scene(host_spoke=True)
            with self.lock:
                self._take_input(readable)
                target = sim0 + (time.monotonic() - wall0) * self.speed
                left = min(max(target - self.sim.t, 0.0), 0.05)
                held = False
                while True:  # advance in short chunks and pump the ptys between them
                    held = self._host_behind()
                    if held:  # the simulation waits for the host (time held)
                        break
                    # a full pty holds the device's transmitter, as USB flow control would
                    self.sim.sensor.link_blocked = len(self.ports["sensor"].pending) > 65536
                    dt = min(left, 0.005)
                    if dt > 0:
                        self.sim.advance(dt)
                    for p in self.ports.values():
                        self._pump_out(p, dt)
                        if p.clock is not None:
                            p.clock.publish(self.sim.t)
                    left -= dt
                    if left <= 1e-9:
                        break
                    # behind the wall clock the loop runs 50 ms at once: take what the host
                    # sent meanwhile at each chunk, so a reply-driven exchange (ok, next
                    # line) costs a chunk of simulated time, not the whole 50 ms
                    try:
                        more, _, _ = select.select(fds, [], [], 0)
                    except (OSError, ValueError):
                        more = []
                    self._take_input(more)
            if held:  # until the host has read some (the pty takes more) or 10 ms
                sensor = self.ports["sensor"]
                try:
                    select.select([], [sensor.master], [], 0.01)
                except (OSError, ValueError):
                    pass
                self._flush(sensor)

    def _host_behind(self) -> bool:
        """True while the sensor's host has left output in the full pty, for up to
        HOST_HOLD_S (s, wall clock) of each such spell."""
        p = self.ports["sensor"]
        if not p.pending or p.master < 0:
            self._behind_since = None
            return False
        now = time.monotonic()
        if self._behind_since is None:
            self._behind_since = now
        return now - self._behind_since < HOST_HOLD_S

    def _take_input(self, readable: list[int]) -> None:
        """Bytes the host wrote to the readable ports, into the simulation now."""
        for p in self.ports.values():
            if p.master >= 0 and p.master in readable:
                try:
                    data = os.read(p.master, 65536)
                except OSError:
                    data = b""
                if data:
                    self.sim.write(p.name, data)

    def _pump_out(self, p: Port, dt: float) -> None:
        p.pending += self.sim.read(p.name)
        if len(p.pending) > MAX_PENDING:
            del p.pending[:len(p.pending) - MAX_PENDING]
        chan = self.sim.channels[(p.name, "up")]
        if p.master >= 0 and chan.disconnects(dt):
            p.close()
            p.pending.clear()
            p.down_until = self.sim.t + chan.f.reconnect_s
        if p.master < 0:
            if self.sim.t >= p.down_until:
                p.open()
            return
        self._flush(p)

    @staticmethod
    def _flush(p: Port) -> None:
        """Write what the pty takes of the port's pending output."""
        if p.pending and p.master >= 0:
            try:
                n = os.write(p.master, bytes(p.pending))
                del p.pending[:n]
            except (BlockingIOError, OSError):
                pass
