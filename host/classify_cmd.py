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
    WINDOW,
    ClassifyError,
    Dataset,
    assemble,
    evaluate_loo,
    evaluate_random,
    fit,
    per_class_accuracy,
    predict_lone,
)

MODEL_FORMAT = "dmdsm-classifier/1"
PAPER = {"artificial materials": ">= 98.5 %", "apple": "79.0 %"}
MODALITY = {"both": MODS, "oa": ("oa",), "us": ("us",)}


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register `classify`."""
    p = sub.add_parser("classify", help="train, evaluate and use material classifiers")
    p.add_argument("action", choices=["train", "evaluate", "predict"])
    p.add_argument("--db", type=Path, help="scan database directory")
    p.add_argument("--classifier", choices=["boss", "minirocket"], default="minirocket")
    p.add_argument("--classifiers", nargs="+", choices=["boss", "minirocket"],
                   default=["boss", "minirocket"], help="evaluate: which ones")
    p.add_argument("--modality", choices=list(MODALITY), default="both",
                   help="train/evaluate: OA and US fused (default) or one alone")
    p.add_argument("--window", type=int, default=WINDOW,
                   help=f"samples per window (default {WINDOW}); a model only takes its own")
    p.add_argument("--trials", type=int, default=50, help="evaluate: random 3:1 splits")
    p.add_argument("--boss-trials", type=int, default=10,
                   help="evaluate: random splits for BOSS (about 20 s per fit)")
    p.add_argument("--no-loo", action="store_true",
                   help="evaluate: skip the leave-one-object-out protocol")
    p.add_argument("--out", type=Path, default=Path("classify"),
                   help="evaluate: folder for confusion matrices (CSV, PNG)")
    p.add_argument("-o", "--model", type=Path, default=Path("material.model"))
    p.add_argument("--scan", type=Path, help="predict: every point of this scan file")
    p.add_argument("--sensor", help="predict: acquire where the sensor is now")
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
    """Pickle the model with the provenance that load_model() checks."""
    import aeon

    prov = {"format": MODEL_FORMAT, "fs_hz": ds.fs_hz, "window": ds.window, "pre": PRE,
            "classes": [str(c) for c in model.classes], "classifier": model.name,
            "modalities": list(model.modalities), "n_average": ds.n_average,
            "scans": ds.scans, "points": len(ds), "dmdsm": __version__,
            "aeon": aeon.__version__,
            "created": datetime.datetime.now().isoformat(timespec="seconds")}
    with open(path, "wb") as f:
        pickle.dump({"provenance": prov, "model": model}, f)


def read_model(path: Path) -> tuple[object, dict]:
    """A model file and its provenance, unchecked. (Model files are pickles: load only
    your own.)"""
    try:
        with open(path, "rb") as f:
            obj = pickle.load(f)
        prov = obj["provenance"]
        if prov.get("format") != MODEL_FORMAT:
            raise KeyError("format")
        return obj["model"], prov
    except (OSError, pickle.UnpicklingError, KeyError, TypeError, EOFError, ValueError,
            AttributeError, ImportError) as e:
        raise ClassifyError(f"{path} is not a readable dmdsm classifier model ({e!r}); train "
                            f"one with `dmdsm classify train`") from None


def check_provenance(prov: dict, path: Path, fs_hz: float, window: int) -> None:
    """Refuse data the model was not trained for (another sample rate or window)."""
    if abs(prov["fs_hz"] - fs_hz) > 1e-6 * fs_hz:
        raise ClassifyError(f"{path} was trained on {prov['fs_hz']:.0f} Hz data, these "
                            f"waveforms are {fs_hz:.0f} Hz: retrain on data at this rate")
    if prov["window"] != window or prov.get("pre", PRE) != PRE:
        raise ClassifyError(f"{path} was trained on {prov['window']}-sample windows, not "
                            f"{window}: pass --window {prov['window']} or retrain")


def load_model(path: Path, fs_hz: float, window: int) -> tuple[object, dict]:
    """read_model() + check_provenance()."""
    model, prov = read_model(path)
    check_provenance(prov, path, fs_hz, window)
    return model, prov


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


def confusion_table(cm: np.ndarray, classes: np.ndarray) -> str:
    """Row-normalised confusion matrix in percent as text (rows: true material)."""
    pct = 100 * cm / np.maximum(cm.sum(axis=1, keepdims=True), 1)
    w = max(9, *(len(c) + 1 for c in classes))
    head = "true/pred"
    lines = [f"{head:<{w}}" + "".join(f"{c[:w - 1]:>{w}}" for c in classes)]
    for c, row, n in zip(classes, pct, cm.sum(axis=1)):
        cells = "".join(f"{v:>{w}.1f}" if n else f"{'-':>{w}}" for v in row)
        lines.append(f"{c:<{w}}{cells}")
    return "\n".join(lines)


def cmd_classify(args: argparse.Namespace) -> int:
    """Dispatch the three actions; every ClassifyError becomes one line."""
    from .cli import CliError

    try:
        if args.window < 16:
            raise ClassifyError(f"--window must be at least 16 samples (got {args.window})")
        return {"train": _train, "evaluate": _evaluate, "predict": _predict}[args.action](args)
    except ClassifyError as e:
        raise CliError(str(e)) from None


def _train(args: argparse.Namespace) -> int:
    ds = assemble(_db_paths(args.db), args.window)
    model = fit(ds, args.classifier, modalities=MODALITY[args.modality], lone_pulses=True)
    save_model(model, ds, args.model)
    out = {"model": str(args.model), "classifier": args.classifier, "points": len(ds),
           "modality": args.modality, "classes": model.classes.tolist(),
           "fit_s": round(model.fit_s, 2)}
    print(json.dumps(out) if args.json else f"trained {args.classifier} ({args.modality}) on "
          f"{len(ds)} points ({', '.join(model.classes)}) in {model.fit_s:.1f} s; saved "
          f"{args.model}")
    return 0


def _evaluate(args: argparse.Namespace) -> int:
    ds = assemble(_db_paths(args.db), args.window)
    mods = MODALITY[args.modality]
    classes = np.unique(ds.y)
    args.out.mkdir(parents=True, exist_ok=True)
    res: dict = {"points": len(ds), "objects": len(np.unique(ds.groups)),
                 "modality": args.modality, "classifiers": {}}
    tables = []
    for name in args.classifiers:
        r = {}
        trials = args.boss_trials if name == "boss" else args.trials
        protocols = [("random", lambda n=name, k=trials: evaluate_random(ds, n, k,
                                                                          modalities=mods))]
        if not args.no_loo:
            protocols.append(("loo", lambda n=name: evaluate_loo(ds, n, modalities=mods)))
        for proto, run in protocols:
            cm = run()
            r[proto] = per_class_accuracy(cm, classes)
            tag = f"{name}_{proto}" + ("" if args.modality == "both" else f"_{args.modality}")
            np.savetxt(args.out / f"confusion_{tag}.csv", cm, fmt="%d", delimiter=",",
                       header=",".join(classes))
            label = (f"{trials} random 3:1 splits" if proto == "random"
                     else "leave one object out")
            confusion_figure(cm, classes, args.out / f"confusion_{tag}.png",
                             f"{name} ({args.modality}): {label} (simulated data)")
            tables.append(f"{name} ({args.modality}), {label}, % of each true material:\n"
                          + confusion_table(cm, classes))
        res["classifiers"][name] = {**r, "trials": trials}
    if args.json:
        print(json.dumps(res))
        return 0
    print(f"{len(ds)} points, {res['objects']} objects (simulated data, not a reproduction "
          f"of the paper's {PAPER})")
    for name, r in res["classifiers"].items():
        for proto, acc in ((k, v) for k, v in r.items() if k != "trials"):
            print(f"{name:>10} {proto:>6}: " + ", ".join(f"{c} {a:.1%}" for c, a in acc.items()))
    print("\n" + "\n\n".join(tables))
    return 0


def _predict(args: argparse.Namespace) -> int:
    if args.scan:
        from .scandb import ScanFileError, read_scan

        try:
            read_scan(args.scan)
        except ScanFileError as e:
            raise ClassifyError(str(e)) from None
        ds = assemble([args.scan], args.window)
        model, _ = load_model(args.model, ds.fs_hz, ds.window)
        ds = ds.subset(ds.usable(model.modalities))
        if not len(ds):
            raise ClassifyError(f"{args.scan} has no {'/'.join(model.modalities).upper()} "
                                f"windows for this model")
        prob = model.predict_proba(ds)
        source, n = str(args.scan), len(ds)
    elif args.sensor:
        from .classify_live import acquire_windows

        model, prov = read_model(args.model)
        paired, lone = acquire_windows(args, prov, check_provenance)
        prob = np.vstack([model.predict_proba(paired) if len(paired) else
                          np.zeros((0, len(model.classes))),
                          predict_lone(model, lone) if len(lone) else
                          np.zeros((0, len(model.classes)))])
        source, n = args.sensor, len(prob)
    else:
        raise ClassifyError("predict needs --scan FILE or --sensor PORT")
    mean = prob.mean(axis=0)
    best = int(mean.argmax())
    out = {"source": source, "material": str(model.classes[best]),
           "confidence": float(mean[best]), "points": n,
           "votes": {str(c): int(v) for c, v in zip(model.classes, np.bincount(
               prob.argmax(axis=1), minlength=len(model.classes))) if v},
           "probabilities": {str(c): float(p) for c, p in zip(model.classes, mean)}}
    print(json.dumps(out) if args.json else f"{source}: {out['material']} "
          f"(confidence {out['confidence']:.0%} over {n} waveforms)")
    return 0
