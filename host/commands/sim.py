"""`dmdsm sim`: start the SIL emulator of both boards and print the two port names."""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
import time

import numpy as np


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register `sim`."""
    p = sub.add_parser("sim", help="run the emulator of both boards on pseudo-terminals")
    p.add_argument("--scene", default=None,
                   help="objects on the turntable (--list-scenes shows them; default "
                        "aluminium_block, or nothing else beside --object)")
    p.add_argument("--object", default=None, metavar="FILE",
                   help="also mount this closed mesh (STL, OBJ, PLY or OFF, in mm) standing "
                        "centred on the turntable")
    p.add_argument("--material", default="plastic", metavar="M",
                   help="the --object's material: aluminium, apple, foam, glass, paper, "
                        "plastic, steel or graphite (default plastic)")
    p.add_argument("--regions", default=None, metavar="JSON",
                   help='the --object\'s parts of other materials: {"paper": [face, ...]} '
                        "with faces numbered from 0 in the mesh file's order")
    p.add_argument("--hollow", action="store_true",
                   help="let the sound see the --object's inside (inner walls, the far wall: "
                        "docs/sim.md, what the physics does at an interface)")
    p.add_argument("--fill", default=None, metavar="M",
                   help="what fills the --object's cavities (e.g. water); implies --hollow")
    p.add_argument("--yaw", type=float, default=0.0,
                   help="turn the --object about the table's axis (deg)")
    p.add_argument("--tilt", type=float, default=0.0,
                   help="tilt the --object about the table's x axis before the yaw (deg)")
    p.add_argument("--offset", type=float, nargs=2, default=(0.0, 0.0), metavar=("X", "Y"),
                   help="place the --object's centre X, Y mm off the table's axis (default "
                        "0 0: centred)")
    p.add_argument("--list-scenes", action="store_true",
                   help="print the scenes (objects, materials, sizes in mm) and exit")
    p.add_argument("--positions", action="store_true",
                   help="print where the README's hand pipeline puts the sensor on this "
                        "emulator (the block's gauge distance, the rig's tip and filament) "
                        "and exit: what a user finds by jogging on the machine")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--speed", type=float, default=1.0,
                   help="simulated seconds per wall-clock second (default 1)")
    p.add_argument("--faults", default="",
                   help="e.g. sensor.flip=1e-5,sensor.drop=1e-5,stage.lost_ok=0.01")
    p.add_argument("--link-dir", default=None,
                   help="also create stable symlinks DIR/sensor and DIR/stage")
    p.add_argument("--temperature", type=float, default=20.0, help="air temperature (degC)")
    p.add_argument("--rep-rate", type=float, default=1000.0, help="laser shots per second")
    p.add_argument("--sensor-link", type=float, default=200_000.0,
                   help="sensor link bytes/s (default 2 Mbaud: 200000; USB FS: 1150000)")
    p.add_argument("--sensor-firmware", default="", metavar="nucleo|ELF",
                   help="run this NUCLEO firmware ELF ('nucleo': the one `make` builds) on "
                        "the rehosted H743 instead of the firmware core")
    p.add_argument("--stage-firmware", default="", metavar="ELF",
                   help="run this stage firmware (Marlin.elf built from firmware/marlin_patch, "
                        "docs/marlin.md) under simavr instead of the Marlin emulator")
    p.add_argument("--json", action="store_true", help="print the ports as one JSON line")
    p.set_defaults(func=cmd_sim)


def cmd_sim(args: argparse.Namespace) -> int:
    """Run until Ctrl-C (or SIGTERM)."""
    from dmdsm.sim.physics.objects import SCENES
    from dmdsm.sim.servers.emulator import Emulator
    from dmdsm.sim.servers.runner import SimConfig

    from .errors import CliError

    if args.list_scenes:
        print(list_scenes(SCENES))
        return 0
    if args.positions:
        print(hand_positions(SimConfig()))
        return 0
    if args.speed <= 0:
        raise CliError("--speed must be positive")
    objects = [user_object(args.object, args.material, args.yaw, args.tilt, args.regions,
                           args.hollow, args.fill, args.offset)] if args.object else []
    if args.scene is None:
        args.scene = "empty" if objects else "aluminium_block"
    try:
        emu = Emulator(SimConfig(scene=args.scene, seed=args.seed, faults=args.faults,
                                 objects=objects,
                                 temperature_c=args.temperature, rep_rate_hz=args.rep_rate,
                                 sensor_link_bytes_per_s=args.sensor_link,
                                 sensor_firmware=args.sensor_firmware,
                                 stage_firmware=args.stage_firmware),
                       speed=args.speed, link_dir=args.link_dir)
    except (ValueError, TypeError, OSError, RuntimeError) as e:
        raise CliError(str(e)) from None
    sim, server = emu.sim, emu.server
    ports = {"sensor": emu.sensor, "stage": emu.stage}
    mounted = "".join(f" + {o.name} ({o.material})" for o in objects)
    if args.json:
        print(json.dumps({"sensor": ports["sensor"], "stage": ports["stage"],
                          "scene": args.scene, "seed": args.seed,
                          **({"object": args.object} if args.object else {})}), flush=True)
    else:
        print(f"sensor board: {ports['sensor']}\nstage board:  {ports['stage']}\n"
              f"scene {args.scene}{mounted}, seed {args.seed}, speed x{args.speed:g}; "
              "Ctrl-C stops",
              flush=True)
    # Ctrl-C and SIGTERM set the stop flag rather than raise: an exception raised inside a
    # unicorn MMIO callback (the rehosted board) is swallowed by ctypes and the stop was lost
    signal.signal(signal.SIGTERM, lambda *_: server.stop())
    signal.signal(signal.SIGINT, lambda *_: server.stop())
    if args.sensor_firmware:
        threading.Thread(target=_watch_rules, args=(sim, server), daemon=True).start()
    try:
        emu.serve()  # closes the simulation when it returns
    except KeyboardInterrupt:
        pass
    except RuntimeError as e:  # the stage firmware's harness ended or the firmware crashed
        raise CliError(f"the stage firmware stopped: {e}") from None
    broken = getattr(sim.sensor, "violation", None)
    if broken is not None:
        raise CliError(f"the sensor firmware broke a hardware rule and halted: {broken}")
    print("dmdsm sim: stopped", file=sys.stderr)
    return 0


def user_object(path: str, material: str, yaw: float = 0.0, tilt: float = 0.0,
                regions: str | None = None, hollow: bool = False,
                fill: str | None = None, offset_mm: tuple[float, float] = (0.0, 0.0)) -> object:
    """A user's mesh file as a SceneObject standing on the table (yaw, tilt in deg; offset
    x, y in mm from the axis;
    a region map JSON gives parts other materials; hollow: the sound sees inside it; fill:
    what fills it); a file that cannot be mounted is one line saying what to fix (a
    CliError)."""
    from dmdsm.sim.physics.mesh import MeshFileError
    from dmdsm.sim.physics.mesh import user_object as mount

    from .errors import CliError

    try:
        return mount(path, material, yaw, tilt, regions, interior=hollow, fill=fill,
                     offset_mm=tuple(offset_mm))
    except MeshFileError as e:
        raise CliError(str(e)) from None


def _watch_rules(sim: object, server: object) -> None:
    """Stop the emulator when the rehosted firmware breaks a rule (checked every 0.2 s)."""
    while getattr(sim.sensor, "violation", None) is None:  # type: ignore[attr-defined]
        time.sleep(0.2)
    server.stop()  # type: ignore[attr-defined]


def list_scenes(scenes: dict) -> str:
    """One line per scene: its objects with material and size (width x depth x height, mm,
    in the table frame), what `dmdsm plan new --size-mm` takes."""
    from dmdsm.sim.physics.objects import bounding_size

    lines = []
    for name, make in scenes.items():
        parts = []
        for obj in make():
            w, d, h = bounding_size(obj)
            shape = type(obj.shape).__name__.lower()
            extra = [f"{m} {_region_name(obj, r)}" for r, m in sorted(obj.regions.items())]
            level = f" to {obj.fill_level:g} mm" if np.isfinite(obj.fill_level) else ""
            extra += [f"filled with {obj.fill}{level}"] if obj.fill else []
            more = f" ({', '.join(extra)})" if extra else ""
            parts.append(f"{obj.material} {shape} {w:.1f} x {d:.1f} x {h:.1f} mm{more}")
        lines.append(f"{name:18s} {'; '.join(parts) or 'nothing on the table'}")
    return "\n".join(lines)


def _region_name(obj: object, region: int) -> str:
    """A mesh region's name (`region_names`), or its number."""
    names = getattr(obj.shape, "region_names", ())  # type: ignore[attr-defined]
    return names[region] if region < len(names) else f"region {region}"


