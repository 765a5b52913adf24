"""3D models of scanned objects: an object's scans fused into points with covariances, a closed
surface with sigma, coverage and material per vertex, stored per object and version."""
