"""Data made straight from the physics without a serial link: scan databases and rig
calibration data, for tests and benchmarks."""

