"""Material classification (paper §V-B2): OA and US windows from the scan database, BOSS
(aeon, alphabet_size=4, as the paper) and MiniRocket per modality, fused by their
probabilities (or one modality alone), evaluated by random 3:1 splits and by leaving one
object out.

Pure computation apart from `assemble`, which reads scan files. Windows start PRE samples
before the ranged arrival and are scaled to unit RMS: the pulse shape and the material's
ringing are kept, the distance-dependent amplitude is not.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..ranging.calibrate import K, RangeCal, RangingSetup
from ..scan.scanfile import ScanData, read_scan

MODS = ("oa", "us")
BOSS_PER_CLASS = 20  # BOSS trains on at most this many windows per class and modality:
# its ensemble search costs ~n^2 (leave-one-out 1-NN per parameter set): 1-2 s per fit
# here on 64-sample windows, 20-40 s on 128
WINDOW = 64  # samples per window (19.2 us at 3.333 MS/s): an OA window then ends before the
# US echo, which follows the OA arrival by t0_US - t0_OA + d/c (2 us + d/c here), beyond d = 5 mm
PRE = 8       # samples kept before the arrival
SHORTEST_WINDOW = 16  # samples (4.8 us): the shortest window either classifier is given
BOSS_WORD_MIN = 16    # BOSS's shortest word window, samples, where the window allows it
BOSS_WORD_PROP = 0.34  # BOSS's longest word window as a share of the window


class ClassifyError(ValueError):
    """Data or a model that cannot be used as asked; str() says what to do."""


@dataclass
class Dataset:
    """Per point: OA and US windows (NaN rows where absent), material, object, scan."""

    X: dict[str, np.ndarray]      # modality -> (n, WINDOW) float32
    has: dict[str, np.ndarray]    # modality -> (n,) bool
    y: np.ndarray                 # material labels
    groups: np.ndarray            # object ids
    fs_hz: float
    window: int
    scans: list[str] = field(default_factory=list)
    n_average: int = 0            # laser shots averaged per waveform (most common value)

    def __len__(self) -> int:
        return len(self.y)

    def subset(self, idx: np.ndarray) -> Dataset:
        """The points idx (same provenance)."""
        return Dataset({m: x[idx] for m, x in self.X.items()},
                       {m: h[idx] for m, h in self.has.items()}, self.y[idx],
                       self.groups[idx], self.fs_hz, self.window, self.scans, self.n_average)

    def usable(self, modalities: tuple[str, ...]) -> np.ndarray:
        """Indices of the points with a window in at least one of these modalities."""
        return np.nonzero(np.any([self.has[m] for m in modalities], axis=0))[0]


def windows(waveforms: np.ndarray, arrival: np.ndarray, window: int = WINDOW,
            pre: int = PRE) -> tuple[np.ndarray, np.ndarray]:
    """Unit-RMS windows (n, window) starting pre samples before each arrival (sample index,
    NaN: none); the second array says which rows are valid."""
    n, length = waveforms.shape
    out = np.full((n, window), np.nan, np.float32)
    ok = np.isfinite(arrival)
    start = np.where(ok, np.round(np.nan_to_num(arrival)) - pre, -1).astype(int)
    ok &= (start >= 0) & (start + window <= length)
    for i in np.nonzero(ok)[0]:
        w = waveforms[i, start[i]:start[i] + window].astype(np.float32) - 32768.0
        rms = float(np.sqrt(np.mean(w * w)))
        out[i] = w / rms if rms > 0 else w
    return out, ok


def arrival_sample(cal: RangeCal, modality: str, d_mm: np.ndarray, phase_s: np.ndarray,
                   fs_hz: float, pretrigger: int = 0) -> np.ndarray:
    """Sample index where a pulse from distance d_mm (one way for OA, round trip for US)
    arrives, given the trigger phase (s) of each waveform."""
    t = cal.t0_s + K[modality] * np.asarray(d_mm, float) / cal.c_mm_s
    return (t - phase_s) * fs_hz + pretrigger


def arrivals(scan: ScanData, modality: str) -> np.ndarray:
    """Sample index of each point's arrival from its stored distance (NaN where none)."""
    setup = RangingSetup.from_json(scan.ranging_json)
    if modality not in setup.cals:
        return np.full(scan.n_points, np.nan)
    p = scan.points
    idx = arrival_sample(setup.cals[modality], modality, p[f"distance_{modality}_mm"],
                         p["trigger_phase"] / float(scan.sensor["tick_hz"]), setup.fs_hz,
                         int(scan.sensor.get("config_pretrigger", 0)))
    return np.where(p["received"], idx, np.nan)


