"""G-code handlers of the Marlin emulator: motion, homing, position reports, capabilities."""

from __future__ import annotations

import re

import numpy as np

FIRMWARE_NAME = "Marlin bugfix-2.1.x"
BUILT = "Dec  3 2026 08:00:38"  # M115 and the banner name the build's __DATE__ __TIME__
Z_AFTER_HOMING_MM = 5.0  # the real Chiron build stands at Z 5.00 after G28 (issue 20)

WORD = re.compile(r"([A-Z])\s*([-+]?(?:\d+\.?\d*|\.\d+))?")
CAPS = ("SERIAL_XON_XOFF:0", "BINARY_FILE_TRANSFER:0", "EEPROM:1", "VOLUMETRIC:0",
        "AUTOREPORT_POS:1", "AUTOREPORT_TEMP:0", "PROGRESS:0", "PRINT_JOB:1",
        "AUTOLEVEL:0", "RUNOUT:0", "Z_PROBE:0", "LEVELING_DATA:0", "BUILD_PERCENT:1",
        "SOFTWARE_POWER:0", "TOGGLE_LIGHTS:0", "CASE_LIGHT_BRIGHTNESS:0",
        "EMERGENCY_PARSER:1", "HOST_ACTION_COMMANDS:1", "PROMPT_SUPPORT:1", "SDCARD:0",
        "REPEAT:0", "SD_WRITE:0", "AUTOREPORT_SD_STATUS:0", "LONG_FILENAME:0",
        "LFN_WRITE:0", "CUSTOM_FIRMWARE_UPLOAD:0", "EXTENDED_M20:0", "THERMAL_PROTECTION:1",
        "MOTION_MODES:0", "ARCS:1", "BABYSTEPPING:0", "EP_BABYSTEP:0", "CHAMBER_TEMPERATURE:0",
        "COOLER_TEMPERATURE:0", "MEATPACK:0", "CONFIG_EXPORT:0")


def parse_words(cmd: str) -> tuple[str, dict[str, float | None]]:
    """('G1', {'X': 10.0, 'F': 3000.0}) from 'G1 X10 F3000'. Case matters, as in Marlin
    without GCODE_CASE_INSENSITIVE: 'g1 x15' is no command ('', {})."""
    if not cmd[:1].isupper():
        return "", {}
    words = WORD.findall(cmd)
    if not words:
        return "", {}
    (letter, num), *rest = words
    code = letter + (num.split(".")[0] if num else "")
    if num and "." in num and num.split(".")[1].strip("0"):
        code = letter + num  # e.g. G29.1: unknown to this firmware
    return code, {k: (float(v) if v else None) for k, v in rest}


# (cleaning_buffer_counter), and M410 answers only then: its ok came 1.03 s after it on the
# real Marlin in simavr (issue 20 saw ~1.2 s)


