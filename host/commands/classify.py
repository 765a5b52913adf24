"""`dmdsm classify train|evaluate|predict`: material classifiers on the scan database, model
files with their data's provenance, and predictions on scans or a live acquisition."""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..classify.materials import (
    MODS,
    SHORTEST_WINDOW,
    WINDOW,
    ClassifyError,
    assemble,
    evaluate_loo,
    evaluate_random,
    fit,
    per_class_accuracy,
    predict_lone,
)
from ..classify.model_file import check_provenance, read_model, save_model
from ..classify.predict import predict_scan, vote
from ..files import atomic_output
from ..links.sensor import config_range
from ..report.plots import confusion_figure
from .errors import check_output

PAPER = {"artificial materials": ">= 98.5 %", "apple": "79.0 %"}
MODALITY = {"both": MODS, "oa": ("oa",), "us": ("us",)}


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register `classify train|evaluate|predict`."""
    p = sub.add_parser("classify", help="train, evaluate and use material classifiers")
    psub = p.add_subparsers(dest="action", required=True, metavar="ACTION")
    common = argparse.ArgumentParser(add_help=False)
    longest = config_range("n_samples")[1]
    common.add_argument("--window", type=int, default=WINDOW,
                        help=f"samples per window, {SHORTEST_WINDOW}..{longest} for both "
                             f"classifiers (default {WINDOW}); a model only takes its own")
    common.add_argument("--json", action="store_true", help="machine-readable output")

    data = argparse.ArgumentParser(add_help=False, parents=[common])  # train, evaluate
    data.add_argument("--db", type=Path, required=True, action="append",
                      help="scan database folder (again for more: step and fly scans of "
                           "the same objects, say)")
    data.add_argument("--modality", choices=list(MODALITY), default="both",
                      help="OA and US fused (default) or one alone")

    t = psub.add_parser("train", parents=[data], help="fit a classifier to a database")
    t.add_argument("--classifier", choices=["boss", "minirocket"], default="minirocket",
                   help="default minirocket (seconds to fit); boss as the paper (minutes)")
    t.add_argument("-o", "--output", type=Path, required=True,
                   help="model file to write (numpy arrays + JSON provenance, no pickle)")

    e = psub.add_parser("evaluate", parents=[data],
                        help="the paper's accuracy protocols on a database")
    e.add_argument("--classifiers", nargs="+", choices=["boss", "minirocket"],
                   default=["boss", "minirocket"], help="which ones (default both)")
    e.add_argument("--trials", type=int, default=50, help="random 3:1 splits")
    e.add_argument("--boss-trials", type=int, default=10,
                   help="random splits for BOSS (1-2 s per fit at 64 samples)")
    e.add_argument("--no-loo", action="store_true",
                   help="skip the leave-one-object-out protocol")
    e.add_argument("--out", type=Path, default=Path("classify"),
                   help="folder for confusion matrices (CSV, PNG; default ./classify)")

    r = psub.add_parser("predict", parents=[common],
                        help="the material of a scan, or of what the sensor sees now")
    r.add_argument("--model", type=Path, required=True,
                   help="model file from `dmdsm classify train`")
    src = r.add_mutually_exclusive_group(required=True)
    src.add_argument("--scan", type=Path, help="every point of this scan file")
    src.add_argument("--sensor", help="acquire where the sensor is now (port)")
    r.add_argument("--ranging", type=Path, default=Path("ranging.json"),
                   help="--sensor: ranging calibration (default ./ranging.json)")
    r.add_argument("--shots", type=int, default=8, help="--sensor: waveforms to classify")
    for q in (t, e, r):
        q.set_defaults(func=cmd_classify)


def _db_paths(dbs: list[Path] | None) -> list[Path]:
    """The complete scans' files of every database given (each once)."""
    from ..scan.catalogue import CatalogueError, list_scans

    if not dbs:
        raise ClassifyError("give --db DIR (a scan database)")
    paths: list[Path] = []
    for db in dbs:
        try:
            rows = [r for r in list_scans(db) if r["status"] == "complete"]
        except CatalogueError as e:
            raise ClassifyError(str(e)) from None
        if not rows:
            raise ClassifyError(f"{db} has no complete scans; `dmdsm scan` fills it")
        paths += [Path(r["path"]).resolve() for r in rows]
    return list(dict.fromkeys(paths))


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
    from .errors import CliError

    try:
        hi = config_range("n_samples")[1]  # a window longer than any waveform
        if not SHORTEST_WINDOW <= args.window <= hi:
            raise ClassifyError(f"--window must be {SHORTEST_WINDOW}..{hi} samples (got "
                                f"{args.window})")
        for flag in ("trials", "boss_trials"):
            if getattr(args, flag, 1) < 1:
                raise ClassifyError(f"--{flag.replace('_', '-')} must be at least 1 (got "
                                    f"{getattr(args, flag)})")
        return {"train": _train, "evaluate": _evaluate, "predict": _predict}[args.action](args)
    except ClassifyError as e:
        raise CliError(str(e)) from None