def sample_rate(sensor: dict) -> float:
    """Samples per second of a scan's waveforms (ADC rate / configured divider), Hz."""
    return float(sensor["adc_rate_hz"]) / int(sensor.get("config_sample_rate_div", 1))


def scan_dataset(scan: ScanData, window: int = WINDOW) -> Dataset:
    """Every point of one scan (row i = the file's point row i), with its windows where it has
    an arrival: what `assemble` takes the usable rows of, and what a 3D model places."""
    if not scan.sample.get("material"):
        raise ClassifyError(f"{scan.path} has no material label (scan plan [sample] material)")
    X, has = {}, {}
    for m in MODS:
        X[m], has[m] = windows(scan.waveforms, arrivals(scan, m), window)
    n = scan.n_points
    avg = scan.points["n_average"][scan.points["received"]].astype(int)
    return Dataset(X, has, np.array([str(scan.sample["material"])] * n),
                   np.array([str(scan.sample["name"])] * n), sample_rate(scan.sensor), window,
                   [str(scan.entry.get("scan_id", Path(scan.path).stem))],
                   int(np.bincount(avg).argmax()) if len(avg) else 0)


def assemble(paths: list[Path], window: int = WINDOW) -> Dataset:
    """The dataset of all points of these scan files (their sample rates must agree)."""
    parts: list[Dataset] = []
    averages: list[np.ndarray] = []
    for path in paths:
        scan = read_scan(path)
        one = scan_dataset(scan, window)
        if parts and abs(one.fs_hz - parts[0].fs_hz) > 1e-6 * parts[0].fs_hz:
            raise ClassifyError(f"{path} was sampled at {one.fs_hz:.0f} Hz, the others at "
                                f"{parts[0].fs_hz:.0f} Hz: build one database per sample rate")
        parts.append(one)
        averages.append(scan.points["n_average"][scan.points["received"]])
    if not parts:
        raise ClassifyError("no scans to classify: scan objects into the database first")
    avg = np.concatenate(averages).astype(int)
    ds = Dataset({m: np.vstack([p.X[m] for p in parts]) for m in MODS},
                 {m: np.concatenate([p.has[m] for p in parts]) for m in MODS},
                 np.concatenate([p.y for p in parts]), np.concatenate([p.groups for p in parts]),
                 parts[0].fs_hz, window, [s for p in parts for s in p.scans],
                 int(np.bincount(avg).argmax()) if len(avg) else 0)
    return ds.subset(ds.usable(MODS))  # points without any arrival carry no signal


def boss_word_windows(window: int) -> tuple[int, int]:
    """BOSS's word windows (shortest, longest) in samples for windows of `window` samples:
    16 up to 0.34 of the window (16..21 for the default 64, 4.8-6.3 us: a few carrier
    cycles; 16..43 for 128); a window too short for 16 (47 samples or fewer) gets one word
    window of 0.34 of it, the longest that fits, instead of aeon's ValueError."""
    longest = int(window * BOSS_WORD_PROP)
    return min(BOSS_WORD_MIN, longest), longest


def check_window(window: int) -> None:
    """Refuse, in one line, a window neither classifier is given (shorter than 16 samples)."""
    if window < SHORTEST_WINDOW:
        raise ClassifyError(f"windows must be at least {SHORTEST_WINDOW} samples for either "
                            f"classifier (got {window}): use a longer --window")


