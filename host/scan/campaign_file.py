"""Campaign files: the list of objects `dmdsm campaign` scans into one database, read with the
checks a hostile file needs (pure: no port is opened, nothing is written).

The format (TOML, UTF-8, at most MAX_BYTES)::

    [campaign]                      # optional, every key optional
    classifier = "household.joblib" # a `dmdsm classify train` model, relative to this file's
                                    # folder: each scan's material is checked against it
    mode = "auto"                   # the scan mode: auto (default), step, fly or sweep
    modality = "both"               # both (default), oa or us

    [[object]]                      # one table per object, scanned in this order
    id = "soda_can"                 # the object id (as a plan's sample.object_id)
    material = "aluminium"          # the material declared (compared with the classifier's)
    size_mm = [66.0, 66.0, 122.0]   # width, depth, height in mm (its keep-out is made of it)
    round = true                    # round in plan (a can, a cup); default false: a box,
                                    # whose bounding cylinder is the diagonal's
    reach_mm = 73.5                 # optional: the farthest any part is from the table axis
                                    # (mm), for an object not centred by its footprint (a mug
                                    # centred by its body: to the handle's end)
    notes = "empty, ring pull away" # optional, kept in the scan file
    scene = "soda_can"              # optional: the emulator's scene to mount (default: id)
    levels_mm = [40.0, 42.0]        # optional: only these heights (mm above the table)
                                    # instead of the plan's (auto: every 2 mm)
    modality = "us"                 # optional: this object's, instead of [campaign]'s (glass
                                    # and steel give no OA: "us"; foam no US echo: "oa")

Each object's scan plan is `plan_for_size(id, size_mm, round, material, mode, modality,
reach_mm)`
(host/scan/plan.py) with its notes and levels; it is checked here, so a size out of the
machine's reach or an id that cannot name a scan is refused before anything moves. Every
refusal is one line naming the object, the key and what to write instead.
"""

from __future__ import annotations

import math
import tomllib
import unicodedata
from dataclasses import dataclass, field
from pathlib import Path

from ..files import not_utf8, one_line, shown
from .plan import MODALITIES, MODES, PlanError, ScanPlan, plan_for_size

MAX_BYTES = 1 << 20     # a campaign file's size
MAX_OBJECTS = 1000      # objects in one campaign
MAX_TEXT = 1000         # characters of a notes, material or path value
MAX_LEVELS = 200        # levels_mm values of one object
MAX_ID = 90             # an id's characters: the scan id is ID-<8 hex digits>, at most 100
CAMPAIGN_KEYS = ("classifier", "mode", "modality")
OBJECT_KEYS = ("id", "material", "size_mm", "round", "notes", "scene", "levels_mm", "modality",
               "reach_mm")
EXAMPLE = ('[[object]]\\nid = "soda_can"\\nmaterial = "aluminium"\\n'
           'size_mm = [66.0, 66.0, 122.0]\\nround = true')


class CampaignError(ValueError):
    """A campaign file that cannot be run; str() is one line naming what to change."""


@dataclass(frozen=True)
class CampaignObject:
    """One object of a campaign: what the operator places and how its plan is made."""

    object_id: str
    material: str
    size_mm: tuple[float, float, float]
    round: bool = False
    notes: str = ""
    scene: str = ""  # the emulator's scene; "" in the file means the id (see `scene_name`)
    levels_mm: tuple[float, ...] = ()  # () : the plan's own levels
    modality: str = ""  # "": the campaign's
    reach_mm: float | None = None  # farthest from the table axis (mm); None: from size_mm

    @property
    def scene_name(self) -> str:
        """The scene the emulator mounts for this object: `scene`, else the id."""
        return self.scene or self.object_id


