"""Classifier model files: the fitted model as plain numpy arrays in a zip (.npz, no pickles)
with JSON provenance and a sha256 of every array, so loading one can never run code.

MiniRocket models keep their fitted state (kernel dilations and biases, feature scales, ridge
weights, softmax temperature) and predict from it directly. BOSS models keep the windows and
labels they were trained on and are refit on load (deterministic for a seed; 1-2 s per
modality at 64 samples, about 20 s at 128), then checked against the probabilities stored at
training time.
"""

from __future__ import annotations

import datetime
import hashlib
import io
import json
import math
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..files import atomic_output, one_line
from ..version import __version__
from .materials import MODS, PRE, ClassifyError, Dataset, FusedModel, make_classifier

MODEL_FORMAT = "dmdsm-classifier/2"
MAX_MEMBERS = 256                  # arrays in one model file
MAX_UNPACKED_BYTES = 512 << 20     # a file that unpacks to more is refused before reading
CHECK_ROWS = 16                    # training windows whose probabilities a BOSS refit must repeat
RETRAIN = "train one with `dmdsm classify train`"


@dataclass
class MiniRocketState:
    """A fitted MiniRocket + scaler + CalibratedRidge as arrays: features of each window,
    divided by the two feature scales, through the ridge, softmax at the fitted temperature."""

    parameters: tuple[np.ndarray, ...]   # aeon MiniRocket: channels, channel indices,
    scales: tuple[np.ndarray, ...]       # dilations, features per dilation, biases
    coef: np.ndarray
    intercept: np.ndarray
    classes_: np.ndarray
    temperature: float

    @classmethod
    def of(cls, clf: object) -> MiniRocketState:
        """The state of a fitted aeon MiniRocketClassifier built by make_classifier()."""
        scaler, ridge = clf.estimator_[0], clf.estimator_[-1]
        return cls(tuple(clf._transformer.parameters), (clf._scaler.scale_, scaler.scale_),
                   np.atleast_2d(ridge.coef_), np.atleast_1d(ridge.intercept_),
                   np.asarray(clf.classes_).astype(str),
                   float(ridge.scale_))

    def predict_proba(self, X: np.ndarray) -> np.ndarray:
        """(n, classes) probabilities of windows X (n, 1, window)."""
        from aeon.transformations.collection.convolution_based._minirocket import (
            MiniRocket,
            _static_transform_uni,
        )

        from .ridge import log_softmax, two_columns  # scikit-learn: imported when used

        f = _static_transform_uni(np.ascontiguousarray(X[:, 0, :], np.float32),
                                  self.parameters, MiniRocket._indices)
        for s in self.scales:  # as the pipeline's two StandardScaler(with_mean=False)
            f = (f / s).astype(np.float32)
        d = f @ self.coef.T + self.intercept
        return np.exp(log_softmax(two_columns(d) * self.temperature))

    def arrays(self, prefix: str) -> dict[str, np.ndarray]:
        """The state as named arrays."""
        out = {f"{prefix}.parameters.{i}": p for i, p in enumerate(self.parameters)}
        out.update({f"{prefix}.scales.{i}": s for i, s in enumerate(self.scales)})
        out.update({f"{prefix}.coef": self.coef, f"{prefix}.intercept": self.intercept,
                    f"{prefix}.classes": self.classes_,
                    f"{prefix}.temperature": np.array([self.temperature])})
        return out

    @classmethod
    def from_arrays(cls, a: dict[str, np.ndarray], prefix: str) -> MiniRocketState:
        """Inverse of arrays(); dtypes and shapes are checked against what aeon fits."""
        par = tuple(a[f"{prefix}.parameters.{i}"] for i in range(5))
        if [p.dtype for p in par] != [np.int32] * 4 + [np.float32] or \
                any(p.ndim != 1 for p in par):
            raise ValueError(f"{prefix}: MiniRocket parameters of the wrong type")
        scales = (a[f"{prefix}.scales.0"], a[f"{prefix}.scales.1"])
        coef = a[f"{prefix}.coef"]
        if coef.ndim != 2 or any(s.shape != (coef.shape[1],) for s in scales):
            raise ValueError(f"{prefix}: feature scales and ridge weights disagree")
        return cls(par, scales, coef, a[f"{prefix}.intercept"], a[f"{prefix}.classes"],
                   float(a[f"{prefix}.temperature"][0]))


