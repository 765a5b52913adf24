"""Shared fixtures: hypothesis profile, the ASan-built C protocol tool, and the `realtime` mark.

A test that serves the emulator in wall-clock time (an `Emulator` thread, `dmdsm sim` or the
demo in a subprocess, a board under test) is slow and is marked `realtime`; `make test-fast`
leaves those out. Tests that use the emulator fixtures are marked here; any other test that
starts an `Emulator` in this process without the mark fails, so the fast loop stays fast."""

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

from dmdsm.sim.servers.emulator import Emulator  # noqa: E402

# fixtures that serve a board in real time (tests/emulator_fixture.py, tests/stage/conftest.py,
# tests/conformance/conftest.py)
REALTIME_FIXTURES = {"emulator", "stage_url", "sensor_url", "stage_sim"}
_running: dict = {"item": None, "unmarked_starts": []}


def pytest_collection_modifyitems(items: list) -> None:
    """Mark every test that uses a real-time fixture `realtime`."""
    for item in items:
        if REALTIME_FIXTURES & set(getattr(item, "fixturenames", ())):
            item.add_marker(pytest.mark.realtime)


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item) -> None:
    """Remember which test runs, before its fixtures start anything."""
    _running["item"] = item
    _running["unmarked_starts"].clear()


_start = Emulator.start


def _checked_start(self: Emulator) -> Emulator:
    item = _running["item"]
    if item is not None and item.get_closest_marker("realtime") is None:
        _running["unmarked_starts"].append(item.nodeid)
    return _start(self)


Emulator.start = _checked_start  # type: ignore[method-assign]


@pytest.fixture(autouse=True)
def _realtime_is_marked():
    """Fail a test that served the emulator in real time without the `realtime` mark."""
    yield
    assert not _running["unmarked_starts"], (
        "this test serves the emulator in real time: mark it @pytest.mark.realtime "
        "(or use the emulator fixture)")