def _train(args: argparse.Namespace) -> int:
    check_output(args.output)  # before the fit
    ds = assemble(_db_paths(args.db), args.window)
    if not args.json:  # one fit, no steps to count: say what runs and for about how long
        print(f"training {args.classifier} on {len(ds)} points of "
              f"{len(np.unique(ds.y))} materials"
              + (" (a BOSS fit takes seconds, more on long windows)"
                 if args.classifier == "boss" else "")
              + "...", file=sys.stderr, flush=True)
    model = fit(ds, args.classifier, modalities=MODALITY[args.modality], lone_pulses=True)
    save_model(model, ds, args.output)
    out = {"model": str(args.output), "classifier": args.classifier, "points": len(ds),
           "modality": args.modality, "classes": model.classes.tolist(),
           "fit_s": round(model.fit_s, 2)}
    print(json.dumps(out) if args.json else f"trained {args.classifier} ({args.modality}) on "
          f"{len(ds)} points ({', '.join(model.classes)}) in {model.fit_s:.1f} s; saved "
          f"{args.output}")
    return 0


def _out_folder(out: Path, make: bool = False) -> None:
    """Refuse an --out that is not a folder (a file, a device, ...) before minutes of
    evaluation rather than after them; with make, create it."""
    from .errors import CliError

    if os.path.lexists(out) and not out.is_dir():
        raise CliError(f"{out} is not a folder: give a folder for --out (the confusion "
                       f"matrices are written into it)")
    try:
        if make:
            out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise CliError(f"cannot make the folder {out}: {e.strerror}; give another --out") \
            from None


def _evaluate(args: argparse.Namespace) -> int:
    _out_folder(args.out)
    ds = assemble(_db_paths(args.db), args.window)
    mods = MODALITY[args.modality]
    classes = np.unique(ds.y)
    _out_folder(args.out, make=True)
    res: dict = {"points": len(ds), "objects": len(np.unique(ds.groups)),
                 "modality": args.modality, "classifiers": {}}
    tables = []
    for name in args.classifiers:
        r = {}
        trials = args.boss_trials if name == "boss" else args.trials
        protocols = [("random", lambda n=name, k=trials, p=None: evaluate_random(
            ds, n, k, modalities=mods, progress=p))]
        if not args.no_loo:
            protocols.append(("loo", lambda n=name, p=None: evaluate_loo(
                ds, n, modalities=mods, progress=p)))
        for proto, run in protocols:
            what = f"{name} {'random splits' if proto == 'random' else 'leave one out'}"
            with tqdm(desc=what, unit="fit" if proto == "random" else "object",
                      disable=args.json, file=sys.stderr) as bar:
                def tick(done: int, total: int, bar: tqdm = bar) -> None:
                    bar.total = total
                    bar.update(done - bar.n)
                cm = run(p=tick)
            r[proto] = per_class_accuracy(cm, classes)
            tag = f"{name}_{proto}" + ("" if args.modality == "both" else f"_{args.modality}")
            with atomic_output(args.out / f"confusion_{tag}.csv", flag="--out") as tmp:
                np.savetxt(tmp, cm, fmt="%d", delimiter=",", header=",".join(classes))
            label = (f"{trials} random 3:1 splits" if proto == "random"
                     else "leave one object out")
            with atomic_output(args.out / f"confusion_{tag}.png", flag="--out") as tmp:
                confusion_figure(cm, classes, tmp,
                                 f"{name} ({args.modality}): {label} (simulated data)")
            tables.append(f"{name} ({args.modality}), {label}, % of each true material:\n"
                          + confusion_table(cm, classes))
        res["classifiers"][name] = {**r, "trials": trials}
    if args.json:  # a material no split could test has no accuracy: null, not NaN
        for r in res["classifiers"].values():
            for proto in ("random", "loo"):
                if proto in r:
                    r[proto] = {c: a if np.isfinite(a) else None for c, a in r[proto].items()}
        print(json.dumps(res))
        return 0
    print(f"{len(ds)} points, {res['objects']} objects (simulated data, not a reproduction "
          f"of the paper's {PAPER})")
    for name, r in res["classifiers"].items():
        for proto, acc in ((k, v) for k, v in r.items() if k != "trials"):
            print(f"{name:>10} {proto:>6}: " + ", ".join(
                f"{c} {a:.1%}" if np.isfinite(a) else f"{c} untested" + (
                    " (no other object of it)" if proto == "loo" else "")
                for c, a in acc.items()))
    print("\n" + "\n\n".join(tables))
    return 0


def _predict(args: argparse.Namespace) -> int:
    if args.scan:
        out = predict_scan(args.model, args.scan, args.window)
    else:
        from ..classify.live import acquire_windows

        model, prov = read_model(args.model)
        paired, lone = acquire_windows(args, prov, check_provenance)
        prob = np.vstack([model.predict_proba(paired) if len(paired) else
                          np.zeros((0, len(model.classes))),
                          predict_lone(model, lone) if len(lone) else
                          np.zeros((0, len(model.classes)))])
        out = vote(model.classes, prob, args.sensor)
    print(json.dumps(out) if args.json else f"{out['source']}: {out['material']} "
          f"(confidence {out['confidence']:.0%} over {out['points']} waveforms)")
    return 0
