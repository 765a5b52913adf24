"""Scanning: plans, the step-and-shoot and fly executors, scan files and their catalogue, and the
reconstruction of points in the object frame (paper §V)."""

from ..ranging.point import PointRanger
from .catalogue import CatalogueError, find_scan, list_scans
from .common import ScanStats
from .executor import run_scan
from .fly_executor import FlyRun, run_fly_scan
from .plan import PlanError, ScanPlan, expand, load_plan, point_ranger
from .points import scan_points, validate_block
from .reconstruct import fit_box, object_points, stage_points
from .scanfile import ScanData, ScanFileError, ScanWriter, read_scan
from .session import ScanRun, checked_points, finished_scan, run_plan

__all__ = [
    "CatalogueError", "expand", "find_scan", "fit_box", "list_scans", "load_plan", "object_points",
    "PlanError", "PointRanger", "read_scan", "run_plan", "run_scan", "scan_points", "ScanData",
    "ScanFileError", "ScanPlan", "ScanRun", "ScanStats", "ScanWriter", "stage_points",
    "validate_block", "checked_points", "finished_scan", "FlyRun", "point_ranger",
    "run_fly_scan",
]
