"""Compile aeon's numba kernels for BOSS and MiniRocket once, into numba's on-disk cache.

aeon's kernels are `njit(cache=True)`: the first process to call one compiles it (a cold BOSS
takes ~150 s of CPU) and writes the machine code beside aeon's modules; every later process
loads it in well under a second. Processes started together (pytest-xdist workers, the demo)
would each compile the same kernels, so `make test` runs this once first. It fits the same
classifiers as `materials.fit`, on the same array types (float32, (n, 1, WINDOW)), so the
cached signatures are the ones the pipeline calls.
"""

from __future__ import annotations

import sys
import time

import numpy as np

from .materials import MODS, WINDOW, Dataset, fit, predict_lone


def tiny_dataset(n_per_class: int = 8, seed: int = 0, window: int = WINDOW) -> Dataset:
    """Two 'materials' of decaying tones, both modalities, in the pipeline's window shape
    (window samples long)."""
    rng = np.random.default_rng(seed)
    t = np.arange(window)
    X: dict[str, list[np.ndarray]] = {m: [] for m in MODS}
    y = []
    for k, name in enumerate(["a", "b"]):
        for _ in range(n_per_class):
            for m, f in (("oa", 0.05), ("us", 0.12)):
                w = np.sin(2 * np.pi * (f + 0.04 * k) * t) * np.exp(-t / (12 + 10 * k))
                X[m].append(w + 0.1 * rng.standard_normal(window))
            y.append(name)
    n = len(y)
    return Dataset({m: np.array(v, np.float32) for m, v in X.items()},
                   {m: np.ones(n, bool) for m in MODS}, np.array(y),
                   np.array([f"{c}{i % 2}" for i, c in enumerate(y)]), 3.333e6, window)


def warm_up() -> float:
    """Fit and predict with both classifiers on a tiny dataset; returns the seconds taken."""
    t0 = time.perf_counter()
    ds = tiny_dataset()
    for name in ("boss", "minirocket"):
        model = fit(ds, name, lone_pulses=name == "minirocket")
        model.predict_proba(ds)
        if name == "minirocket":
            predict_lone(model, ds.X["us"][:4])
    return time.perf_counter() - t0


if __name__ == "__main__":
    print(f"aeon kernels compiled or loaded in {warm_up():.1f} s", file=sys.stderr)
