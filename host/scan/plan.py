"""Scan plans: what to scan and how (TOML or flags), expanded into stage points and checked
against the machine envelope and the keep-outs of the object and the turntable before any move.

The sensor stays in one plane in front of the object (the front plane, `standoff_mm` in front
of the object's bounding cylinder along the beam); each point is (X, Z) in that plane plus a
turntable angle. Points run angle by angle, level by level, and X back and forth so that
consecutive points are one step apart.
"""

from __future__ import annotations

import hashlib
import math
import tomllib
import unicodedata
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from dmdsm.marlin_patch import MachineLimits

from ..files import shown
from ..links.safety import KeepOut, UnsafeMove, check_move
from ..ranging.calibrate import RangingSetup
from ..ranging.point import PointRanger
from .reach import box_passes

MODALITIES = ("both", "oa", "us")
MODES = ("step", "fly", "auto", "sweep")


class PlanError(ValueError):
    """A scan plan that cannot be run; str() names the key and what to change."""


MAX_SETTLE_S = 60.0  # s of dwell per point a plan may ask for
MAX_OFFSETS = 9      # a sweep's passes at most (each a whole stack of rings)


@dataclass
class ScanPlan:
    """One scan: object, keep-out sizes (mm), raster (mm, deg), acquisition settings."""

    object_id: str
    material: str = ""
    notes: str = ""
    radius_mm: float = 30.0          # bounding cylinder about the table axis
    height_mm: float = 40.0
    levels_mm: list[float] = field(default_factory=lambda: [20.0])  # sensor Z above table
    angles_deg: list[float] = field(default_factory=lambda: [0.0, 90.0, 180.0, 270.0])
    half_width_mm: float = 35.0      # X raster: -half..+half about the table axis
    step_mm: float = 1.0
    standoff_mm: float = 8.0         # beam distance from the bounding cylinder to the sensor
    average: int = 16                # laser shots averaged on board per point
    samples: int = 1024
    settle_s: float = 0.0            # dwell after each move (G4) before acquiring
    feed_mm_min: float = 3000.0
    modality: str = "both"           # which distances the scan is for (both are ranged)
    turntable_radius_mm: float = 60.0
    depth_margin_mm: float = 3.0     # echoes are searched standoff - m .. standoff + 2R + m
    mode: str = "step"               # "step": step and shoot; "fly": each line one move
    laser_hz: float = 1000.0         # laser repetition rate; fly sets the speed from it
    # auto: a first look (levels this far apart, 8 angles) measures the outline; lines then
    # follow it standoff_mm away at levels_mm and at angles_deg plus those that see the rest
    # of it within max_incidence_deg, at most max_angles in all (docs/scanning.md)
    first_look_step_mm: float = 6.0
    max_incidence_deg: float = 45.0
    max_angles: int = 16
    rescan_budget_s: float = 60.0    # lines scanned again for the holes left, in s at most
    # sweep: one pass of rings per offset (mm) of the beam from the table axis, across
    # the beam in the table plane: a flat face seen head on away from its middle
    offsets_mm: list[float] = field(default_factory=lambda: [0.0])

    def validate(self) -> None:
        """Raise PlanError naming the first bad value."""
        if not self.object_id or any(c in self.object_id for c in "/\\ \t"):
            raise PlanError("sample.object_id must be a non-empty name without spaces or "
                            "slashes")
        for key in ("object_id", "material"):
            value = getattr(self, key)
            if any(unicodedata.category(c) == "Cc" for c in value):  # ESC, BEL, NUL, DEL
                raise PlanError(f"sample.{key} = {shown(value)} holds a control character: "
                                f"give printable text")
        pos = {"radius_mm": self.radius_mm, "step_mm": self.step_mm,
               "half_width_mm": self.half_width_mm, "average": self.average,
               "samples": self.samples, "feed_mm_min": self.feed_mm_min}
        for k, v in pos.items():
            if not v > 0:
                raise PlanError(f"{k} must be positive (got {v})")
        if self.height_mm < 0 or self.settle_s < 0:
            raise PlanError("height_mm and settle_s must not be negative")
        if self.settle_s > MAX_SETTLE_S:  # G4 P<ms>: a huge number is not honoured
            raise PlanError(f"settle_s = {self.settle_s:g} s is more than {MAX_SETTLE_S:g} s of "
                            f"dwell per point: give the seconds the stage needs to stand still")
        if not self.levels_mm or not self.angles_deg:
            raise PlanError("levels_mm and angles_deg need at least one value each")
        if self.modality not in MODALITIES:
            raise PlanError(f"modality must be one of {', '.join(MODALITIES)} "
                            f"(got {self.modality!r})")
        if self.mode not in MODES:
            raise PlanError(f"mode must be one of {', '.join(MODES)} (got {self.mode!r})")
        if not self.laser_hz > 0:
            raise PlanError(f"laser_hz must be positive (got {self.laser_hz})")
        if not 0 < self.max_incidence_deg < 90:
            raise PlanError(f"max_incidence_deg must be between 0 and 90 (got "
                            f"{self.max_incidence_deg:g})")
        if not 1 <= self.max_angles <= 72 or not self.first_look_step_mm > 0 or \
                not 0 <= self.rescan_budget_s <= 36_000:
            raise PlanError("max_angles must be 1..72, first_look_step_mm positive and "
                            "rescan_budget_s 0..36000 s")
        if self.mode in ("fly", "auto"):
            from dmdsm.marlin_patch import load_machine

            m = load_machine()
            v = self.step_mm * self.laser_hz / self.average
            vmax = m.max_feedrate[m.axis("X")]
            if v > vmax:
                raise PlanError(f"a fly scan at step_mm {self.step_mm:g} with average "
                                f"{self.average} and laser_hz {self.laser_hz:g} moves at "
                                f"{v:.0f} mm/s, above the X axis's {vmax:g} mm/s: raise "
                                f"average or lower step_mm")
        from dmdsm.marlin_patch import load_machine as _machine

        m = _machine()
        reach = max(hi - lo for lo, hi in zip(m.min_pos[:3], m.max_pos[:3]))
        for key in ("radius_mm", "height_mm", "half_width_mm", "standoff_mm"):
            if getattr(self, key) > reach:  # (a huge number also made a 400-character line)
                raise PlanError(f"{key} = {getattr(self, key):.6g} mm is more than the "
                                f"machine's longest travel ({reach:g} mm): give the object's "
                                f"size in mm")
        fastest = 60.0 * max(m.max_feedrate)
        if not 0 < self.feed_mm_min <= fastest:
            raise PlanError(f"feed_mm_min must be above 0 and at most the machine's fastest "
                            f"axis, {fastest:g} mm/min (got {self.feed_mm_min:g})")
        if self.step_mm > 2 * self.half_width_mm and self.mode != "sweep":  # (no raster)
            raise PlanError("step_mm is larger than the raster width (2 x half_width_mm)")
        numbers = {k: v for k, v in asdict(self).items() if isinstance(v, float | int)}
        numbers.update({f"levels_mm[{i}]": x for i, x in enumerate(self.levels_mm)})
        numbers.update({f"angles_deg[{i}]": x for i, x in enumerate(self.angles_deg)})
        numbers.update({f"offsets_mm[{i}]": x for i, x in enumerate(self.offsets_mm)})
        for k, v in numbers.items():
            if not math.isfinite(v):
                raise PlanError(f"{k} must be a finite number (got {v})")
        for k, (lo, hi) in _sensor_limits().items():  # the protocol's ranges (set_config)
            if not lo <= getattr(self, k) <= hi:
                raise PlanError(f"{k} = {getattr(self, k)} is outside what the sensor board "
                                f"takes ({lo}..{hi})")
        if not 1 <= len(self.offsets_mm) <= MAX_OFFSETS or \
                not all(abs(d) < self.radius_mm for d in self.offsets_mm):
            raise PlanError(f"offsets_mm must give 1 to {MAX_OFFSETS} offsets of the beam "
                            f"from the table axis, each within the bounding cylinder's radius "
                            f"({self.radius_mm:g} mm; got {self.offsets_mm!r:.60})")
        if self.mode != "sweep" and self.offsets_mm != [0.0]:
            raise PlanError("offsets_mm is for sweeps (mode = \"sweep\"): leave it out of a "
                            f"{self.mode} plan")
        n = len(self.levels_mm) * len(self.angles_deg) * \
            (2 * self.half_width_mm / self.step_mm + 1)  # float: no huge integers
        limit = MAX_POINTS
        if self.mode == "sweep":  # a ring's waveforms per pass, the table's limit aside
            n = (max(self.levels_mm) - min(self.levels_mm)) / self.step_mm * sum(
                waveforms_per_turn(self, math.inf, o) for o in self.offsets_mm)
            limit = MAX_SWEEP_POINTS
        if not n <= limit:
            raise PlanError(f"the plan has {n:.3g} points (at most {limit}): raise step_mm "
                            f"or lower half_width_mm, or split the scan into several plans")

    def n_points(self) -> int:
        """How many points the plan expands to (levels x angles x raster columns; a sweep's:
        turns x one every step_mm around the bounding cylinder, for a level beam: one that
        dips or climbs adds a turn or so, sweep.sweep_turns)."""
        if self.mode == "sweep":  # as sweep.sweep_points
            from dmdsm.marlin_patch import load_machine

            m = load_machine()
            span = max(self.levels_mm) - min(self.levels_mm)
            rings = max(math.ceil(span / self.step_mm - 1e-9), 1)
            return rings * sum(waveforms_per_turn(self, m.max_feedrate[m.axis("A")], o)
                               for o in self.offsets_mm)
        columns = math.floor(2 * self.half_width_mm / self.step_mm + 1e-9) + 1
        return len(self.levels_mm) * len(self.angles_deg) * columns

    def to_toml(self) -> str:
        """The plan as TOML text (what load_plan reads; stored in every scan file)."""
        d = asdict(self)

        def val(v: object) -> str:
            if isinstance(v, str):
                return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
            if isinstance(v, list):
                return "[" + ", ".join(val(x) for x in v) + "]"
            return repr(float(v)) if isinstance(v, float) else str(v)

        sample = ("object_id", "material", "notes")
        obj = ("radius_mm", "height_mm", "turntable_radius_mm")
        out = ["[sample]"] + [f"{k} = {val(d[k])}" for k in sample]
        out += ["", "[object]"] + [f"{k} = {val(d[k])}" for k in obj]
        step_only = ("mode", "laser_hz") if self.mode == "step" else ()  # same ids as before
        if self.mode != "auto":
            step_only += ("first_look_step_mm", "max_incidence_deg", "max_angles",
                          "rescan_budget_s")
        if self.offsets_mm == [0.0]:  # the plain sweep's text (and id) as before offsets
            step_only += ("offsets_mm",)
        out += ["", "[scan]"] + [f"{k} = {val(v)}" for k, v in d.items()
                                 if k not in sample + obj + step_only]
        return "\n".join(out) + "\n"

    def hash(self) -> str:
        """sha256 of the plan text: the identity used to resume."""
        return hashlib.sha256(self.to_toml().encode()).hexdigest()

    def depth_gate_mm(self) -> tuple[float, float]:
        """(lo, hi) beam distances (mm) where echoes are searched: from the standoff less the
        margin (at least 0.5) to the far side of the bounding cylinder plus the margin."""
        return (max(self.standoff_mm - self.depth_margin_mm, 0.5),
                self.standoff_mm + 2 * self.radius_mm + self.depth_margin_mm)


