"""`dmdsm campaign`: a database of many objects from a list (host/scan/campaign_file.py): each
object placed (mounted, on the emulator), scanned in auto mode, modelled and classified, with
one progress bar over the campaign and one per scan, resumable at any object, and a table at
the end (docs/scanning.md, "Campaigns: a database of many objects")."""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from ..calibration.result import load_calibration
from ..classify.materials import ClassifyError
from ..files import OutputError, one_line, shown
from ..links.config import load_config, resolve_port
from ..links.safety import UnsafeMove
from ..links.stage import StageStopped
from ..links.transport import LinkError
from ..ranging.calibrate import RangingSetup
from ..scan.campaign_file import Campaign, CampaignError, CampaignObject, load_campaign
from ..scan.catalogue import CatalogueError
from ..scan.plan import PlanError, ScanPlan
from ..scan.scanfile import ScanFileError, ScanWriter, read_scan
from ..scan.session import ScanRun, checked_points, finished_scan, run_plan
from .errors import CliError
from .options import add_ports

log = logging.getLogger("dmdsm.campaign")

# what makes one object fail (a row with its reason) while the campaign goes on
OBJECT_ERRORS = (ScanFileError, UnsafeMove, PlanError, ClassifyError, OutputError,
                 CatalogueError, ValueError, OSError)


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register `campaign`."""
    p = sub.add_parser("campaign", help="scan a list of objects into one database: place, "
                       "auto scan, model and classify each; resumable")
    p.add_argument("campaign", type=Path, metavar="CAMPAIGN.toml",
                   help="the objects (id, material, size_mm, notes; docs/scanning.md)")
    p.add_argument("--db", type=Path, required=True,
                   help="database folder (created if missing)")
    add_ports(p)
    p.add_argument("--calibration", type=Path, default=Path("calibration.toml"),
                   help="scanner calibration from `dmdsm calibrate` (default ./calibration.toml)")
    p.add_argument("--ranging", type=Path, default=Path("ranging.json"),
                   help="ranging calibration from `dmdsm calibrate-range` (default ./ranging.json)")
    p.add_argument("--classifier", type=Path,
                   help="a `dmdsm classify train` model (instead of the file's [campaign] "
                        "classifier): each object's material is checked against it")
    p.add_argument("--yes", action="store_true",
                   help="do not wait for Enter before each object (for scripts)")
    p.add_argument("--no-home", action="store_true",
                   help="the stage is homed and clear of every object: do not home it "
                        "before each scan")
    p.add_argument("--json", action="store_true", help="print the table as JSON")
    p.set_defaults(func=cmd_campaign)


@dataclass
class Row:
    """One object's line of the final table."""

    object_id: str
    material: str
    status: str = "not reached"  # scanned, done before, failed, skipped, not reached
    reason: str = ""
    scan_id: str = ""
    points: int = 0
    coverage: dict = field(default_factory=dict)   # modality -> share (auto scans)
    model_version: int = 0
    vertices: int = 0
    supported_share: float | None = None
    sigma_median_mm: float | None = None
    verdict: dict | None = None  # material, confidence, right; None: no classifier
    scan_s: float = 0.0
    total_s: float = 0.0


class Models:
    """The 3D model API the campaign uses (host/model); a test may give another."""

    def current(self, db: Path, object_id: str) -> Any | None:
        """The object's latest model if there is one and it is not stale, else None."""
        from ..model.store import ModelError, load_object_model, staleness

        try:
            model = load_object_model(db, object_id)
        except ModelError:
            return None
        return model if staleness(db, model) == ["ok"] else None

    def build(self, db: Path, object_id: str, classifier: Path | None) -> Any:
        """Build and write a new model version (ModelError, a ValueError, if it cannot)."""
        from ..model.build import build_object_model
        from ..model.store import write_model

        model = build_object_model(db, object_id, classifier=classifier)
        write_model(db, model)
        return model


class Stop(Exception):
    """The operator typed q (or stdin ended): the campaign stops before this object."""


