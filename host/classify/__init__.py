"""Material classification (paper §V-B2): OA/US windows from scans, BOSS and MiniRocket fused
by probability, model files, and the vote for one object."""

from .materials import ClassifyError, Dataset, assemble, evaluate_loo, evaluate_random, fit
from .model_file import load_model, save_model
from .predict import predict_scan, vote

__all__ = [
    "assemble", "ClassifyError", "Dataset", "evaluate_loo", "evaluate_random", "fit", "load_model",
    "predict_scan", "save_model", "vote",
]
