"""Classification benchmark on a hil_sim database (14 household objects, 7 materials): accuracy
per class for BOSS and MiniRocket under the paper's protocol (random 3:1 splits) and leave one
object out, next to the paper's Fig. 5 — simulated data, not a reproduction — and fit and
predict time per 1000 waveforms.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from dmdsm.host.classify import (  # noqa: E402
    assemble,
    evaluate_loo,
    evaluate_random,
    fit,
    per_class_accuracy,
)
from dmdsm.sim.dataset import make_database  # noqa: E402

PAPER = {"aluminium": ">=98.5", "foam": ">=98.5", "glass": ">=98.5", "paper": ">=98.5",
         "plastic": ">=98.5", "steel": ">=98.5", "apple": "79.0"}


def main() -> int:
    """Print the table and the timings."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=40, help="positions per object")
    ap.add_argument("--trials", type=int, default=50, help="random splits (MiniRocket)")
    ap.add_argument("--boss-trials", type=int, default=10, help="random splits (BOSS)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        make_database(Path(tmp), args.points, seed=3)
        ds = assemble(sorted((Path(tmp) / "scans").glob("*.h5")))
    classes = np.unique(ds.y)
    n_windows = int(ds.has["oa"].sum() + ds.has["us"].sum())
    print(f"{len(ds)} points ({n_windows} windows), {len(np.unique(ds.groups))} objects, "
          f"{len(classes)} materials — simulated data")
    table = {}
    for name, trials in (("minirocket", args.trials), ("boss", args.boss_trials)):
        fit(ds.subset(np.arange(min(len(ds), 40))), name)  # compile (numba) outside timing
        t0 = time.perf_counter()
        model = fit(ds, name)
        t_fit = time.perf_counter() - t0
        t0 = time.perf_counter()
        model.predict(ds)
        t_pred = time.perf_counter() - t0
        trained = n_windows if name == "minirocket" else sum(
            min(int(((ds.y == c) & ds.has[m]).sum()), 20) for c in classes for m in ds.has)
        print(f"{name}: fit {1000 * t_fit / trained:.2f} s per 1000 training windows "
              f"({trained} windows in {t_fit:.1f} s), predict "
              f"{1000 * t_pred / n_windows:.3f} s per 1000 windows")
        t0 = time.perf_counter()
        table[(name, "random")] = per_class_accuracy(evaluate_random(ds, name, trials), classes)
        table[(name, "loo")] = per_class_accuracy(evaluate_loo(ds, name), classes)
        print(f"  evaluation ({trials} random splits + leave one object out): "
              f"{time.perf_counter() - t0:.0f} s")
    cols = [(n, p) for n in ("boss", "minirocket") for p in ("random", "loo")]
    print(f"{'material':<10} {'paper':>7} " + " ".join(f"{n + ' ' + p:>16}" for n, p in cols))
    for c in classes:
        print(f"{c:<10} {PAPER[c]:>7} " + " ".join(f"{100 * table[k][c]:15.1f}%" for k in cols))
    return 0


if __name__ == "__main__":
    sys.exit(main())
