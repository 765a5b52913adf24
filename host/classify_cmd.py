"""`dmdsm classify train|evaluate|predict`: material classifiers on the scan database, model
files with their data's provenance, and predictions on scans or a live acquisition."""

from __future__ import annotations

import argparse
import datetime
import json
import pickle
from pathlib import Path

import numpy as np

from . import __version__
from .classify import (
    MODS,
    PRE,
    ClassifyError,
    Dataset,
    assemble,
    evaluate_loo,
    evaluate_random,
    fit,
    per_class_accuracy,
    windows,
)

MODEL_FORMAT = "dmdsm-classifier/1"
PAPER = {"artificial materials": ">= 98.5 %", "apple": "79.0 %"}


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register `classify`."""
    p = sub.add_parser("classify", help="train, evaluate and use material classifiers")
    p.add_argument("action", choices=["train", "evaluate", "predict"])
    p.add_argument("--db", type=Path, help="scan database directory")
    p.add_argument("--classifier", choices=["boss", "minirocket"], default="minirocket")
    p.add_argument("--classifiers", nargs="+", choices=["boss", "minirocket"],
                   default=["boss", "minirocket"], help="evaluate: which ones")
    p.add_argument("--trials", type=int, default=50, help="evaluate: random 3:1 splits")
    p.add_argument("--boss-trials", type=int, default=10,
                   help="evaluate: random splits for BOSS (about 20 s per fit)")
    p.add_argument("--no-loo", action="store_true",
                   help="evaluate: skip the leave-one-object-out protocol")
    p.add_argument("--out", type=Path, default=Path("classify"),
                   help="evaluate: folder for confusion matrices (CSV, PNG)")
    p.add_argument("-o", "--model", type=Path, default=Path("material.model"))
    p.add_argument("--scan", type=Path, help="predict: every point of this scan file")
    p.add_argument("--sensor", help="predict: acquire at the stage's current position")
    p.add_argument("--ranging", type=Path, default=Path("ranging.json"))
    p.add_argument("--shots", type=int, default=8, help="predict --sensor: waveforms")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_classify)


def _db_paths(db: Path | None) -> list[Path]:
    from .catalogue import CatalogueError, list_scans

    if db is None:
        raise ClassifyError("give --db DIR (a scan database)")
    try:
        rows = [r for r in list_scans(db) if r["status"] == "complete"]
    except CatalogueError as e:
        raise ClassifyError(str(e)) from None
    if not rows:
        raise ClassifyError(f"{db} has no complete scans; `dmdsm scan` fills it")
    return [Path(r["path"]) for r in rows]


def save_model(model: object, ds: Dataset, path: Path) -> None:
    """Pickle the model with the provenance that predict() checks."""
    prov = {"format": MODEL_FORMAT, "fs_hz": ds.fs_hz, "window": ds.window, "pre": PRE,
            "classes": [str(c) for c in model.classes], "classifier": model.name,
            "scans": ds.scans, "points": len(ds), "dmdsm": __version__,
            "created": datetime.datetime.now().isoformat(timespec="seconds")}
    with open(path, "wb") as f:
        pickle.dump({"provenance": prov, "model": model}, f)


def load_model(path: Path, fs_hz: float, window: int) -> tuple[object, dict]:
    """A model file, refused if it was trained on another sample rate or window length.
    (Model files are pickles: load only your own.)"""
    try:
        with open(path, "rb") as f:
            obj = pickle.load(f)
        prov = obj["provenance"]
        if prov.get("format") != MODEL_FORMAT:
            raise KeyError("format")
    except (OSError, pickle.UnpicklingError, KeyError, TypeError, EOFError) as e:
        raise ClassifyError(f"{path} is not a dmdsm classifier model ({e}); train one with "
                            f"`dmdsm classify train`") from None
    if abs(prov["fs_hz"] - fs_hz) > 1e-6 * fs_hz:
        raise ClassifyError(f"{path} was trained on {prov['fs_hz']:.0f} Hz data, these "
                            f"waveforms are {fs_hz:.0f} Hz: retrain on data at this rate")
    if prov["window"] != window:
        raise ClassifyError(f"{path} was trained on {prov['window']}-sample windows, not "
                            f"{window}: retrain")
    return obj["model"], prov


def confusion_figure(cm: np.ndarray, classes: np.ndarray, path: Path, title: str) -> None:
    """PNG like the paper's Fig. 5: row-normalised confusion matrix in percent."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pct = 100 * cm / np.maximum(cm.sum(axis=1, keepdims=True), 1)
    fig, ax = plt.subplots(figsize=(5.2, 4.6))
    ax.imshow(pct, cmap="Blues", vmin=0, vmax=100)
    for i in range(len(classes)):
        for j in range(len(classes)):
            ax.text(j, i, f"{pct[i, j]:.1f}", ha="center", va="center", fontsize=7,
                    color="white" if pct[i, j] > 60 else "black")
    ax.set_xticks(range(len(classes)), classes, rotation=45, ha="right", fontsize=8)
    ax.set_yticks(range(len(classes)), classes, fontsize=8)
    ax.set_xlabel("predicted")
    ax.set_ylabel("true")
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def cmd_classify(args: argparse.Namespace) -> int:
    """Dispatch the three actions; every ClassifyError becomes one line."""
    from .cli import CliError

    try:
        return {"train": _train, "evaluate": _evaluate, "predict": _predict}[args.action](args)
    except ClassifyError as e:
        raise CliError(str(e)) from None