def marlin_float(v: float, digits: int = 2) -> str:
    """A float as Marlin prints it on an AVR: 32-bit floats, rounded by adding half a unit
    of the last digit, then digit by digit (-694.275 -> -694.28, 10.395 -> 10.39)."""
    f32 = np.float32
    x = f32(v)
    sign = "-" if x < 0 else ""
    x = f32(abs(x))
    r = f32(0.5)
    for _ in range(digits):
        r = f32(r * f32(0.1))
    x = f32(x + r)
    whole = int(x)
    rem = f32(x - f32(whole))
    out = f"{sign}{whole}"
    if digits:
        out += "."
        for _ in range(digits):
            rem = f32(rem * f32(10.0))
            d = min(int(rem), 9)
            out += str(d)
            rem = f32(rem - f32(d))
    return out


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

    def _counts(self, raw: np.ndarray) -> np.ndarray:
        """Stepper counts as Marlin keeps them: native position x steps/unit (homing sets the
        count to the min position's, G92 leaves it alone)."""
        return np.rint((raw + self.native0) * self.planner.spu).astype(np.int64)

    def _position_line(self, live: bool = False, live_counts: bool = False) -> str:
        """The M114 / M154 report (report_current_position_projected): logical position of
        the last move, then the planner's position in steps, which a move too short to queue
        left where it was (live: where the steppers are now, as M114 R; live_counts: the last
        move's position with the steppers' counts now, as Marlin's report_current_position
        after G92 and G28 prints them)."""
        self.planner.update(self.now)
        if live:
            raw = self.planner.count_position()
            pos_v, counts_v = raw + self.offset, self._counts(raw)
        elif live_counts:
            pos_v, counts_v = self.current, self._counts(self.planner.count_position())
        else:
            pos_v = self.current
            counts_v = self.planner.pos + np.rint(self.native0 * self.planner.spu).astype(int)
        pos = " ".join(f"{a}:{marlin_float(v)}" for a, v in zip(self._axes(), pos_v))
        counts = " ".join(f"{a}:{int(c)}" for a, c in zip(self._axes(), counts_v))
        return f"{pos} Count {counts}"

    def _sync_current_from_steppers(self) -> None:
        self.current = self.planner.count_position() + self.offset

    def _target(self, words: dict) -> np.ndarray:
        target = self.current.copy()
        for i, a in enumerate(self._axes()):
            v = words.get(a)
            if v is None:
                continue
            target[i] = target[i] + v if self.relative else v
            lo, hi = self.limits.min_pos[i], self.limits.max_pos[i]
            if self.homed[i]:  # soft endstops: on the native position, homed axes only
                shift = self.offset[i] - self.native0[i]  # G92's
                target[i] = min(max(target[i] - shift, lo), hi) + shift
        return target

    # ------------------------------------------------------------------ motion
    def _G0(self, words: dict, n: int | None) -> bool:
        feed = words.get("F")
        if feed is not None and feed > 0:  # Marlin keeps the last feedrate for F <= 0, NaN
            self.feed_mm_s = feed / 60.0
        target = self._target(words)
        end = self.planner.to_steps(target - self.offset)
        self.current = target  # even when the planner drops the move (too few steps)
        if self.planner.free_blocks() <= 0:
            self._block("move", 0.0, n, args=(end, self.feed_mm_s))
            return False
        self.planner.line_to(self.now, end, self.feed_mm_s)
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

        z_raise = "Z" in which and Z_AFTER_HOMING_MM > self.limits.min_pos[2]
        if z_raise:
            t += (Z_AFTER_HOMING_MM - self.limits.min_pos[2]) / (
                self.limits.homing_feedrate_mm_m[2] / 60.0)

        def done() -> None:
            for a in which:
                i = self.limits.axis(a)
                self.offset[i] = self.native0[i] = self.limits.min_pos[i]  # raw 0: endstop
                self.current[i] = self.limits.min_pos[i]
                self.homed[i] = True
                self.planner.set_axis(i, 0)
            if z_raise:  # the Chiron example's Z_AFTER_HOMING: the nozzle clears the bed
                i = self.limits.axis("Z")
                self.current[i] = Z_AFTER_HOMING_MM
                self.planner.set_axis(i, round((Z_AFTER_HOMING_MM - self.offset[i]) *
                                               self.planner.spu[i]))
            # sync_plan_position(): every other axis's planner position and count from its
            # commanded one, so steps a dropped move left owed are counted, never taken
            synced = self.planner.to_steps(self.current - self.offset)
            for i, a in enumerate(self._axes()):
                if a not in which:
                    self.planner.sync_axis(i, int(synced[i]))
            self.out.append(self._position_line(live_counts=True))

        self._block("sync", t, n, then=done)
        return False

    def _G90(self, words: dict, n: int | None) -> None:
        self.relative = False

    def _G91(self, words: dict, n: int | None) -> None:
        self.relative = True

    def _G92(self, words: dict, n: int | None) -> None:
        # with workspace offsets (the build's default) G92 shifts the offset alone: the native
        # position, the planner's steps (and any steps a dropped move left owed) stay
        for i, a in enumerate(self._axes()):
            if words.get(a) is not None:
                raw = self.current[i] - self.offset[i]
                self.offset[i] = words[a] - raw
                self.current[i] = words[a]
        # Marlin's G92 ends in report_current_position(): the new logical position, and
        # stepper.report_positions(), the counts where the steppers are now (a move may run)
        self.out.append(self._position_line(live_counts=True))

    # ------------------------------------------------------------------ M codes
    def _M17(self, words: dict, n: int | None) -> None:
        pass

    def _M18(self, words: dict, n: int | None) -> bool:
        # motors off once the moves are done (Marlin synchronises the planner first);
        # positions are kept (the host re-homes if it cares)
        self._block("sync", self.now, n)
        return False

    _M84 = _M18

    def _M105(self, words: dict, n: int | None) -> bool:
        # M105 sends its own "ok" with the temperatures (none here): no N, P or B, even for
        # a numbered line, so its ok proves nothing about line numbers
        self.out.append("ok T:0")
        return False

    def _M110(self, words: dict, n: int | None) -> None:
        if words.get("N") is not None:
            self.last_n = int(words["N"])

    def _M114(self, words: dict, n: int | None) -> bool | None:
        if "R" in words:  # M114_REALTIME: where the steppers are now, with their counts
            self.out.append(self._position_line(live=True))
            return None
        if "D" in words:  # M114_DETAIL: synchronises the planner first
            def detail() -> None:
                native = self.current - self.offset + self.native0

                def fmt(axes: object, values: object, digits: int = 3) -> str:
                    if digits == 0:  # counts: "X:-800 Y:0"
                        return "".join(f" {a}:{int(v)}" for a, v in zip(axes, values))
                    return "".join(f" {a}:{float(np.float32(v)): .{digits}f}"  # "Y: 0.000"
                                   for a, v in zip(axes, values))
                from_steps = self.planner.count_position() + self.native0
                self.out += [  # report_current_position(): the steppers' counts
                    self._position_line(live_counts=True), "",
                    "Logical:" + fmt("XYZ", self.current),
                    "Raw:    " + fmt("XYZ", native),
                    "Stepper:" + fmt(self._axes(), self._counts(self.planner.count_position()), 0),
                    "FromStp:" + fmt(self._axes(), from_steps),
                    "Diff:   " + fmt(self._axes(), from_steps - native)]
            self._block("sync", self.now, n, then=detail)
            return False
        self.out.append(self._position_line())
        return None

    def _M115(self, words: dict, n: int | None) -> None:
        self.out.append(f"FIRMWARE_NAME:{FIRMWARE_NAME} ({BUILT}) SOURCE_CODE_URL:github.com/"
                        f"MarlinFirmware/Marlin PROTOCOL_VERSION:1.0 MACHINE_TYPE:Anycubic "
                        f"Chiron KINEMATICS:Cartesian EXTRUDER_COUNT:0 "
                        f"AXIS_COUNT:{len(self._axes())} "
                        f"UUID:cede2a2f-41a2-4748-9b12-c55c62f367ff")
        self.out += [f"Cap:{c}" for c in CAPS]

    def _M117(self, words: dict, n: int | None) -> None:
        pass  # a status message for an LCD the Chiron build has not enabled: just ok

    def _M154(self, words: dict, n: int | None) -> None:
        self.auto_report_s = float(words.get("S") or 0)
        self.next_report = self.now + self.auto_report_s

    def _M400(self, words: dict, n: int | None) -> bool:
        # planner.synchronize(): until the planner is empty, however that happens (the moves
        # end, or an M410 drops them), not until the time the moves would have ended
        self._block("sync", self.now, n)
        return False

    def _M410(self, words: dict, n: int | None) -> None:
        # with EMERGENCY_PARSER the stop happened when the line's bytes arrived (marlin.py
        # _emergency); the queued command is a no-op (gcode.cpp `case 410: break;`), so its
        # ok comes once the loop runs again, after the 1 s clean-up
        pass

    def _M999(self, words: dict, n: int | None) -> bool:
        self.rx.clear()
        self.out += [f"Resend: {self.last_n + 1}", "ok"]
        return False