def table_speed_deg_s(plan: ScanPlan, a_max_deg_s: float, offset_mm: float = 0.0) -> float:
    """The table's speed (deg/s) in a sweep's pass offset_mm across from the axis:
    consecutive waveforms step_mm apart on the bounding cylinder, at most the table's maximum
    feed rate (deg/s), and slow enough that a flat face's distance along a beam that far off
    the axis (changing by offset_mm per radian, head on) changes by at most SWEEP_SMEAR_MM over
    one waveform's shots (an averaged pulse smeared over more depth ranges worse: the tissue
    box's head-on OA points at 90 deg/s were 0.056 mm off at 0.14 mm of change, 0.18 at
    0.99)."""
    w = plan.step_mm / plan.radius_mm  # rad per waveform
    if offset_mm:
        w = min(w, SWEEP_SMEAR_MM / abs(float(offset_mm)))
    return min(math.degrees(w * plan.laser_hz / plan.average), a_max_deg_s)


def waveforms_per_turn(plan: ScanPlan, a_max_deg_s: float, offset_mm: float = 0.0) -> int:
    """The waveforms the laser gives in one 360 deg turn of a sweep's pass offset_mm across
    from the axis, at its speed (table_speed_deg_s; the table at most a_max_deg_s)."""
    speed = table_speed_deg_s(plan, a_max_deg_s, offset_mm)
    return max(int(round(360.0 / speed * plan.laser_hz / plan.average)), 1)


