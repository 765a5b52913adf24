"""What `Simulation` drives on a board: the sensor and stage board interfaces, declared once.

Each emulated board is one implementation: the sensor as the firmware core fed by the physics
(`sensor/core_board.py`) or the NUCLEO ELF on the rehosted H743 (`sensor/rehost/board.py`);
the stage as the Marlin emulator (`stage/marlin.py`) or a stage firmware under simavr in
lock-step (`stage/avr_lockstep.py`). tests/test_sim_board_interfaces.py checks each against
its Protocol by member and parameter names. Times are simulated seconds.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np


class Board(Protocol):
    """A board on one serial link, stepped in simulated time."""

    def receive(self, data: bytes, now: float) -> None:
        """Bytes from the host that reached the board at time `now` (s)."""

    def step(self, now: float) -> bytes:
        """Run the board up to time `now` (s); the bytes it sends the host meanwhile."""


class SensorBoardInterface(Board, Protocol):
    """The sensor board: a laser, an ADC, and a link the host may not drain."""

    link_blocked: bool  # the host side takes no more bytes (pty full): back-pressure

    def sampling(self) -> bool:
        """True while shots sample the moving stage, so the simulation takes fine steps."""


class StageBoardInterface(Board, Protocol):
    """The stage board: where the steppers are, and when they stepped."""

    def position_at(self, t: float) -> np.ndarray:
        """Logical X Y Z (mm) and A (deg) of the steppers at time t (s), from the homed 0."""

    def step_edges(self, axis: int, t_from: float, t_to: float) -> np.ndarray:
        """Times (s) of that axis's STEP pulses in (t_from, t_to]: the motion-sync wire."""