def emulator_scene_file(port: str) -> Path | None:
    """DIR/scene if `port` is DIR/sensor of `dmdsm sim --link-dir DIR` (or a symbolic link
    leading to it): writing a scene's name there mounts it, as a user does by hand."""
    p = Path(port)
    for _ in range(40):
        scene = p.parent / "scene"
        if p.name == "sensor" and p.is_symlink() and scene.is_file() and \
                not scene.is_symlink():
            return scene
        if not p.is_symlink():
            return None
        target = Path(os.readlink(p))
        p = target if target.is_absolute() else p.parent / target
    return None


def mount(scene_file: Path, name: str) -> None:
    """Write the scene's name into the emulator's scene file (atomically: the emulator never
    reads half a name)."""
    tmp = scene_file.with_name(f".scene-{os.getpid()}")
    tmp.write_text(name + "\n")
    os.replace(tmp, scene_file)


def cmd_campaign(args: argparse.Namespace, models: Models | None = None) -> int:
    """Place, scan, model and classify each object of the campaign in turn; see the module."""
    models = models or Models()
    try:
        campaign = load_campaign(args.campaign)
    except CampaignError as e:
        raise CliError(str(e)) from None
    db = args.db
    if db.exists() and not db.is_dir():
        raise CliError(f"{db} is a file, not a scan database folder: name a folder (a new one "
                       f"is created)")
    classifier_path = args.classifier or campaign.classifier
    classifier = None
    if classifier_path is not None:
        from ..classify.model_file import load_model

        try:
            classifier = load_model(classifier_path)
        except ClassifyError as e:
            raise CliError(f"classifier: {e}") from None
    cal, cal_text = load_calibration(args.calibration)
    try:
        setup = RangingSetup.load(args.ranging)
    except ValueError as e:
        raise CliError(f"{e}; run `dmdsm calibrate-range` first") from None
    plans: list[ScanPlan] = []
    done: list[ScanRun | ScanFileError | None] = []
    for i, obj in enumerate(campaign.objects, 1):  # every plan's moves, before any port
        plan = campaign.plan(obj)
        try:
            checked_points(plan, cal)
        except UnsafeMove as e:
            raise CliError(f"object {i} ({shown(obj.object_id)}): {e}") from None
        try:
            done.append(finished_scan(plan, cal_text, setup, db))
        except ScanFileError as e:  # its file is damaged: that object fails, not the rest
            done.append(e)
        plans.append(plan)
    out = sys.stderr if args.json else sys.stdout
    return Run(args, campaign, plans, done, cal, cal_text, setup, classifier_path, classifier,
               models, out).go()