def make_classifier(name: str, window: int, seed: int = 0) -> object:
    """An aeon classifier for windows of `window` samples: 'boss' (BOSSEnsemble,
    alphabet_size=4, word windows from boss_word_windows) or 'minirocket' (its standard
    ridge, with probabilities from CalibratedRidge)."""
    check_window(window)
    if name == "boss":
        from aeon.classification.dictionary_based import BOSSEnsemble
        shortest, _ = boss_word_windows(window)
        return BOSSEnsemble(alphabet_size=4, min_window=shortest,
                            max_win_len_prop=BOSS_WORD_PROP, max_ensemble_size=50,
                            random_state=seed)
    if name == "minirocket":
        from aeon.classification.convolution_based import MiniRocketClassifier
        from sklearn.pipeline import make_pipeline
        from sklearn.preprocessing import StandardScaler

        from .ridge import CalibratedRidge

        ridge = CalibratedRidge(alphas=np.logspace(-3, 3, 10), store_cv_results=True,
                                scoring="accuracy")
        return MiniRocketClassifier(estimator=make_pipeline(StandardScaler(with_mean=False),
                                                            ridge), random_state=seed)
    raise ClassifyError(f"unknown classifier {name!r}: use boss or minirocket")


@dataclass
class FusedModel:
    """One classifier per modality, fused: P(c | x) ~ P(pattern | c) P(c) prod_m
    p_m(c | x_m) / P_m(c), where pattern says which modalities a point has (a missing
    modality is itself evidence: glass gives no OA, foam no US). A one-modality model sees
    only that modality's windows and no pattern."""

    name: str
    classes: np.ndarray
    models: dict[str, object]
    prior: np.ndarray                       # P(c)
    mod_prior: dict[str, np.ndarray]        # P_m(c) in modality m's training set
    pattern: np.ndarray                     # P(pattern | c): (4, n_classes)
    fit_s: float = 0.0
    modalities: tuple[str, ...] = MODS
    modality_model: object | None = None    # tells an OA window from a US one (lone pulses)
    seed: int = 0
    training: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    # BOSS only: the windows and labels each modality's model was fit on (a model file keeps
    # them and refits; BOSS's fitted dictionaries are not arrays)

    def predict_proba(self, ds: Dataset, us_absence_said: np.ndarray | None = None
                      ) -> np.ndarray:
        """(n, n_classes) probabilities. us_absence_said (n,) bool (None: all True): whether
        a point without a US window says its material gives no echo; False where the geometry
        explains the silence (the surface turned beyond the echo's cone, which no material
        escapes): that point's pattern term is then the odds of its OA presence alone."""
        return self._posterior(self._windows_logp(ds), _pattern(ds), us_absence_said)

    def predict_proba_silence(self, ds: Dataset) -> tuple[np.ndarray, np.ndarray]:
        """predict_proba with every point's missing US echo taken as its material's, and as
        the geometry's: both from one pass of the classifiers over the windows."""
        logp, pat = self._windows_logp(ds), _pattern(ds)
        return (self._posterior(logp, pat, None),
                self._posterior(logp, pat, np.zeros(len(pat), bool)))

    def _windows_logp(self, ds: Dataset) -> np.ndarray:
        """(n, n_classes): sum over modalities of log p_m(c | x_m) / P_m(c)."""
        logp = np.zeros((len(ds.y), len(self.classes)))
        for m, model in self.models.items():
            idx = np.nonzero(ds.has[m])[0]
            if len(idx):
                p = np.zeros((len(idx), len(self.classes)))
                cols = np.searchsorted(self.classes, model.classes_)
                p[:, cols] = model.predict_proba(ds.X[m][idx][:, None, :])
                logp[idx] += np.log(np.clip(p, 1e-6, 1)) - np.log(self.mod_prior[m])
        return logp

    def _posterior(self, logp_windows: np.ndarray, pat: np.ndarray,
                   us_absence_said: np.ndarray | None) -> np.ndarray:
        like = self.pattern[pat]
        if us_absence_said is not None:
            free = ~np.asarray(us_absence_said, bool) & (pat < 2)  # no US window: marginalise
            like[free] = self.pattern[pat[free]] + self.pattern[pat[free] + 2]
        logp = np.log(self.prior)[None, :] + np.log(like) + logp_windows
        logp -= logp.max(axis=1, keepdims=True)
        prob = np.exp(logp)
        return prob / prob.sum(axis=1, keepdims=True)

    def predict(self, ds: Dataset) -> np.ndarray:
        """Most probable material per point."""
        return self.classes[self.predict_proba(ds).argmax(axis=1)]