# where the hand pipeline puts the sensor (README "The same pipeline by hand"); the demo
# imports these (host/demo/session.py)
RANGING_AT_MM = (235.0, 266.0, 20.0)  # in front of the block's face, 7-8 mm away
TIP_AT = (np.array([0.0, -10.0, 20.0]), 6.0)     # table frame point, then back along v (mm)
EDGE_AT = (np.array([25.0, 0.0, 0.0]), 6.25)


def hand_positions(cfg: object) -> str:
    """The README's positions on this emulator, from its truth (v, n, X_R, the block): on
    the machine a gauge block gives the distance and jogging finds the tip and filament."""
    from dmdsm.sim.physics.objects import aluminium_block
    from dmdsm.sim.physics.scene import Scene, table_frame

    v_raw, n_raw, X_R = (np.asarray(x, float) for x in (cfg.v, cfg.n, cfg.X_R))
    scene = Scene(v=v_raw, n=n_raw, X_R=X_R, objects=aluminium_block())  # as runner.py
    v, n = v_raw / np.linalg.norm(v_raw), n_raw / np.linalg.norm(n_raw)
    frame = table_frame(n)
    d = scene.cast(np.array(RANGING_AT_MM), 0.0).d
    tip = X_R + frame @ TIP_AT[0] - TIP_AT[1] * v
    edge = X_R + frame @ EDGE_AT[0] - EDGE_AT[1] * v
    at = " ".join(f"{c:g}" for c in RANGING_AT_MM)
    return "\n".join([
        f"ranging: stage at {at}: the block's face is {d:.3f} mm in front of the sensor "
        f"(calibrate-range --at {at} --start-distance {d:.3f})",
        f"tip:     --at {tip[0]:.1f} {tip[1]:.1f} {tip[2]:.1f} (rig_horizontal: "
        f"{TIP_AT[1]:g} mm in front of the filament's tip, level with it)",
        f"edge:    --at {edge[0]:.1f} {edge[1]:.1f} 0 (rig_vertical: {EDGE_AT[1]:g} mm in "
        f"front of the filament)"])
