"""The one way to run the emulator in-process: a Simulation served on two ptys, as a context.

Tests, benchmarks, the demo and `dmdsm sim` all start it here, so how the boards are booted,
served and shut down is written once:

    with Emulator(SimConfig(seed=1), speed=20.0) as emu:
        StageClient(emu.stage) ...; SensorClient(emu.sensor) ...; emu.sim.truth ...

`serve()` runs it in the foreground instead (`dmdsm sim`, until `stop()` from a signal).
"""

from __future__ import annotations

import shutil
import tempfile
import threading

from .pty_server import PtyServer
from .runner import SimConfig, Simulation


class Emulator:
    """Both boards of a Simulation behind pseudo-terminals, simulated time x `speed` the wall
    clock; `link_dir` gives the ports stable names (DIR/sensor, DIR/stage, DIR/scene)."""

    def __init__(self, cfg: SimConfig | None = None, speed: float = 1.0,
                 link_dir: str | None = None, boot_s: float = 0.0,
                 sim: Simulation | None = None) -> None:
        self.sim = sim if sim is not None else Simulation(cfg)
        if boot_s > 0:  # let a firmware boot first: bytes sent before its UART is up are lost
            self.sim.advance(boot_s)
        self._own_links: str | None = None
        if link_dir is None and any(self.sim.channels[(name, "up")].f.disconnect
                                    for name in ("sensor", "stage")):
            # a port that is pulled comes back as another /dev/pts/N: give it a stable name,
            # as udev's by-id link does for a real board, so the host can find it again
            link_dir = self._own_links = tempfile.mkdtemp(prefix="dmdsm-ports-")
        self.server = PtyServer(self.sim, speed=speed, link_dir=link_dir)
        self.thread: threading.Thread | None = None
        self._closed = False

    @property
    def sensor(self) -> str:
        """The sensor board's port name, as the host opens it."""
        return self.server.ports["sensor"].name_for_host

    @property
    def stage(self) -> str:
        """The stage board's port name, as the host opens it."""
        return self.server.ports["stage"].name_for_host

    def start(self) -> Emulator:
        """Serve in a background thread (daemon: a crashed test cannot hang the process)."""
        if self.thread is None:
            self.thread = threading.Thread(target=self.server.serve_forever, daemon=True,
                                           name="dmdsm-emulator")
            self.thread.start()
        return self

    def serve(self) -> None:
        """Serve in this thread until stop() (from a signal handler or another thread); the
        simulation is closed when it returns or raises."""
        try:
            self.server.serve_forever()
        finally:
            self._closed = True
            self.sim.close()
            self._remove_own_links()

    def stop(self) -> None:
        """Stop serving, wait for the thread and close the simulation (a stage firmware's
        simavr harness, if one runs). Safe to call twice."""
        self.server.stop()
        if self.thread is not None:
            self.thread.join(5)
            self.thread = None
        if not self._closed:
            self._closed = True
            self.sim.close()
        self._remove_own_links()

    def _remove_own_links(self) -> None:
        """Remove the link directory made for pulled ports (none given by the caller)."""
        if self._own_links is not None:
            shutil.rmtree(self._own_links, ignore_errors=True)
            self._own_links = None

    def __enter__(self) -> Emulator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
