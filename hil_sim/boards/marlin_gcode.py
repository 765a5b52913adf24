"""G-code handlers of the Marlin emulator: motion, homing, position reports, capabilities."""

from __future__ import annotations

import re

import numpy as np

FIRMWARE_NAME = "Marlin bugfix-2.1.x (dmdsm hil_sim)"

WORD = re.compile(r"([A-Z])\s*([-+]?(?:\d+\.?\d*|\.\d+))?")
CAPS = ("SERIAL_XON_XOFF:0", "BINARY_FILE_TRANSFER:0", "EEPROM:1", "VOLUMETRIC:0",
        "AUTOREPORT_POS:1", "AUTOREPORT_TEMP:0", "PROGRESS:0", "PRINT_JOB:1",
        "AUTOLEVEL:0", "RUNOUT:0", "Z_PROBE:0", "LEVELING_DATA:0", "BUILD_PERCENT:0",
        "SOFTWARE_POWER:0", "TOGGLE_LIGHTS:0", "CASE_LIGHT_BRIGHTNESS:0",
        "EMERGENCY_PARSER:1", "HOST_ACTION_COMMANDS:1", "PROMPT_SUPPORT:0", "SDCARD:0",
        "REPEAT:0", "SD_WRITE:0", "AUTOREPORT_SD_STATUS:0", "LONG_FILENAME:0",
        "LFN_WRITE:0", "CUSTOM_FIRMWARE_UPLOAD:0", "EXTENDED_M20:0", "THERMAL_PROTECTION:0",
        "MOTION_MODES:0", "ARCS:1", "BABYSTEPPING:0", "EP_BABYSTEP:0", "CHAMBER_TEMPERATURE:0",
        "COOLER_TEMPERATURE:0", "MEATPACK:0", "CONFIG_EXPORT:0")


def parse_words(cmd: str) -> tuple[str, dict[str, float | None]]:
    """('G1', {'X': 10.0, 'F': 3000.0}) from 'G1 X10 F3000'; the code is upper-cased."""
    words = WORD.findall(cmd.upper())
    if not words:
        return "", {}
    (letter, num), *rest = words
    code = letter + (num.split(".")[0] if num else "")
    if num and "." in num and num.split(".")[1].strip("0"):
        code = letter + num  # e.g. G29.1: unknown to this firmware
    return code, {k: (float(v) if v else None) for k, v in rest}