@dataclass(frozen=True)
class Campaign:
    """A parsed campaign file: its objects in order and the settings of [campaign]."""

    objects: tuple[CampaignObject, ...]
    classifier: Path | None = None  # resolved against the file's folder
    mode: str = "auto"
    modality: str = "both"
    source: Path | None = field(default=None, compare=False)

    def plan(self, obj: CampaignObject) -> ScanPlan:
        """The object's scan plan (PlanError if it cannot be made: load_campaign has
        checked every object's)."""
        plan = plan_for_size(obj.object_id, obj.size_mm, obj.round, obj.material,
                             mode=self.mode, modality=obj.modality or self.modality,
                             reach_mm=obj.reach_mm)
        plan.notes = obj.notes
        if obj.levels_mm:
            plan.levels_mm = [float(z) for z in obj.levels_mm]
        plan.validate()
        return plan

    def to_toml(self) -> str:
        """The campaign as a file load_campaign reads back to an equal Campaign (the
        classifier written as its resolved path)."""
        out = ["[campaign]", f"mode = {_str(self.mode)}", f"modality = {_str(self.modality)}"]
        if self.classifier is not None:
            out.append(f"classifier = {_str(str(self.classifier))}")
        for o in self.objects:
            out += ["", "[[object]]", f"id = {_str(o.object_id)}",
                    f"material = {_str(o.material)}",
                    "size_mm = [" + ", ".join(repr(float(x)) for x in o.size_mm) + "]",
                    f"round = {'true' if o.round else 'false'}"]
            if o.notes:
                out.append(f"notes = {_str(o.notes)}")
            if o.scene:
                out.append(f"scene = {_str(o.scene)}")
            if o.levels_mm:
                out.append("levels_mm = [" + ", ".join(repr(float(z)) for z in o.levels_mm)
                           + "]")
            if o.modality:
                out.append(f"modality = {_str(o.modality)}")
            if o.reach_mm is not None:
                out.append(f"reach_mm = {float(o.reach_mm)!r}")
        return "\n".join(out) + "\n"


def _str(s: str) -> str:
    """A TOML basic string: quotes, backslashes and control characters escaped."""
    return '"' + "".join(
        "\\\\" if c == "\\" else '\\"' if c == '"' else
        f"\\u{ord(c):04x}" if unicodedata.category(c) == "Cc" else c for c in s) + '"'