def _pattern(ds: Dataset) -> np.ndarray:
    return ds.has["oa"].astype(int) + 2 * ds.has["us"].astype(int)


def fit(ds: Dataset, name: str, seed: int = 0, modalities: tuple[str, ...] = MODS,
        lone_pulses: bool = False) -> FusedModel:
    """Train the per-modality classifiers and the fusion on the points that have a window in
    one of `modalities`; lone_pulses: also learn to tell OA from US windows (live use)."""
    _check_modalities(modalities)
    check_window(ds.window)
    ds = ds.subset(ds.usable(modalities))
    classes = np.unique(ds.y)
    if len(classes) < 2:
        raise ClassifyError("need at least two materials to train a classifier")
    t0 = time.perf_counter()
    counts = np.array([(ds.y == c).sum() for c in classes], float)
    pat = np.ones((4, len(classes)))  # Laplace smoothing; uniform for one modality
    for j, c in enumerate(classes):
        if len(modalities) == len(MODS):
            pat[:, j] += np.bincount(_pattern(ds)[ds.y == c], minlength=4)
    models, mod_prior, training = {}, {}, {}
    rng = np.random.default_rng(seed)
    for m in modalities:
        idx = np.nonzero(ds.has[m])[0]
        if len(np.unique(ds.y[idx])) < 2:
            continue
        if name == "boss":
            idx = np.concatenate([rng.permutation(idx[ds.y[idx] == c])[:BOSS_PER_CLASS]
                                  for c in np.unique(ds.y[idx])])
        models[m] = make_classifier(name, ds.window, seed).fit(ds.X[m][idx][:, None, :],
                                                               ds.y[idx])
        if name == "boss":
            training[m] = (ds.X[m][idx], ds.y[idx])
        mc = np.array([(ds.y[idx] == c).sum() for c in classes], float) + 1.0
        mod_prior[m] = mc / mc.sum()
    if not models:
        raise ClassifyError(f"no {'/'.join(modalities).upper()} windows of two or more "
                            f"materials to learn from")
    which = None
    if lone_pulses and len(modalities) == len(MODS):
        which = fit_modality(ds, seed)
    return FusedModel(name, classes, models, counts / counts.sum(), mod_prior,
                      pat / pat.sum(axis=0, keepdims=True), time.perf_counter() - t0,
                      tuple(modalities), which, seed, training)


def _check_modalities(modalities: tuple[str, ...]) -> None:
    if not modalities or any(m not in MODS for m in modalities):
        raise ClassifyError(f"modalities must be some of {', '.join(MODS)} (got {modalities})")


def fit_modality(ds: Dataset, seed: int = 0) -> object:
    """MiniRocket telling OA windows from US windows (classes 'oa', 'us')."""
    X = np.vstack([ds.X[m][ds.has[m]] for m in MODS])
    y = np.concatenate([[m] * int(ds.has[m].sum()) for m in MODS])
    if len(np.unique(y)) < 2:
        raise ClassifyError("telling lone OA from US pulses needs windows of both modalities")
    return make_classifier("minirocket", X.shape[1], seed).fit(X[:, None, :], y)


