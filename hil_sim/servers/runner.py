"""The simulation: both boards, the scene and the faulty links, stepped in simulated time.

`Simulation` is deterministic for a seed: tests drive it with `advance()` and the host-side
`write()`/`read()`. `PtyServer` puts it behind two pseudo-terminals, with simulated time tied
to the wall clock (times `speed`), so `dmdsm` or plain pySerial open the ports by name.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import TYPE_CHECKING

import numpy as np

from dmdsm.marlin_patch import load_machine

from ..boards.interface import SensorBoardInterface, StageBoardInterface
from ..boards.sensor.core_board import SensorBoard
from ..boards.stage.marlin import MarlinEmulator, StageFaults
from ..physics.objects import SCENES
from ..physics.scene import TABLE_I_N, TABLE_I_V, TABLE_I_XR, Scene, hash_noise
from ..physics.signals import SensorModel, arrival_times_us
from .faults import FaultyChannel, LinkFaults, parse_faults

if TYPE_CHECKING:
    from ..physics.mesh import ObjectTruth

STEP_S = 0.005  # simulated-time resolution of the main loop while shots are sampled


@dataclass
class SimConfig:
    """Everything that defines a simulation run (defaults: paper Table I, 20 degC air)."""

    scene: str = "aluminium_block"
    seed: int = 0
    rep_rate_hz: float = 1000.0            # laser repetition rate
    sensor_link_bytes_per_s: float = 200_000.0  # ST-LINK VCP at 2 Mbaud, 8N1
    stage_noise_mm: float = 0.002          # physical stage position scatter per position
    angle_noise_deg: float = 0.01          # turntable angle scatter per commanded angle
    temperature_c: float = 20.0
    v: tuple[float, ...] = tuple(TABLE_I_V)
    n: tuple[float, ...] = tuple(TABLE_I_N)
    X_R: tuple[float, ...] = tuple(TABLE_I_XR)
    faults: str = ""                       # e.g. "sensor.flip=1e-5,stage.lost_ok=0.01"
    objects: list = field(default_factory=list)  # extra SceneObjects (tests)
    frozen_noise: bool = False             # same pose + config -> same waveforms
    # "" runs the firmware core (PC build); "nucleo" or an ELF path runs that NUCLEO ELF
    # on the rehosted H743 (hil_sim/boards/sensor/rehost)
    sensor_firmware: str = ""
    # "" runs the Marlin emulator; an AVR ELF path runs that stage firmware (Marlin built from
    # firmware/marlin_patch) under simavr in lock-step (hil_sim/boards/stage/avr_lockstep.py)
    stage_firmware: str = ""
    # the motion-sync wires from the stage's X and A STEP lines to the sensor board
    # (docs/firmware.md): "xa" both, "x" the X line only, "" none
    sync_wire: str = "xa"


class Simulation:
    """Sensor board + stage board + scene, with faulty links, in simulated time (s)."""

    def __init__(self, cfg: SimConfig | None = None) -> None:
        self.cfg = cfg = cfg or SimConfig()
        if cfg.scene not in SCENES:
            raise ValueError(f"unknown scene {cfg.scene!r}; known: {', '.join(SCENES)}")
        for what, value, lo, hi in (("--rep-rate (laser shots per s)", cfg.rep_rate_hz, 1, 1e5),
                                    ("--sensor-link (bytes/s)", cfg.sensor_link_bytes_per_s,
                                     1e3, 1e9),
                                    ("--temperature (degC)", cfg.temperature_c, -40, 80)):
            if not lo <= value <= hi:  # also NaN; the emulator's physics holds in these ranges
                raise ValueError(f"{what} must be within {lo:g}..{hi:g} (got {value:g})")
        f = parse_faults(cfg.faults)
        stage_keys = {"lost_ok", "spurious_resend", "busy_extra_s"}
        stage_faults = StageFaults(**{k: v for k, v in f["stage"].items() if k in stage_keys})
        link = {name: LinkFaults(**{k: v for k, v in f[name].items() if k not in stage_keys})
                for name in ("sensor", "stage")}
        self.limits = load_machine()
        self.scene = Scene(v=np.array(cfg.v), n=np.array(cfg.n), X_R=np.array(cfg.X_R),
                           objects=SCENES[cfg.scene]() + list(cfg.objects))
        self.model = SensorModel(temperature_c=cfg.temperature_c)
        self.stage: StageBoardInterface  # MarlinEmulator or AvrStageBoard
        if cfg.stage_firmware:
            from ..boards.stage.avr_lockstep import AvrStageBoard
            self.stage = AvrStageBoard(cfg.stage_firmware, self.limits, seed=cfg.seed,
                                       faults=stage_faults)
        else:
            self.stage = MarlinEmulator(self.limits, seed=cfg.seed, faults=stage_faults)
        self.sensor: SensorBoardInterface  # SensorBoard or RehostedSensor
        if not set(cfg.sync_wire) <= set("xa"):
            raise ValueError(f"sync_wire must name the STEP lines wired: 'xa', 'x', 'a' or '' "
                             f"(got {cfg.sync_wire!r})")
        sync = [self.x_step_edges if "x" in cfg.sync_wire else None,  # the STEP wires plugged
                self.a_step_edges if "a" in cfg.sync_wire else None]
        if cfg.sensor_firmware:
            from ..boards.sensor.rehost.board import RehostedSensor  # unicorn only when asked
            self.sensor = RehostedSensor(self.scene, self.pose, self.model, seed=cfg.seed,
                                         rep_rate_hz=cfg.rep_rate_hz,
                                         elf=cfg.sensor_firmware, sync_edges=sync)
        else:
            self.sensor = SensorBoard(self.scene, self.pose, self.model, seed=cfg.seed,
                                      rep_rate_hz=cfg.rep_rate_hz,
                                      link_bytes_per_s=cfg.sensor_link_bytes_per_s,
                                      frozen_noise=cfg.frozen_noise, sync_edges=sync)
        self.channels = {
            (name, way): FaultyChannel(link[name], seed=cfg.seed * 4 + i)
            for i, (name, way) in enumerate((n, w) for n in ("sensor", "stage")
                                            for w in ("up", "down"))}
        self.to_host = {"sensor": bytearray(), "stage": bytearray()}
        self.t = 0.0

    # ------------------------------------------------------------------ ground truth
    def pose(self, t: float) -> tuple[np.ndarray, float]:
        """True sensor position S (mm, frame {0}) and table angle theta (deg) at time t.

        S is the stage's physical position with {0} at logical (0, 0, 0) after homing
        (raw steps + the homed origin), plus a fixed per-position scatter.
        """
        raw = self.stage.position_at(t)
        S = raw[:3] + np.asarray(self.limits.min_pos[:3], float)
        S = S + hash_noise("S[{:.3f} {:.3f} {:.3f}]".format(*raw[:3]),
                           self.cfg.stage_noise_mm, 3, self.cfg.seed)
        theta = raw[3] + hash_noise(f"A{round(raw[3], 3)}", self.cfg.angle_noise_deg, 1,
                                     self.cfg.seed)[0]
        return S, float(theta)

    def x_step_edges(self, t_from: float, t_to: float) -> np.ndarray:
        """Times (s) of the X stepper's STEP pulses in (t_from, t_to]: the motion-sync wire
        from the stage board's X STEP line to the sensor board (docs/firmware.md)."""
        return self.stage.step_edges(self.limits.axis("X"), t_from, t_to)

    def a_step_edges(self, t_from: float, t_to: float) -> np.ndarray:
        """Times (s) of the turntable stepper's STEP pulses in (t_from, t_to]: the second
        motion-sync wire (docs/firmware.md)."""
        return self.stage.step_edges(self.limits.axis("A"), t_from, t_to)

    def truth(self) -> dict:
        """What the host must estimate: v, n, X_R, c, t0s, the current pose and distance."""
        S, theta = self.pose(self.t)
        hit = self.scene.cast(S, theta)
        oa, us = arrival_times_us(hit.d, self.model) if np.isfinite(hit.d) else (None, None)
        return {"v": self.scene.v.tolist(), "n": self.scene.n.tolist(),
                "X_R": self.scene.X_R.tolist(), "c_mm_per_us": self.model.c_mm_us,
                "t0_oa_us": self.model.t0_oa_us, "t0_us_us": self.model.t0_us_us,
                "temperature_c": self.model.temperature_c, "S": S.tolist(), "theta": theta,
                "distance_mm": hit.d, "material": hit.material, "object": hit.obj,
                "arrival_oa_us": oa, "arrival_us_us": us, "time_s": self.t,
                "config": {f.name: getattr(self.cfg, f.name) for f in fields(self.cfg)
                           if f.name != "objects"}}

    def truth_objects(self) -> list[ObjectTruth]:
        """Each mounted object's true surface in its own frame (mesh, signed distance,
        material per face, fill) and its pose on the table: what a scan or a model is
        scored against. In process only, as truth()."""
        from ..physics.mesh import object_truth  # trimesh only when asked

        return [object_truth(obj) for obj in self.scene.objects]

    def close(self) -> None:
        """Stop what runs outside this process (the stage firmware's simavr harness)."""
        close = getattr(self.stage, "close", None)
        if close is not None:
            close()

    # ------------------------------------------------------------------ host side
    def write(self, link: str, data: bytes) -> None:
        """Bytes the host sends on `link` ('sensor' or 'stage')."""
        data = self.channels[(link, "down")].deliver(data, self.t, 0.0)
        if data:
            board = self.sensor if link == "sensor" else self.stage
            board.receive(data, self.t)

    def read(self, link: str) -> bytes:
        """Bytes that reached the host on `link` since the last read."""
        out = bytes(self.to_host[link])
        self.to_host[link].clear()
        return out

    def advance(self, dt: float) -> None:
        """Run both boards for dt seconds of simulated time."""
        end = self.t + dt
        while self.t < end - 1e-12:
            # fine steps only while shots sample the moving stage; moves are analytic
            fine = self.sensor.sampling()
            step = min(STEP_S if fine else 0.05, end - self.t)
            self.t += step
            for link, board in (("stage", self.stage), ("sensor", self.sensor)):
                out = board.step(self.t)
                up = self.channels[(link, "up")]
                self.to_host[link] += up.deliver(out, self.t, step)
                down = self.channels[(link, "down")]
                late = down.deliver(b"", self.t, step)  # bytes held by a stall
                if late:
                    board.receive(late, self.t)
