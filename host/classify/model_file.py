"""Classifier model files: the fitted model with the provenance a prediction checks."""

from __future__ import annotations

import datetime
import pickle
from pathlib import Path

from .. import __version__
from .materials import (
    PRE,
    ClassifyError,
    Dataset,
)

MODEL_FORMAT = "dmdsm-classifier/1"


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