def predict_lone(model: FusedModel, x: np.ndarray) -> np.ndarray:
    """(n, n_classes) probabilities for windows x (n, window) of lone pulses whose modality
    is unknown (one arrival, no partner): the posteriors of reading each as OA alone and as
    US alone, weighted by P(modality | window)."""
    n = len(x)

    def alone(m: str) -> np.ndarray:
        ds = Dataset({k: x if k == m else np.full_like(x, np.nan) for k in MODS},
                     {k: np.full(n, k == m) for k in MODS}, np.full(n, "?"),
                     np.full(n, "live"), 0.0, x.shape[1])
        return model.predict_proba(ds)

    if len(model.modalities) == 1:
        return alone(model.modalities[0])
    if model.modality_model is None:
        raise ClassifyError("this model cannot read lone pulses: train it with "
                            "`dmdsm classify train` (it learns OA from US windows)")
    p = model.modality_model.predict_proba(x[:, None, :])
    p_oa = p[:, list(model.modality_model.classes_).index("oa")][:, None]
    return p_oa * alone("oa") + (1 - p_oa) * alone("us")


def confusion(y_true: np.ndarray, y_pred: np.ndarray, classes: np.ndarray) -> np.ndarray:
    """Counts: rows true class, columns predicted class."""
    cm = np.zeros((len(classes), len(classes)), int)
    ti, pi = np.searchsorted(classes, y_true), np.searchsorted(classes, y_pred)
    np.add.at(cm, (ti, pi), 1)
    return cm


def evaluate_random(ds: Dataset, name: str, trials: int = 50, test_size: float = 0.25,
                    seed: int = 0, modalities: tuple[str, ...] = MODS,
                    progress: Callable[[int, int], None] | None = None) -> np.ndarray:
    """The paper's protocol: random stratified 3:1 splits of the points with a window in
    `modalities`; the summed confusion matrix (rows and columns: np.unique(ds.y)).
    progress(done, total) after each fit."""
    from sklearn.model_selection import StratifiedShuffleSplit

    classes = np.unique(ds.y)
    _check_modalities(modalities)
    check_window(ds.window)
    ds = ds.subset(ds.usable(modalities))
    cm = np.zeros((len(classes), len(classes)), int)
    split = StratifiedShuffleSplit(n_splits=trials, test_size=test_size, random_state=seed)
    for k, (tr, te) in enumerate(split.split(np.zeros(len(ds)), ds.y)):
        model = fit(ds.subset(tr), name, seed + k, modalities)
        cm += confusion(ds.y[te], model.predict(ds.subset(te)), classes)
        if progress is not None:
            progress(k + 1, trials)
    return cm


def evaluate_loo(ds: Dataset, name: str, seed: int = 0,
                 modalities: tuple[str, ...] = MODS,
                 progress: Callable[[int, int], None] | None = None) -> np.ndarray:
    """Leave one object out: train on the other objects, test on this one's points;
    progress(objects done, objects) after each."""
    classes = np.unique(ds.y)
    _check_modalities(modalities)
    check_window(ds.window)
    ds = ds.subset(ds.usable(modalities))
    cm = np.zeros((len(classes), len(classes)), int)
    objects = np.unique(ds.groups)
    for i, obj in enumerate(objects):
        te = np.nonzero(ds.groups == obj)[0]
        tr = np.nonzero(ds.groups != obj)[0]
        if ds.y[te[0]] in set(ds.y[tr]):  # else the only object of its material: nothing
            model = fit(ds.subset(tr), name, seed, modalities)  # to learn it from
            cm += confusion(ds.y[te], model.predict(ds.subset(te)), classes)
        if progress is not None:
            progress(i + 1, len(objects))
    return cm


def per_class_accuracy(cm: np.ndarray, classes: np.ndarray) -> dict[str, float]:
    """Recall of each class from a confusion matrix (NaN where a class was never tested)."""
    n = cm.sum(axis=1)
    return {str(c): float(cm[i, i] / n[i]) if n[i] else float("nan")
            for i, c in enumerate(classes)}