class GcodeMixin:
    """The commands of MarlinEmulator (see marlin.py for the line protocol)."""

    # attributes provided by MarlinEmulator
    limits: object
    planner: object

    def _execute(self, cmd: str, n: int | None) -> None:
        self.executed.append((n, cmd))
        code, words = parse_words(cmd)
        handler = getattr(self, f"_{code}", None)
        if handler is None:
            self.out.append(f'echo:Unknown command: "{cmd}"')
            self._ok(n)
            return
        if handler(words, n) is not False:  # False: the handler blocks and sends ok later
            self._ok(n)

    # ------------------------------------------------------------------ helpers
    def _axes(self) -> list[str]:
        return list(self.limits.axes)

    def _position_line(self) -> str:
        """The M114 / M154 report: logical position of the last move, then stepper counts."""
        self.planner.update(self.now)
        pos = " ".join(f"{a}:{v:.2f}" for a, v in zip(self._axes(), self.current))
        counts = " ".join(f"{a}:{int(s)}" for a, s in zip(self._axes(), self.planner.steps))
        return f"{pos} Count {counts}"

    def _sync_current_from_steppers(self) -> None:
        self.current = self.planner.position() + self.offset

    def _target(self, words: dict) -> np.ndarray:
        target = self.current.copy()
        for i, a in enumerate(self._axes()):
            v = words.get(a)
            if v is None:
                continue
            target[i] = target[i] + v if self.relative else v
            lo, hi = self.limits.min_pos[i], self.limits.max_pos[i]
            if self.homed[i]:  # soft endstops apply to homed axes only
                raw = target[i] - self.offset[i]
                target[i] = min(max(raw, lo), hi) + self.offset[i]
        return target

    # ------------------------------------------------------------------ motion
    def _G0(self, words: dict, n: int | None) -> bool:
        if words.get("F"):
            self.feed_mm_s = words["F"] / 60.0
        target = self._target(words)
        start = self.planner.to_steps(self.current - self.offset)
        end = self.planner.to_steps(target - self.offset)
        self.current = target
        if self.planner.free_blocks() <= 0:
            self._block("move", 0.0, n, args=(start, end, self.feed_mm_s))
            return False
        self.planner.add(self.now, start, end, self.feed_mm_s)
        return True

    _G1 = _G0

    def _G4(self, words: dict, n: int | None) -> bool:
        wait = (words.get("P") or 0) / 1000.0 + (words.get("S") or 0)
        self._block("sync", self.planner.busy_until(self.now) + wait, n)
        return False

    def _G28(self, words: dict, n: int | None) -> bool:
        which = [a for a in "XYZ" if a in words] or ["X", "Y", "Z"]  # A has no endstop
        t = self.planner.busy_until(self.now)
        physical = self.planner.position()  # raw position the steppers really are at
        for a in which:
            i = self.limits.axis(a)
            # travel to the min endstop (raw 0 is where it triggers), back off, re-bump slower
            dist = abs(physical[i]) + 5.0 + 5.0 * 2
            t += dist / (self.limits.homing_feedrate_mm_m[i] / 60.0)

        def done() -> None:
            for a in which:
                i = self.limits.axis(a)
                self.offset[i] = self.limits.min_pos[i]  # endstop at raw 0 = logical min
                self.current[i] = self.limits.min_pos[i]
                self.homed[i] = True
                self.planner.steps[i] = 0
            self.out.append(self._position_line())

        self._block("sync", t, n, then=done)
        return False

    def _G90(self, words: dict, n: int | None) -> None:
        self.relative = False

    def _G91(self, words: dict, n: int | None) -> None:
        self.relative = True

    def _G92(self, words: dict, n: int | None) -> None:
        for i, a in enumerate(self._axes()):
            if words.get(a) is not None:
                raw = self.current[i] - self.offset[i]
                self.offset[i] = words[a] - raw
                self.current[i] = words[a]

    # ------------------------------------------------------------------ M codes
    def _M17(self, words: dict, n: int | None) -> None:
        pass

    def _M18(self, words: dict, n: int | None) -> None:
        pass  # motors off; positions are kept (the host re-homes if it cares)

    _M84 = _M18

    def _M105(self, words: dict, n: int | None) -> None:
        pass  # no temperature sensors: a plain ok

    def _M110(self, words: dict, n: int | None) -> None:
        if words.get("N") is not None:
            self.last_n = int(words["N"])

    def _M114(self, words: dict, n: int | None) -> bool | None:
        if "R" in words:  # M114_REALTIME: where the steppers are now
            self.planner.update(self.now)
            real = self.planner.position() + self.offset
            self.out.append(" ".join(f"{a}:{v:.2f}" for a, v in zip(self._axes(), real)))
            return None
        if "D" in words:  # M114_DETAIL: synchronises the planner first
            def detail() -> None:
                raw = self.current - self.offset
                fmt = " ".join
                self.out += [
                    "Logical: " + fmt(f"{a}:{v:.2f}" for a, v in zip("XYZ", self.current)),
                    "Raw:     " + fmt(f"{a}:{v:.2f}" for a, v in zip("XYZ", raw)),
                    "Stepper: " + fmt(f"{a}:{int(s)}" for a, s in
                                      zip(self._axes(), self.planner.steps)),
                    "FromStp: " + fmt(f"{a}:{v:.2f}" for a, v in
                                      zip(self._axes(), self.planner.position())),
                    "Diff:    " + fmt(f"{a}:{v:.2f}" for a, v in
                                      zip(self._axes(), self.planner.position() - raw)),
                    self._position_line()]
            self._block("sync", self.now, n, then=detail)
            return False
        self.out.append(self._position_line())
        return None

    def _M115(self, words: dict, n: int | None) -> None:
        self.out.append(f"FIRMWARE_NAME:{FIRMWARE_NAME} SOURCE_CODE_URL:github.com/MarlinFirmware"
                        f"/Marlin PROTOCOL_VERSION:1.0 MACHINE_TYPE:Anycubic Chiron "
                        f"EXTRUDER_COUNT:0 AXIS_COUNT:{len(self._axes())} "
                        f"UUID:cede2a2f-41a2-4748-9b12-c55c62f367ff")
        self.out += [f"Cap:{c}" for c in CAPS]

    def _M154(self, words: dict, n: int | None) -> None:
        self.auto_report_s = float(words.get("S") or 0)
        self.next_report = self.now + self.auto_report_s

    def _M400(self, words: dict, n: int | None) -> bool:
        # planner.synchronize(): until the planner is empty, however that happens (the moves
        # end, or an M410 drops them), not until the time the moves would have ended
        self._block("sync", self.now, n)
        return False

    def _M410(self, words: dict, n: int | None) -> None:
        self.planner.quick_stop(self.now)
        self._sync_current_from_steppers()

    def _M999(self, words: dict, n: int | None) -> bool:
        self.rx.clear()
        self.out += [f"Resend: {self.last_n + 1}", "ok"]
        return False