AUTO_SPACING_MM = 2.0  # an auto plan's levels apart (the coverage target's spacing)
SWEEP_SMEAR_MM = 0.3   # a sweep's waveform: a flat face's distance changes this much at most
AUTO_LOWEST_MM = 4.5   # its lowest level: the turntable's keep-out ends 2 mm above the table
FLY_AVERAGE = 12  # shots per fly waveform: 12 at 1 kHz, 2 mm apart = 167 mm/s (docs/scanning.md)
# an auto scan's: 24, so 83 mm/s: its lines are short, and at 167 mm/s the run-up and
# run-out (v^2 / 2a = 40 mm each at 350 mm/s^2) would take most of every line's time
AUTO_AVERAGE = 24
AUTO_FEED_MM_MIN = 9000.0  # its moves between lines: 150 mm/s (Z and A at their own limits)


US_ONLY_MATERIALS = ("glass", "steel")  # no OA pulse: the laser is reflected, not absorbed
OA_ONLY_MATERIALS = ("foam",)           # no US echo back: the foam soaks the sound up
# both: an OA pulse wherever a US echo comes back (US within ~15 deg of head on, OA to 30-60)
BOTH_MATERIALS = ("aluminium", "plastic", "paper", "apple", "graphite")


def modality_for(material: str) -> str:
    """The modality an object of this material answers in: "us" for glass and steel (no OA
    pulse), "oa" for foam (no US echo), "both" for any other (or none given). A "both"
    plan of a one-modality object hears lone pulses it cannot read (host/ranging/point.py)."""
    m = material.strip().lower()
    return "us" if m in US_ONLY_MATERIALS else "oa" if m in OA_ONLY_MATERIALS else "both"


