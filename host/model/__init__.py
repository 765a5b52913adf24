"""3D models of scanned objects: an object's scans fused into points with covariances, a closed
surface with sigma, coverage and material per vertex, stored per object and version."""

from .store import (
    ModelError,
    ObjectModel,
    list_models,
    load_object_model,
    read_model,
    staleness,
    write_model,
)

__all__ = ["ModelError", "ObjectModel", "list_models", "load_object_model", "read_model",
           "staleness", "write_model"]
