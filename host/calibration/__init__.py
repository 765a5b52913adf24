"""Scanner calibration (paper §IV): v, n and X_R from center points of the rig (pure), the
rig procedure that records raw points, and the files of both."""

from .center_points import center_points
from .procedure import RigPlan, scan_rig
from .result import load_calibration, result_dict, write_result
from .rig_file import RawWriter, read_raw
from .solver import CalibrationData, CalibrationError, CalibrationResult, cramer_rao_bound, solve

__all__ = [
    "CalibrationData", "CalibrationError", "CalibrationResult", "center_points",
    "cramer_rao_bound", "load_calibration", "RawWriter", "read_raw", "result_dict", "RigPlan",
    "scan_rig", "solve", "write_result",
]
