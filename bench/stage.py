"""Stage benchmark, the Marlin emulator and the real Marlin side by side (issue 20): moves/s
through the stage client, the time one lost `ok` costs, and how fast a stop stops (issue 29):
stage time from the stop request to the last STEP pulse, and until stop() returned with the
stage proven standing, within a move and behind queued lines, all in real time (speed 1).

usage: python bench/stage.py [--stage-firmware build/marlin/Marlin.elf] [--moves 200]
Without --stage-firmware (or DMDSM_STAGE_FIRMWARE) only the emulator is measured; the
firmware is built by `make check-marlin MARLIN=DIR` (docs/marlin.md).
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

from dmdsm.host.links.stage import StageClient
from dmdsm.sim.servers.emulator import Emulator
from dmdsm.sim.servers.runner import SimConfig


def measure(elf: str, moves: int, losses: int) -> dict:
    """Moves/s for `moves` pipelined 0.2 mm moves and the median recovery time (s) of
    `losses` lost oks, on one stage (the emulator if elf is empty)."""
    emu = Emulator(SimConfig(seed=1, stage_firmware=elf), speed=1.0).start()
    sim, server = emu.sim, emu.server
    try:
        st = StageClient(server.ports["stage"].name_for_host, timeout_s=0.5)
        st.send("G92 X100 Y100 Z100 A0")
        st.send("G91")
        t0 = time.monotonic()
        for i in range(moves):  # 0.2 mm there and back: the planner's queue stays full
            st.send(f"G1 X{0.2 * (-1) ** i:.4f} F6000", wait=False)
        st.drain(timeout_s=30)
        st.wait()
        rate = moves / (time.monotonic() - t0)
        recover = []
        for _ in range(losses):
            with server.lock:
                sim.stage.faults.lose_next_oks = 1
            t0 = time.monotonic()
            st.send("M114", wait=False)
            st.drain()  # a numbered probe after 0.5 s of silence
            recover.append(time.monotonic() - t0)
        st.close()
        st = StageClient(server.ports["stage"].name_for_host)  # the default timeout
        st.send("G90")
        stops = {"within a move": [], "behind 6 queued lines": []}
        for kind, runs in stops.items():
            for k in range(3):
                st.move(x=100 + 40 * (-1) ** k, feed_mm_min=2400)
                if kind != "within a move":
                    for j in range(6):
                        st.move(x=100 + 5 * j, y=100 + 10 * j, feed_mm_min=2400)
                t_first = sim.t
                while not _steps(sim, t_first, sim.t):  # wait for the move to start
                    time.sleep(0.002)
                t_request = sim.t
                st.stop()
                t_return = sim.t
                edges = _steps(sim, t_request - 5.0, t_return)
                runs.append((max(0.0, max(edges) - t_request) if edges else 0.0,
                             t_return - t_request))
        st.close()
        return {"moves_per_s": rate, "recover_s": statistics.median(recover),
                "recover_max_s": max(recover), "stops": stops}
    finally:
        emu.stop()


def _steps(sim, t0: float, t1: float) -> list[float]:
    """Times (s) of every STEP pulse of any axis in (t0, t1]."""
    return [float(t) for a in range(4) for t in sim.stage.step_edges(a, t0, t1)]


def main() -> None:
    """Print the figures for the emulator and, if given, the real firmware."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--stage-firmware", default=os.environ.get("DMDSM_STAGE_FIRMWARE", ""))
    ap.add_argument("--moves", type=int, default=200)
    ap.add_argument("--losses", type=int, default=5)
    args = ap.parse_args()
    stages = {"Marlin emulator": ""}
    if args.stage_firmware:
        stages["real Marlin (simavr)"] = args.stage_firmware
    print(f"stage link, real time: {args.moves} pipelined 0.2 mm moves (reversing), "
          f"{args.losses} lost oks (client timeout 0.5 s)")
    for name, elf in stages.items():
        r = measure(elf, args.moves, args.losses)
        print(f"  {name:22s} {r['moves_per_s']:6.1f} moves/s   one lost ok costs "
              f"{r['recover_s']:.3f} s (max {r['recover_max_s']:.3f} s)")
        for kind, runs in r["stops"].items():
            stand = [a for a, _ in runs]
            back = [b for _, b in runs]
            print(f"  {'':22s} stop {kind}: last step {1e3 * max(stand):.0f} ms after the "
                  f"request (worst of {len(runs)}), stop() returned after "
                  f"{statistics.median(back):.2f} s (max {max(back):.2f} s)")


if __name__ == "__main__":
    main()