def plan_for_size(object_id: str, size_mm: tuple[float, float, float], round_: bool,
                  material: str = "", mode: str = "step", modality: str | None = None,
                  reach_mm: float | None = None) -> ScanPlan:
    """A first plan for an object of width x depth x height (mm) centred on the table: its
    bounding cylinder (+1 mm; a box's from its diagonal, or reach_mm: the farthest any part
    of it is from the table axis, for an object not centred by its footprint, such as a mug
    centred by its body), one level at half its height (at most 40 mm), four angles, the
    middle 70 % of its width; every 4 mm step and shoot, every 2 mm fly; the modality given,
    else the material's (modality_for); a sweep of an object that is not round in passes
    across the beam, one where they would pass the plan's point limit: a box (centred by
    its footprint) in as many as reach.box_passes gives, the beam through the middles of
    equal strips of its widest side, its standoff brought in where its nearest faces would
    be out of the sensor's reach head on (a 120 x 60 mm box: eight strips, 3 mm); one given a
    reach_mm (a round body with a handle, met head on only through its axis) in three, the
    beam through the axis and a quarter of the width to either side. Edit the file for
    more levels or a finer step (docs/scanning.md)."""
    modality = modality_for(material) if modality is None else modality
    w, d, h = (float(x) for x in size_mm)
    if not (w > 0 and d > 0 and h > 0) or not all(map(math.isfinite, (w, d, h))):
        raise PlanError(f"the size must be three positive numbers in mm (got {w:g} {d:g} "
                        f"{h:g})")
    radius = max(w, d) / 2 if round_ else math.hypot(w, d) / 2
    if reach_mm is not None:
        reach = float(reach_mm)
        if not math.isfinite(reach):
            raise PlanError(f"the reach must be a finite number of mm from the table axis "
                            f"(got {reach:g})")
        # whatever the axis, one end of the object's widest side is half its width from it
        if reach < max(w, d) / 2:
            raise PlanError(f"the reach ({reach:g} mm from the table axis) is less than half "
                            f"the object's width or depth ({max(w, d) / 2:g} mm): measure "
                            f"from the axis to the object's farthest point")
        radius = reach
    mm = lambda x: round(float(x), 1)  # noqa: E731 (a plan gives sizes to 0.1 mm)
    levels = [mm(min(0.5 * h, 40.0))]
    if mode in ("auto", "sweep"):  # every 2 mm over the height (the coverage spacing)
        levels = [mm(z) for z in np.arange(AUTO_LOWEST_MM, h - 0.5, AUTO_SPACING_MM)] or [
            mm(max(h / 2, AUTO_LOWEST_MM))]
    plan = ScanPlan(object_id, material=material, radius_mm=mm(radius + 1.0), height_mm=mm(h),
                    levels_mm=levels, angles_deg=[0.0, 90.0, 180.0, 270.0],
                    half_width_mm=max(mm(0.35 * w), 0.1),
                    step_mm=AUTO_SPACING_MM if mode == "sweep" else  # the rings' pitch
                    min(4.0 if mode == "step" else 2.0, 2 * max(mm(0.35 * w), 0.1)),
                    modality=modality, mode=mode,
                    **({"average": FLY_AVERAGE} if mode in ("fly", "sweep") else
                       {"average": AUTO_AVERAGE, "feed_mm_min": AUTO_FEED_MM_MIN}
                       if mode == "auto" else {}),
                    **({"feed_mm_min": AUTO_FEED_MM_MIN} if mode == "sweep" else {}))
    if mode == "sweep" and not round_:
        side = max(w, d)
        if reach_mm is None:  # a box: its strips, in order (one move across a pass)
            plan.offsets_mm, plan.standoff_mm, _ = box_passes(
                w, d, plan.radius_mm, plan.standoff_mm,
                ("oa", "us") if modality == "both" else (modality,), AUTO_SPACING_MM,
                MAX_OFFSETS)
        else:
            quarter = mm(min(side / 4, 0.9 * plan.radius_mm))
            plan.offsets_mm = [0.0, quarter, -quarter]
        try:
            plan.validate()
        except PlanError as e:  # the passes of a tall object over the point limit: one
            plan.notes = (f"one pass, through the axis, not {len(plan.offsets_mm)}: "
                          f"{str(e).split(':')[0]} with them; scan the height in several "
                          f"plans (levels_mm) for them")
            plan.offsets_mm = [0.0]
    plan.validate()
    return plan


