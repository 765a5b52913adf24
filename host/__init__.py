"""The dmdsm host as a Python API: open the boards, calibrate, scan, reconstruct, classify.

The layers, top to bottom (docs/architecture.md): `entry` (the `dmdsm` command) -> `demo` ->
`commands` -> `report` -> `model` -> `classify` -> `scan` -> `calibration` -> `ranging` ->
`links` -> `files` | `version`.
This face exports the objects a notebook composes; they load on first use, so importing
one submodule does not import the whole pipeline. The procedures take any stage and sensor
that satisfy the Protocols Stage / StageMotion and Sensor / ShotSensor / StreamSensor (the
clients do; so may a notebook's own simulation).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

from .version import __version__

_EXPORTS = {  # name -> subpackage (or module) that defines it
    "SensorClient": "links", "StageClient": "links", "LinkError": "links",
    "UnsafeMove": "links", "Stage": "links", "StageMotion": "links", "Sensor": "links",
    "ShotSensor": "links", "StreamSensor": "links",
    "RangingSetup": "ranging", "MatchedFilter": "ranging", "calibrate_range": "ranging",
    "load_calibration": "calibration", "solve": "calibration", "read_raw": "calibration",
    "center_points": "calibration", "CalibrationError": "calibration",
    "CalibrationResult": "calibration",
    "ScanPlan": "scan", "load_plan": "scan", "run_plan": "scan", "read_scan": "scan",
    "scan_points": "scan", "validate_block": "scan", "list_scans": "scan",
    "predict_scan": "classify", "assemble": "classify", "fit": "classify",
    "load_model": "classify", "save_model": "classify",
    "read_model": "model", "load_object_model": "model", "ObjectModel": "model",
    "list_models": "model",
    "live": "robotics.live", "LiveRecord": "robotics.live",
    "export_scan_mcap": "robotics.scan_export",
}
__all__ = [  # the names of _EXPORTS, listed for tools that read __all__ literally
    "__version__", "SensorClient", "StageClient", "LinkError", "UnsafeMove", "Stage",
    "StageMotion", "Sensor", "ShotSensor", "StreamSensor", "RangingSetup",
    "MatchedFilter", "calibrate_range", "load_calibration", "solve", "read_raw", "center_points",
    "CalibrationError", "CalibrationResult", "ScanPlan", "load_plan", "run_plan", "read_scan",
    "scan_points", "validate_block", "list_scans", "predict_scan", "assemble", "fit",
    "load_model", "save_model", "read_model", "load_object_model", "ObjectModel", "list_models",
    "live", "LiveRecord", "export_scan_mcap",
]

if TYPE_CHECKING:  # for type checkers and IDEs; at run time names load in __getattr__
    from .calibration import (
        CalibrationError,
        CalibrationResult,
        center_points,
        load_calibration,
        read_raw,
        solve,
    )
    from .classify import assemble, fit, load_model, predict_scan, save_model
    from .links import (
        LinkError,
        Sensor,
        SensorClient,
        ShotSensor,
        Stage,
        StageClient,
        StageMotion,
        StreamSensor,
        UnsafeMove,
    )
    from .model import ObjectModel, list_models, load_object_model, read_model
    from .ranging import MatchedFilter, RangingSetup, calibrate_range
    from .robotics.live import LiveRecord, live
    from .robotics.scan_export import export_scan_mcap
    from .scan import (
        ScanPlan,
        list_scans,
        load_plan,
        read_scan,
        run_plan,
        scan_points,
        validate_block,
    )


def __getattr__(name: str) -> object:
    """Load an exported name from its subpackage on first use (PEP 562)."""
    if name in _EXPORTS:
        value = getattr(importlib.import_module(f".{_EXPORTS[name]}", __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(__all__)
