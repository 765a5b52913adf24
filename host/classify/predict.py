"""Material of a scanned object: a model's probabilities per waveform, combined into one vote."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..scan.scanfile import ScanFileError, read_scan
from .materials import WINDOW, ClassifyError, FusedModel, assemble
from .model_file import check_provenance, load_model


def vote(classes: np.ndarray, prob: np.ndarray, source: str) -> dict:
    """The material with the highest mean probability over the waveforms (rows of prob),
    its confidence (that mean, 0..1), the per-class votes and mean probabilities."""
    mean = prob.mean(axis=0)
    best = int(mean.argmax())
    return {"source": source, "material": str(classes[best]),
            "confidence": float(mean[best]), "points": len(prob),
            "votes": {str(c): int(v) for c, v in zip(classes, np.bincount(
                prob.argmax(axis=1), minlength=len(classes))) if v},
            "probabilities": {str(c): float(p) for c, p in zip(classes, mean)}}


def predict_scan(model: Path | str | tuple[FusedModel, dict], scan_path: Path,
                 window: int | None = None) -> dict:
    """Classify the object of one scan file (see `vote` for the result) with a model file or
    what `load_model` returned; windows of the model's own length unless `window` (samples)
    is given. Raises ClassifyError if the file is not a scan or has no windows the model
    can use."""
    try:
        read_scan(scan_path)
    except ScanFileError as e:
        raise ClassifyError(str(e)) from None
    if isinstance(model, (str, Path)):
        model_path = Path(model)
        model, prov = load_model(model_path)
    else:
        model_path = Path("<the model given>")
        model, prov = model
    ds = assemble([Path(scan_path)], window or prov.get("window", WINDOW))
    check_provenance(prov, model_path, ds.fs_hz, ds.window)
    ds = ds.subset(ds.usable(model.modalities))
    if not len(ds):
        raise ClassifyError(f"{scan_path} has no {'/'.join(model.modalities).upper()} "
                            f"windows for this model")
    return vote(model.classes, model.predict_proba(ds), str(scan_path))