def point_ranger(plan: ScanPlan, setup: RangingSetup, n_samples: int, tick_hz: float
                 ) -> PointRanger:
    """The ranger of this plan's waveforms (n_samples each, trigger phases in ticks at
    tick_hz): its modality, gated to its depth range (ScanPlan.depth_gate_mm); a sweep of
    a material that answers in both reads a lone pulse as OA where its window allows (its
    path is fixed by the plan: no reading moves the keep-out, as an auto scan's outline
    does, where a US echo read as OA would put the surface twice as far); in any mode such
    a plan reads no lone pulse as US (its OA pulse would be there: it is OA from twice as
    far)."""
    both = plan.modality == "both" and plan.material.strip().lower() in BOTH_MATERIALS
    return PointRanger(setup, n_samples, tick_hz, plan.modality, plan.depth_gate_mm(),
                       answers_both=both, lone_is_oa=both and plan.mode == "sweep")


MAX_POINTS = 200_000  # ~4 h of step and shoot; bounds the memory and time of a plan's check
MAX_SWEEP_POINTS = 400_000  # a sweep's (~100 min at 66 waveforms/s; checked turn by turn)


def _sensor_limits() -> dict[str, tuple[int, int]]:
    """samples and average: the ranges of set_config's n_samples and n_average."""
    from dmdsm.protocol import load_spec

    f = {x.name: x for x in load_spec().by_name["set_config"].fields}
    return {"samples": f["n_samples"].allowed(), "average": f["n_average"].allowed()}