def _digest(arrays: dict[str, np.ndarray]) -> str:
    """sha256 over every array's name, dtype, shape and bytes (sorted by name)."""
    h = hashlib.sha256()
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        h.update(f"{name}|{a.dtype.str}|{a.shape}|".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def save_model(model: FusedModel, ds: Dataset, path: Path) -> None:
    """Write the model and the provenance load_model() checks (atomically, files.atomic_output:
    a temporary file renamed over `path`; a device, FIFO or folder is refused)."""
    import aeon

    a: dict[str, np.ndarray] = {"classes": model.classes.astype(str), "prior": model.prior,
                                "pattern": model.pattern}
    for m, clf in model.models.items():
        a[f"{m}.mod_prior"] = model.mod_prior[m]
        if model.name == "minirocket":
            a.update(MiniRocketState.of(clf).arrays(m))
        else:  # BOSS: its training windows, and what a faithful refit must answer on them
            X, y = model.training[m]
            a.update({f"{m}.X": X.astype(np.float32), f"{m}.y": y.astype(str),
                      f"{m}.check": clf.predict_proba(X[:CHECK_ROWS, None, :])})
    if model.modality_model is not None:
        a.update(MiniRocketState.of(model.modality_model).arrays("which"))
    prov = {"format": MODEL_FORMAT, "fs_hz": ds.fs_hz, "window": ds.window, "pre": PRE,
            "classes": [str(c) for c in model.classes], "classifier": model.name,
            "modalities": list(model.modalities), "seed": model.seed,
            "n_average": ds.n_average, "scans": ds.scans, "points": len(ds),
            "dmdsm": __version__, "aeon": aeon.__version__,
            "created": datetime.datetime.now().isoformat(timespec="seconds"),
            "sha256": _digest(a)}
    a["provenance"] = np.frombuffer(json.dumps(prov).encode(), np.uint8)
    with atomic_output(path) as tmp, open(tmp, "wb") as f:
        np.savez_compressed(f, **a)


def _read_arrays(path: Path) -> dict[str, np.ndarray]:
    """Every array of an .npz, refusing pickles, zip bombs and object arrays."""
    with open(path, "rb") as f:
        head = f.read(4)
    if head[:1] == b"\x80":
        raise ClassifyError(f"{path} is a pickled model from dmdsm 0.1; pickles can run code, "
                            f"so it is not loaded: {RETRAIN}")
    if head != b"PK\x03\x04":
        raise ClassifyError(f"{path} is not a dmdsm classifier model: {RETRAIN}")
    with zipfile.ZipFile(path) as z:
        infos = z.infolist()
        if len(infos) > MAX_MEMBERS or sum(i.file_size for i in infos) > MAX_UNPACKED_BYTES \
                or any(not i.filename.endswith(".npy") for i in infos):
            raise ValueError("members beyond what a model holds")
        out = {}
        for i in infos:
            with z.open(i) as member:
                data = io.BytesIO(member.read(i.file_size + 1))
            version = np.lib.format.read_magic(data)
            shape, _, dtype = (np.lib.format.read_array_header_1_0 if version == (1, 0) else
                               np.lib.format.read_array_header_2_0)(data)
            if math.prod(shape) * dtype.itemsize > len(data.getbuffer()) - data.tell():
                raise ValueError(f"{i.filename} declares more data than it holds")
            data.seek(0)
            out[i.filename[:-4]] = np.lib.format.read_array(data, allow_pickle=False)
        return out


def read_model(path: Path) -> tuple[FusedModel, dict]:
    """A model file and its provenance (sample rate and window unchecked: see load_model)."""
    path = Path(path)
    try:
        a = _read_arrays(path)
        prov = json.loads(bytes(a.pop("provenance").astype(np.uint8)).decode())
        if not isinstance(prov, dict) or prov.get("format") != MODEL_FORMAT:
            raise ClassifyError(f"{path} is a model of another format "
                                f"({one_line(str(prov.get('format')), 40)}): {RETRAIN}")
        if prov.get("sha256") != _digest(a):
            raise ClassifyError(f"{path} is damaged (its arrays do not match their sha256): "
                                f"{RETRAIN}")
        return _rebuild(a, prov, path), prov
    except ClassifyError:
        raise
    except (OSError, zipfile.BadZipFile, zlib.error, KeyError, TypeError, ValueError,
            IndexError, EOFError, AttributeError,
            NotImplementedError,  # zipfile: a compression method it does not know
            RuntimeError) as e:   # zipfile: an encrypted member
        raise ClassifyError(f"{path} is not a readable dmdsm classifier model "
                            f"({type(e).__name__}: {one_line(str(e), 120)}); {RETRAIN}") from None


def _rebuild(a: dict[str, np.ndarray], prov: dict, path: Path) -> FusedModel:
    """The FusedModel the arrays describe (BOSS members refit and checked)."""
    prov["fs_hz"], prov["window"] = float(prov["fs_hz"]), int(prov["window"])
    name, mods = prov["classifier"], tuple(prov["modalities"])
    if name not in ("minirocket", "boss") or not mods or any(m not in MODS for m in mods):
        raise ValueError(f"classifier {name!r} over {mods!r}")
    seed = int(prov["seed"])
    models: dict[str, object] = {}
    for m in MODS:
        if f"{m}.mod_prior" not in a:
            continue
        if name == "minirocket":
            models[m] = MiniRocketState.from_arrays(a, m)
            continue
        X, y = a[f"{m}.X"], a[f"{m}.y"]
        if X.ndim != 2 or X.shape[0] != len(y) or X.shape[1] != int(prov["window"]):
            raise ValueError(f"{m}: training windows of the wrong shape")
        clf = make_classifier("boss", X.shape[1], seed).fit(X[:, None, :], y)
        if not np.allclose(clf.predict_proba(X[:CHECK_ROWS, None, :]), a[f"{m}.check"],
                           atol=1e-9):
            raise ClassifyError(f"{path} was trained with aeon {prov.get('aeon')}; this aeon "
                                f"fits BOSS differently, so it is not the same model: {RETRAIN}")
        models[m] = clf
    which = MiniRocketState.from_arrays(a, "which") if "which.coef" in a else None
    return FusedModel(name, a["classes"], models, a["prior"],
                      {m: a[f"{m}.mod_prior"] for m in models}, a["pattern"],
                      modalities=mods, modality_model=which, seed=seed)


def check_provenance(prov: dict, path: Path, fs_hz: float | None, window: int | None) -> None:
    """Refuse data the model was not trained for (another sample rate in Hz or window in
    samples); a check given None is not made."""
    if fs_hz is not None and abs(prov["fs_hz"] - fs_hz) > 1e-6 * fs_hz:
        raise ClassifyError(f"{path} was trained on {prov['fs_hz']:.0f} Hz data, these "
                            f"waveforms are {fs_hz:.0f} Hz: retrain on data at this rate")
    if window is not None and (prov["window"] != window or prov.get("pre", PRE) != PRE):
        raise ClassifyError(f"{path} was trained on {prov['window']}-sample windows, not "
                            f"{window}: pass --window {prov['window']} or retrain")


def load_model(path: Path, fs_hz: float | None = None, window: int | None = None
               ) -> tuple[FusedModel, dict]:
    """A model file and its provenance (classes, sample rate `fs_hz`, `window`, training
    data); given fs_hz (Hz) or window (samples), data of another one is refused."""
    model, prov = read_model(path)
    check_provenance(prov, path, fs_hz, window)
    return model, prov