def load_campaign(path: Path) -> Campaign:
    """Read and check a campaign file; CampaignError (one line) on anything wrong."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            data = f.read(MAX_BYTES + 1)
    except IsADirectoryError:
        raise CampaignError(f"{path} is a folder: give the campaign's TOML file") from None
    except OSError as e:
        raise CampaignError(f"cannot read campaign file {path}: {e.strerror}") from None
    if len(data) > MAX_BYTES:
        raise CampaignError(f"{path} is larger than {MAX_BYTES // 1024} KiB: a campaign lists "
                            f"at most {MAX_OBJECTS} objects; split it into several files")
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        raise CampaignError(not_utf8(path, "campaign file")) from None
    return parse_campaign(text, path)


def parse_campaign(text: str, path: Path = Path("campaign.toml")) -> Campaign:
    """Check a campaign file's text (path: for the messages and the classifier's folder)."""
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise CampaignError(f"{path} is not valid TOML: {one_line(str(e), 160)}") from None
    except RecursionError:  # [[[[... or {a={a=... a million deep
        raise CampaignError(f"{path} nests arrays or tables too deeply for a campaign file: "
                            f"give [campaign] and [[object]] tables of plain values") from None
    where = str(path)
    unknown = sorted(set(doc) - {"campaign", "object"})
    if unknown:
        raise CampaignError(f"{where}: unknown key {_key(unknown[0])} at the top: a campaign "
                            f"file holds [campaign] and [[object]] tables (docs/scanning.md)")
    settings = doc.get("campaign", {})
    if not isinstance(settings, dict):
        raise CampaignError(f"{where}: campaign must be a table: write [campaign] on a line "
                            f"of its own, then its keys")
    bad = sorted(set(settings) - set(CAMPAIGN_KEYS))
    if bad:
        raise CampaignError(f"{where}: unknown key {_key(bad[0])} in [campaign] (known: "
                            f"{', '.join(CAMPAIGN_KEYS)})")
    mode = _choice(settings, "mode", MODES, "auto", f"{where}: [campaign]")
    modality = _choice(settings, "modality", MODALITIES, "both", f"{where}: [campaign]")
    classifier = None
    if "classifier" in settings:
        text_path = _text(settings["classifier"], f"{where}: [campaign] classifier",
                          "a model file's path", required=True)
        if "\x00" in text_path:
            raise CampaignError(f"{where}: [campaign] classifier holds a NUL character: give "
                                f"the model file's path")
        classifier = Path(path).parent / text_path
    objects = doc.get("object")
    if objects is None or objects == []:
        raise CampaignError(f"{where}: no objects: add one [[object]] table per object, e.g. "
                            f"{EXAMPLE}")
    if isinstance(objects, dict):
        raise CampaignError(f"{where}: write [[object]] (two brackets) above each object, not "
                            f"[object]")
    if not isinstance(objects, list) or not all(isinstance(o, dict) for o in objects):
        raise CampaignError(f"{where}: object must be a list of tables: write [[object]] "
                            f"above each object's keys")
    if len(objects) > MAX_OBJECTS:
        raise CampaignError(f"{where}: {len(objects)} objects, at most {MAX_OBJECTS}: split "
                            f"the campaign into several files")
    out: list[CampaignObject] = []
    seen: dict[str, int] = {}
    campaign = Campaign((), classifier, mode, modality, path)
    for i, raw in enumerate(objects, 1):
        obj = _object(raw, f"{where}: object {i}")
        if obj.object_id in seen:
            raise CampaignError(f"{where}: object {i}: id {shown(obj.object_id)} is object "
                                f"{seen[obj.object_id]}'s too: give each object its own id "
                                f"(e.g. {shown(obj.object_id)}_2)")
        seen[obj.object_id] = i
        try:
            campaign.plan(obj)
        except PlanError as e:
            raise CampaignError(f"{where}: object {i} ({shown(obj.object_id)}): {e}") from None
        out.append(obj)
    return Campaign(tuple(out), classifier, mode, modality, path)


def _key(k: object) -> str:
    return repr(one_line(str(k), 60))


def _choice(table: dict, key: str, allowed: tuple[str, ...], default: str, where: str) -> str:
    if key not in table:
        return default
    v = table[key]
    if not isinstance(v, str) or v not in allowed:
        raise CampaignError(f"{where} {key} must be one of "
                            f"{', '.join(repr(a) for a in allowed)} in quotes (got "
                            f"{one_line(repr(v), 40)})")
    return v


def _text(v: object, what: str, example: str, required: bool = False) -> str:
    if not isinstance(v, str):
        raise CampaignError(f"{what} must be text in quotes, e.g. {example} (got "
                            f"{one_line(repr(v), 40)})")
    if required and not v.strip():
        raise CampaignError(f"{what} is empty: give {example}")
    if len(v) > MAX_TEXT:
        raise CampaignError(f"{what} is {len(v)} characters long, at most {MAX_TEXT}")
    return v


def _printable(v: str, what: str) -> str:
    if not v.isprintable():
        raise CampaignError(f"{what} = {shown(v)!r} holds a control or other unprintable "
                            f"character: give printable text")
    return v


def _number(v: object, what: str, example: str) -> float:
    if isinstance(v, str):
        raise CampaignError(f"{what} is text ({one_line(repr(v), 30)}): write the number "
                            f"without quotes, e.g. {example}")
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise CampaignError(f"{what} must be a number, e.g. {example} (got "
                            f"{one_line(repr(v), 30)})")
    x = float(v)
    if not math.isfinite(x) or not x > 0:
        raise CampaignError(f"{what} must be a positive finite number of mm (got {x:g})")
    return x


def _reach() -> float:
    """The machine's longest travel (mm): no object is larger."""
    from dmdsm.marlin_patch import load_machine

    m = load_machine()
    return max(hi - lo for lo, hi in zip(m.min_pos[:3], m.max_pos[:3]))