MAX_PLAN_BYTES = 1 << 20  # a plan file's size


def load_plan(path: Path, **overrides: object) -> ScanPlan:
    """Read a plan TOML ([sample], [object], [scan]); flags given as overrides win."""
    try:
        with open(path, "rb") as f:
            data = f.read(MAX_PLAN_BYTES + 1)
        if len(data) > MAX_PLAN_BYTES:
            raise PlanError(f"{path} is larger than {MAX_PLAN_BYTES >> 10} KiB: a plan is a "
                            f"short TOML file (docs/scanning.md); is it the right file?")
        doc = tomllib.loads(data.decode("utf-8"))
    except OSError as e:
        raise PlanError(f"cannot read plan {path}: {e.strerror}") from None
    except UnicodeDecodeError:
        raise PlanError(f"{path} is not UTF-8 text: save the plan as UTF-8") from None
    except tomllib.TOMLDecodeError as e:
        raise PlanError(f"{path} is not valid TOML: {e}") from None
    except RecursionError:  # [[[[... or {a={a=... nested thousands deep
        raise PlanError(f"{path} nests arrays or tables too deeply for a plan: give "
                        f"[sample] and [scan] tables of plain values") from None
    flat: dict[str, object] = {}
    for section in ("sample", "object", "scan"):
        flat.update(doc.get(section, {}))
    known = set(ScanPlan.__dataclass_fields__)
    unknown = sorted(set(flat) - known)
    if unknown:
        raise PlanError(f"{path}: unknown key(s) {', '.join(unknown)} (see docs/scanning.md)")
    flat.update({k: v for k, v in overrides.items() if v is not None})
    if "object_id" not in flat:
        raise PlanError(f"{path}: [sample] object_id is required")
    if "levels_mm" not in flat:
        raise PlanError(f"{path}: [scan] levels_mm is required (the sensor heights above the "
                        f"table, mm, e.g. levels_mm = [12.0, 24.0])")
    for key, unit, example in (("levels_mm", "mm", "[12.0, 24.0]"),
                               ("angles_deg", "deg", "[0.0, 90.0, 180.0, 270.0]"),
                               ("offsets_mm", "mm", "[0.0, 12.0, -12.0]")):
        value = flat.get(key, [])
        if not isinstance(value, list) or not all(
                isinstance(x, (int, float)) and not isinstance(x, bool) for x in value):
            raise PlanError(f"{path}: [scan] {key} must be a list of numbers in {unit}, "
                            f"e.g. {key} = {example} (got {value!r:.40})")
    for key, value in flat.items():  # the kind each key takes, named before any board opens
        kind = ScanPlan.__dataclass_fields__[key].type
        number = isinstance(value, (int, float)) and not isinstance(value, bool)
        if kind == "float" and not number:
            raise PlanError(f"{path}: {key} must be a number (got {value!r:.40}): write it "
                            f"without quotes, e.g. {key} = 2.0")
        if kind == "int" and not (number and float(value).is_integer()):
            raise PlanError(f"{path}: {key} must be a whole number (got {value!r:.40})")
        if kind == "str" and not isinstance(value, str):
            raise PlanError(f"{path}: {key} must be text in quotes (got {value!r:.40})")
        if kind == "int":
            flat[key] = int(value)
    try:
        plan = ScanPlan(**flat)
        plan.levels_mm = [float(x) for x in plan.levels_mm]
        plan.angles_deg = [float(x) for x in plan.angles_deg]
        plan.offsets_mm = [float(x) for x in plan.offsets_mm]
    except (TypeError, ValueError) as e:
        raise PlanError(f"{path}: {e}") from None
    plan.validate()
    return plan