class Run:
    """One run of a campaign: the boards (opened when the first object needs them), the bars,
    the rows."""

    def __init__(self, args: argparse.Namespace, campaign: Campaign, plans: list[ScanPlan],
                 done: list[ScanRun | ScanFileError | None], cal: dict, cal_text: str,
                 setup: RangingSetup, classifier_path: Path | None, classifier: tuple | None,
                 models: Models, out: Any) -> None:
        self.args, self.campaign, self.plans, self.done = args, campaign, plans, done
        self.cal, self.cal_text, self.setup = cal, cal_text, setup
        self.classifier_path, self.classifier, self.models = classifier_path, classifier, models
        self.out = out
        self.rows = [Row(o.object_id, o.material) for o in campaign.objects]
        self.stack = contextlib.ExitStack()
        self.sensor = self.stage = None
        self.scene_file: Path | None = None
        self.ports_checked = False
        self.scan: dict = {}  # the scan under way: writer, planned, bar

    def say(self, text: str) -> None:
        """A line between the bars."""
        from tqdm import tqdm

        tqdm.write(text, file=self.out)
        self.out.flush()

    def go(self) -> int:
        from tqdm import tqdm

        objs = self.campaign.objects
        n = len(objs)
        self.bar = tqdm(total=n, unit="obj", desc="campaign", position=0,
                        disable=self.args.json, dynamic_ncols=True)
        i = 0
        try:
            with self.stack:  # Ctrl-C leaving it quick-stops the stage (StageClient)
                try:
                    for i, obj in enumerate(objs):
                        self.object(i, obj)
                        self.bar.update(1)
                except Stop as e:
                    self.bar.close()
                    for row in self.rows[i:]:
                        row.status, row.reason = "not reached", str(e)
                    self.say(f"campaign stopped before object {i + 1} of {n} "
                             f"({shown(objs[i].object_id)}): {e}; run the same command to "
                             f"go on")
        except (LinkError, StageStopped) as e:
            self.close_scan_bar()
            self.bar.close()
            r = self.rows[i]
            r.status, r.reason = "failed", one_line(f"the boards: {e}", 300)
            for row in self.rows[i + 1:]:
                row.status, row.reason = "not reached", "the campaign stopped"
            self.say(f"campaign stopped at object {i + 1} of {n} ({shown(objs[i].object_id)}): "
                     f"{one_line(str(e), 200)}; check the boards, then run the same command "
                     f"to go on")
        except KeyboardInterrupt:
            self.close_scan_bar()
            self.bar.close()
            w = self.scan.get("writer")
            saved = (f"; its scan {Path(w.path).stem} holds {w.n_done} of "
                     f"{self.scan['planned']} points, saved in {w.path}" if w is not None
                     else "")
            print(f"campaign stopped at object {i + 1} of {n} ({shown(objs[i].object_id)})"
                  f"{saved}; run the same command to resume there", file=sys.stderr)
            raise
        finally:
            self.bar.close()
        self.table()
        failed = [r for r in self.rows if r.status == "failed"]
        left = [r for r in self.rows if r.status in ("skipped", "not reached")]
        if failed or left:
            print(f"dmdsm: {len(failed)} of {n} objects failed"
                  + (f", {len(left)} not scanned (skipped or stopped)" if left else "")
                  + ": the same command scans them again; the others are kept",
                  file=sys.stderr)
            return 1
        return 0

    # --- one object ---------------------------------------------------------------------

    def object(self, i: int, obj: CampaignObject) -> None:
        row, plan, finished = self.rows[i], self.plans[i], self.done[i]
        name = shown(obj.object_id)
        if isinstance(finished, ScanFileError):
            row.status, row.reason = "failed", one_line(str(finished), 300)
            self.say(f"{name}: failed: {row.reason}")
            return
        model = self.models.current(self.args.db, obj.object_id) if finished else None
        if finished is not None and model is not None:
            self.fill_scan(row, finished, None)
            self.fill_model(row, model)
            row.status = "done before"
            try:
                self.classify(row, obj, finished.path, model)
            except ClassifyError as e:
                row.reason = one_line(f"classify: {e}", 300)
            self.say(f"{name}: done before (scan {finished.scan_id}, model "
                     f"v{model.version})")
            return
        t0 = time.monotonic()
        try:
            if finished is None:
                self.place(i, obj)
                t_scan = time.monotonic()
                t0 = t_scan  # the time per object leaves out the operator's wait
                run = self.run_scan(plan)
                row.scan_s = round(time.monotonic() - t_scan, 1)
                self.fill_scan(row, run, run)
            else:
                self.say(f"{name}: its scan {finished.scan_id} is complete; building its "
                         f"model")
                self.fill_scan(row, finished, None)
            self.say(f"{name}: building the model")
            try:
                model = self.models.build(self.args.db, obj.object_id, self.classifier_path)
            except ValueError as e:
                raise ValueError(f"model: {e}") from None
            self.fill_model(row, model)
            self.classify(row, obj, Path(row_path(self.args.db, row.scan_id)), model)
            row.status = "scanned"
        except Stop:
            raise
        except (LinkError, StageStopped, KeyboardInterrupt):
            row.total_s = round(time.monotonic() - t0, 1)
            raise
        except _Skip:
            row.status, row.reason = "skipped", "skipped by the operator (s)"
            self.say(f"{name}: skipped")
            return
        except OBJECT_ERRORS as e:
            self.close_scan_bar()
            row.status, row.reason = "failed", one_line(str(e), 300)
            self.say(f"{name}: failed: {row.reason}")
        row.total_s = round(time.monotonic() - t0, 1)
        if row.status == "scanned":
            self.say(f"{name}: done in {row.total_s:.0f} s: {row.points} points"
                     + (f", coverage {_coverage(row.coverage)}" if row.coverage else "")
                     + f", model v{row.model_version} {row.vertices} vertices"
                     + (f", {_verdict(row.verdict)}" if row.verdict else ""))

    def place(self, i: int, obj: CampaignObject) -> None:
        """Mount the object on the emulator, or ask the operator to place it."""
        self.open_boards()
        name = shown(obj.object_id)
        if self.scene_file is not None:
            mount(self.scene_file, obj.scene_name)
            self.say(f"{name}: mounted scene {shown(obj.scene_name)} on the emulator "
                     f"({self.scene_file})")
            return
        size = " x ".join(f"{x:g}" for x in obj.size_mm)
        what = ", ".join(x for x in (shown(obj.material), f"{size} mm",
                                     shown(obj.notes)) if x)
        self.say(f"place {name} ({what}) on the table, centred; Enter to scan, s to skip, "
                 f"q to stop")
        if self.args.yes:
            return
        line = sys.stdin.readline()
        if not line:
            raise Stop("the input ended (give --yes to run without waiting for Enter)")
        answer = line.strip().lower()
        if answer == "q":
            raise Stop("q typed")
        if answer == "s":
            raise _Skip()

    def open_boards(self) -> None:
        """Open both boards (once), and find the emulator's scene file beside the sensor's
        port; every scene the campaign mounts is checked before the first."""
        if self.sensor is not None:
            return
        from ..links.sensor import SensorClient
        from ..links.stage import StageClient

        cfg = load_config(self.args.config)
        sensor_port = resolve_port("sensor", self.args.sensor, cfg)
        stage_port = resolve_port("stage", self.args.stage, cfg)
        self.scene_file = emulator_scene_file(sensor_port)
        if self.scene_file is not None:
            from dmdsm.sim.physics.objects import SCENES

            unknown = sorted({o.scene_name for o, d in zip(self.campaign.objects, self.done)
                              if d is None and o.scene_name not in SCENES})
            if unknown:
                raise CliError(f"the emulator has no scene {shown(unknown[0])!r} (give the "
                               f"object a scene = NAME from `dmdsm sim --list-scenes`)")
        try:  # a port that does not open is the user's to fix (exit 2), as for `dmdsm scan`
            self.sensor = SensorClient(sensor_port)
            self.stack.callback(self.sensor.close)
            self.stage = self.stack.enter_context(StageClient(stage_port))
        except LinkError as e:
            raise CliError(str(e)) from None

    def run_scan(self, plan: ScanPlan) -> ScanRun:
        from tqdm import tqdm

        self.scan = {}
        name = shown(plan.object_id)

        def on_start(writer: ScanWriter, planned: int) -> None:
            self.scan.update(writer=writer, planned=planned)
            if writer.n_done:
                self.say(f"{name}: resuming {Path(writer.path).stem}: {writer.n_done} "
                         f"points done")
            self.scan["bar"] = tqdm(total=planned, initial=writer.n_done, unit="pt",
                                    desc=plan.object_id[:20], position=1, leave=False,
                                    disable=self.args.json, dynamic_ncols=True)

        def progress(done: int, total: int, timing: dict) -> None:
            bar = self.scan["bar"]
            if total != self.scan["planned"]:  # an auto scan plans its lines after its look
                self.scan["planned"] = bar.total = total
            bar.update(done - bar.n)

        self.say(f"{name}: scanning ({plan.mode}, {len(plan.levels_mm)} levels)")
        run = run_plan(self.sensor, self.stage, plan, calibration=self.cal,
                       calibration_toml=self.cal_text, setup=self.setup, db=self.args.db,
                       home=not self.args.no_home, progress=progress, on_start=on_start)
        self.close_scan_bar()
        self.scan = {}
        return run

    def close_scan_bar(self) -> None:
        if "bar" in self.scan:
            self.scan["bar"].close()

    # --- the figures of a row -----------------------------------------------------------

    def fill_scan(self, row: Row, scan: ScanRun, run: ScanRun | None) -> None:
        row.scan_id, row.points = scan.scan_id, scan.points
        cov = run.auto.get("coverage") if run is not None and run.auto else None
        if cov is None:
            try:
                entry = read_scan(scan.path, waveforms=False).entry
                cov = json.loads(entry.get("coverage") or "{}")
            except (ScanFileError, ValueError, TypeError):
                cov = {}
        row.coverage = {k: float(v) for k, v in (cov or {}).items()
                        if k in ("oa", "us") and isinstance(v, (int, float))}

    def fill_model(self, row: Row, model: Any) -> None:
        s = model.summary
        row.model_version, row.vertices = int(model.version), int(s.get("vertices", 0))
        row.supported_share = s.get("supported_share")
        row.sigma_median_mm = s.get("sigma_median_mm")

    def classify(self, row: Row, obj: CampaignObject, scan_path: Path,
                 model: Any = None) -> None:
        """The object's material: its model's, built with this classifier (the supported
        vertices, each from the clean waveforms near it), else the scan's waveforms'."""
        if self.classifier is None:
            return
        from ..classify.predict import predict_scan
        from ..model.build import model_verdict

        v = None
        if model is not None and model.params.get("classifier") == str(self.classifier_path):
            v = model_verdict(model)
        if v is None:
            v = predict_scan(self.classifier, scan_path)
        row.verdict = {"material": v["material"], "confidence": round(v["confidence"], 3),
                       "right": v["material"].strip().lower() ==
                       obj.material.strip().lower()}

    # --- the table ----------------------------------------------------------------------

    def table(self) -> None:
        if self.args.json:
            print(json.dumps({"campaign": str(self.args.campaign), "db": str(self.args.db),
                              "classifier": str(self.classifier_path)
                              if self.classifier_path else None,
                              "objects": [asdict(r) for r in self.rows]}))
            return
        head = ["object", "material", "status", "points", "coverage", "vertices",
                "supported", "sigma med", "material verdict", "time"]
        lines = [head]
        for r in self.rows:
            has_model = r.model_version > 0
            lines.append([
                shown(r.object_id), shown(r.material), r.status,
                str(r.points) if r.scan_id else "-",
                _coverage(r.coverage) or "-",
                str(r.vertices) if has_model else "-",
                f"{100 * r.supported_share:.1f} %" if has_model and
                r.supported_share is not None else "-",
                f"{r.sigma_median_mm:.3f} mm" if has_model and
                r.sigma_median_mm is not None else "-",
                _verdict(r.verdict) if r.verdict else
                ("no classifier" if self.classifier is None else "-"),
                f"{r.total_s:.0f} s" if r.status in ("scanned", "failed") and r.total_s
                else "-"])
        width = [max(len(x[k]) for x in lines) for k in range(len(head))]
        for k, x in enumerate(lines):
            print("  ".join(c.ljust(w) for c, w in zip(x, width)).rstrip())
            if k == 0:
                print("  ".join("-" * w for w in width))
        for r in self.rows:
            if r.reason and r.status != "not reached":
                print(f"{shown(r.object_id)}: {r.status}: {r.reason}")


class _Skip(Exception):
    """The operator typed s: this object is left out this time."""


def row_path(db: Path, scan_id: str) -> Path:
    return Path(db) / "scans" / f"{scan_id}.h5"


def _coverage(cov: dict) -> str:
    return ", ".join(f"{m.upper()} {100 * c:.1f} %" for m, c in cov.items())


def _verdict(v: dict) -> str:
    return (f"{shown(v['material'])} {100 * v['confidence']:.0f} % "
            f"{'right' if v['right'] else 'WRONG'}")