def _object(raw: dict, where: str) -> CampaignObject:
    """One [[object]] table, checked key by key (before the plan's checks)."""
    if "id" in raw:
        oid = _text(raw["id"], f"{where}: id", 'id = "soda_can"', required=True)
        where = f"{where} ({shown(oid)[:60]})"
    bad = sorted(set(raw) - set(OBJECT_KEYS))
    if bad:
        raise CampaignError(f"{where}: unknown key {_key(bad[0])} (known: "
                            f"{', '.join(OBJECT_KEYS)})")
    for key, example in (("id", 'id = "soda_can"'), ("material", 'material = "aluminium"'),
                         ("size_mm", "size_mm = [66.0, 66.0, 122.0]")):
        if key not in raw:
            raise CampaignError(f"{where}: {key} is missing: add e.g. {example}")
    oid = _printable(raw["id"], f"{where}: id")
    if any(c in oid for c in "/\\ \t") or oid.startswith(".") or ".." in oid or \
            len(oid) > MAX_ID or not all(c.isascii() and (c.isalnum() or c in "._-")
                                         for c in oid):
        raise CampaignError(f"{where}: id {shown(oid)!r} cannot name a scan: use letters, "
                            f"digits, '.', '_' and '-' (at most {MAX_ID}, not starting with "
                            f"'.', no '..')")
    material = _printable(_text(raw["material"], f"{where}: material",
                                'material = "aluminium"', required=True), f"{where}: material")
    size = raw["size_mm"]
    if not isinstance(size, list) or len(size) != 3:
        raise CampaignError(f"{where}: size_mm must be three numbers in mm (width, depth, "
                            f"height), e.g. size_mm = [66.0, 66.0, 122.0] (got "
                            f"{one_line(repr(size), 40)})")
    size_mm = tuple(_number(x, f"{where}: size_mm[{k}]", "size_mm = [66.0, 66.0, 122.0]")
                    for k, x in enumerate(size))
    reach = _reach()
    for k, x in enumerate(size_mm):  # before the plan: a huge height makes a huge plan
        if x > reach:
            raise CampaignError(f"{where}: size_mm[{k}] = {x:.6g} mm is more than the "
                                f"machine's longest travel ({reach:g} mm): give the object's "
                                f"size in mm")
    round_ = raw.get("round", False)
    if not isinstance(round_, bool):
        raise CampaignError(f"{where}: round must be true or false, without quotes (got "
                            f"{one_line(repr(round_), 30)})")
    notes = _text(raw.get("notes", ""), f"{where}: notes", 'notes = "empty, lid off"')
    scene = ""
    if "scene" in raw:
        scene = _printable(_text(raw["scene"], f"{where}: scene", 'scene = "soda_can"',
                                 required=True), f"{where}: scene")
    levels: tuple[float, ...] = ()
    if "levels_mm" in raw:
        lv = raw["levels_mm"]
        if not isinstance(lv, list) or not lv or len(lv) > MAX_LEVELS:
            raise CampaignError(f"{where}: levels_mm must be a list of 1 to {MAX_LEVELS} "
                                f"heights in mm, e.g. levels_mm = [40.0, 42.0] (got "
                                f"{one_line(repr(lv), 40)})")
        levels = tuple(_number(z, f"{where}: levels_mm[{k}]", "levels_mm = [40.0, 42.0]")
                       for k, z in enumerate(lv))
        top = max(levels)
        if top > size_mm[2]:
            raise CampaignError(f"{where}: levels_mm holds {top:g} mm, above the object's "
                                f"height ({size_mm[2]:g} mm, size_mm[2]): give heights on it")
    modality = _choice(raw, "modality", MODALITIES, "", f"{where}:") if "modality" in raw \
        else ""
    reach_mm = None
    if "reach_mm" in raw:
        reach_mm = _number(raw["reach_mm"], f"{where}: reach_mm", "reach_mm = 73.5")
        if reach_mm > reach:
            raise CampaignError(f"{where}: reach_mm = {reach_mm:.6g} mm is more than the "
                                f"machine's longest travel ({reach:g} mm): give the farthest "
                                f"point's distance from the table axis in mm")
    return CampaignObject(oid, material, size_mm, round_, notes, scene, levels, modality,
                          reach_mm)