@dataclass
class Point:
    """One planned measurement: stage X, Y, Z (mm), table angle (deg) and its indices."""

    index: int
    x: float
    y: float
    z: float
    theta_deg: float
    level: int
    column: int
    angle_index: int
    line: int = -1  # an auto scan's line number (-1: lines by angle and level)
    expect_mm: float = math.nan  # an auto follow line's: the beam distance the outline predicts
    # (near, far) beam distances (mm) where the object can be along the beam, NaN where
    # unknown (the ranger reads lone pulses by it): a first look's, where the beam crosses
    # the bounding cylinder; an auto follow line's, from the outline's keep-out to there
    window_mm: tuple[float, float] = (math.nan, math.nan)


def expand(plan: ScanPlan, v: np.ndarray, X_R: np.ndarray) -> list[Point]:
    """The plan's points in execution order, for beam direction v and table centre X_R."""
    v = np.asarray(v, float) / np.linalg.norm(v)
    y = float(X_R[1] - (plan.radius_mm + plan.standoff_mm) * v[1])
    xs = np.arange(-plan.half_width_mm, plan.half_width_mm + 1e-9, plan.step_mm)
    pts: list[Point] = []
    for ai, th in enumerate(plan.angles_deg):
        for li, h in enumerate(plan.levels_mm):
            cols = range(len(xs)) if (ai * len(plan.levels_mm) + li) % 2 == 0 else \
                range(len(xs) - 1, -1, -1)
            for ci in cols:
                pts.append(Point(len(pts), float(X_R[0] + xs[ci]), y, float(X_R[2] + h),
                                 float(th), li, ci, ai))
    return pts


def keep_outs(plan: ScanPlan, n: np.ndarray, X_R: np.ndarray) -> list[KeepOut]:
    """The object's bounding cylinder and the turntable (its disc and the body below it)."""
    n = np.asarray(n, float) / np.linalg.norm(n)
    below = 1000.0
    return [KeepOut(np.asarray(X_R, float), n, plan.radius_mm, plan.height_mm),
            KeepOut(np.asarray(X_R, float) - below * n, n, plan.turntable_radius_mm, below)]


def check_plan(points: list[Point], start: np.ndarray | None, limits: MachineLimits,
               zones: list[KeepOut]) -> None:
    """Raise UnsafeMove (naming the point) if any move of the scan, from `start` (the stage
    now; None: only between the points) through every point, leaves the envelope or crosses
    a keep-out."""
    if not points:
        return
    targets = [np.array([p.x, p.y, p.z]) for p in points]
    labels = [f"point {p.index}" for p in points]
    check_path(targets, labels, start, limits, zones)


def check_path(targets: list[np.ndarray], labels: list[str], start: np.ndarray | None,
               limits: MachineLimits, zones: list[KeepOut]) -> None:
    """Raise UnsafeMove (naming the label) if a straight move through the targets (X, Y, Z
    mm), from `start` (None: from the first target), leaves the envelope or crosses a
    keep-out."""
    targets, labels = list(targets), list(labels)
    if start is None:
        here = targets[0]
    else:  # the approach: along Y into the front plane first, then X and Z
        here = np.asarray(start, float)
        targets.insert(0, np.array([here[0], targets[0][1], here[2]]))
        labels.insert(0, "the approach to the front plane")
    for label, t in zip(labels, targets):
        for zone in zones:
            try:
                check_move(here, t, limits, zone)
            except UnsafeMove as e:
                raise UnsafeMove(f"scan plan refused before moving: {label} "
                                 f"(X{t[0]:.6g} Y{t[1]:.6g} Z{t[2]:.6g}): {e}") from None
        here = t