def _train(args: argparse.Namespace) -> int:
    ds = assemble(_db_paths(args.db))
    model = fit(ds, args.classifier)
    save_model(model, ds, args.model)
    out = {"model": str(args.model), "classifier": args.classifier, "points": len(ds),
           "classes": model.classes.tolist(), "fit_s": round(model.fit_s, 2)}
    print(json.dumps(out) if args.json else f"trained {args.classifier} on {len(ds)} points "
          f"({', '.join(model.classes)}) in {model.fit_s:.1f} s; saved {args.model}")
    return 0


def _evaluate(args: argparse.Namespace) -> int:
    ds = assemble(_db_paths(args.db))
    classes = np.unique(ds.y)
    args.out.mkdir(parents=True, exist_ok=True)
    res: dict = {"points": len(ds), "objects": len(np.unique(ds.groups)), "classifiers": {}}
    for name in args.classifiers:
        r = {}
        trials = args.boss_trials if name == "boss" else args.trials
        protocols = [("random", lambda n=name, k=trials: evaluate_random(ds, n, k))]
        if not args.no_loo:
            protocols.append(("loo", lambda n=name: evaluate_loo(ds, n)))
        for proto, run in protocols:
            cm = run()
            r[proto] = per_class_accuracy(cm, classes)
            np.savetxt(args.out / f"confusion_{name}_{proto}.csv", cm, fmt="%d",
                       delimiter=",", header=",".join(classes))
            label = (f"{trials} random 3:1 splits" if proto == "random"
                     else "leave one object out")
            confusion_figure(cm, classes, args.out / f"confusion_{name}_{proto}.png",
                             f"{name}: {label} (simulated data)")
        res["classifiers"][name] = {**r, "trials": trials}
    if args.json:
        print(json.dumps(res))
        return 0
    print(f"{len(ds)} points, {res['objects']} objects (simulated data, not a reproduction "
          f"of the paper's {PAPER})")
    for name, r in res["classifiers"].items():
        for proto, acc in ((k, v) for k, v in r.items() if k != "trials"):
            print(f"{name:>10} {proto:>6}: " + ", ".join(f"{c} {a:.1%}" for c, a in acc.items()))
    return 0


def _predict(args: argparse.Namespace) -> int:
    from .scandb import ScanFileError, read_scan

    if args.scan:
        try:
            scan = read_scan(args.scan)
        except ScanFileError as e:
            raise ClassifyError(str(e)) from None
        ds = assemble([args.scan])
        model, _ = load_model(args.model, ds.fs_hz, ds.window)
        prob = model.predict_proba(ds)
        source = str(scan.path)
    elif args.sensor:
        ds, source = _live(args)
        model, _ = load_model(args.model, ds.fs_hz, ds.window)
        prob = model.predict_proba(ds)
    else:
        raise ClassifyError("predict needs --scan FILE or --sensor PORT")
    mean = prob.mean(axis=0)
    best = int(mean.argmax())
    out = {"source": source, "material": str(model.classes[best]),
           "confidence": float(mean[best]), "points": len(ds),
           "probabilities": {str(c): float(p) for c, p in zip(model.classes, mean)}}
    print(json.dumps(out) if args.json else f"{source}: {out['material']} "
          f"(confidence {out['confidence']:.0%} over {len(ds)} waveforms)")
    return 0


def _live(args: argparse.Namespace) -> tuple[Dataset, str]:
    """Acquire waveforms where the sensor is, range them and cut windows."""
    from .range_cal import RangingSetup
    from .scan import PointRanger
    from .scan_plan import ScanPlan
    from .sensor import SensorClient

    try:
        setup = RangingSetup.load(args.ranging)
    except ValueError as e:
        raise ClassifyError(f"{e}; run `dmdsm calibrate-range` first") from None
    sc = SensorClient(args.sensor)
    try:
        cfg = sc.configure(n_samples=1024, n_average=16, pretrigger=0,
                           trigger_timeout_ms=2000)
        shots = sc.acquire(args.shots)
        tick = sc.identity.tick_hz
    finally:
        sc.close()
    ok = np.nonzero(shots.received)[0]
    ranger = PointRanger(setup, ScanPlan("live", radius_mm=30.0), cfg["n_samples"], tick)
    X, has = {m: [] for m in MODS}, {m: [] for m in MODS}
    for i in ok:
        r = ranger(shots.samples[i].astype(np.uint16), int(shots.trigger_phase[i]))
        for m in MODS:
            cal = setup.cals.get(m)
            d = r.get(m, (np.nan, 0.0))[0]
            idx = (cal.t0_s + (1 if m == "oa" else 2) * d / cal.c_mm_s
                   - shots.trigger_phase[i] / tick) * setup.fs_hz if cal else np.nan
            w, good = windows(shots.samples[i:i + 1], np.array([idx]))
            X[m].append(w[0])
            has[m].append(bool(good[0]))
    keep = np.array(has["oa"]) | np.array(has["us"])
    if not keep.any():
        raise ClassifyError("no echo in any waveform: is an object in front of the sensor?")
    ds = Dataset({m: np.array(X[m])[keep] for m in MODS},
                 {m: np.array(has[m])[keep] for m in MODS}, np.array(["?"] * keep.sum()),
                 np.array(["live"] * keep.sum()), setup.fs_hz, len(X["oa"][0]))
    return ds, args.sensor
