"""Shared fixtures: hypothesis profile and the ASan-built C protocol tool."""

import os
import subprocess
from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings

ROOT = Path(__file__).resolve().parents[1]

settings.register_profile(
    "ci", deadline=None, suppress_health_check=[HealthCheck.too_slow], print_blob=True)
settings.load_profile("ci")


@pytest.fixture(scope="session")
def proto_tool() -> Path:
    """Path of tests/c/proto_tool built with sanitizers (built on demand)."""
    path = Path(os.environ.get("DMDSM_PROTO_TOOL", ROOT / "build/host/proto_tool"))
    if not path.exists():
        subprocess.run(["make", "-C", str(ROOT), "build/host/proto_tool"], check=True)
    return path


from emulator_fixture import emulator  # noqa: E402,F401  (hil_sim on ptys, one per test)
