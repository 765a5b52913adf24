"""The Marlin patch: every kind of edit, idempotence, refusals, and one source of truth."""

import functools
import operator
import shutil
import subprocess
import sys
from functools import reduce
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dmdsm.marlin_patch import MINIMAL_STEP_RATE, checksum, load_machine, numbered
from dmdsm.marlin_patch.apply import PatchError, apply_config, plan
from dmdsm.marlin_patch.settings import SETTINGS_PATH, load_settings

ROOT = Path(__file__).resolve().parents[1]
FIXTURE = ROOT / "tests/data/marlin"


@pytest.fixture
def checkout(tmp_path):
    dst = tmp_path / "Marlin-checkout"
    shutil.copytree(FIXTURE, dst)
    return dst


def text(checkout, name="Configuration.h"):
    return (checkout / "Marlin" / name).read_text()


def test_every_kind_of_edit_lands(checkout):
    changes = apply_config(checkout)
    cfg, adv = text(checkout), text(checkout, "Configuration_adv.h")
    assert "#define EXTRUDERS 0\n" in cfg                                  # set, was enabled
    assert "#define I_DRIVER_TYPE  A4988\n" in cfg                          # set, was commented
    assert "//#define E0_DRIVER_TYPE A4988\n" in cfg                        # disable
    assert "//#define PIDTEMP           // PID for the hotend\n" in cfg     # disable keeps comment
    assert "#define DEFAULT_AXIS_STEPS_PER_UNIT   { 80, 100, 400, 8.8889 }\n" in cfg
    assert "#define I_HOME_DIR 0\n" in cfg and "#define MANUAL_I_HOME_POS 0\n" in cfg
    assert "#define M114_REALTIME       // real position\n" in adv            # enable
    assert "#define HOMING_BUMP_MM      { 5, 5, 2, 10 }       // backoff\n" in adv
    assert "#define TX_BUFFER_SIZE 32\n" in adv
    assert "//#define PIDTEMPBED\n" in cfg                                  # already off
    assert len(changes) == 44


def test_reapplying_changes_nothing(checkout):
    apply_config(checkout)
    before = text(checkout) + text(checkout, "Configuration_adv.h")
    assert apply_config(checkout) == []
    assert text(checkout) + text(checkout, "Configuration_adv.h") == before


def test_a_missing_line_refuses_and_writes_nothing(checkout):
    path = checkout / "Marlin/Configuration.h"
    original = path.read_text().replace("#define SPEAKER\n", "")
    path.write_text(original)
    adv_before = text(checkout, "Configuration_adv.h")
    with pytest.raises(PatchError, match="no '#define SPEAKER' line"):
        apply_config(checkout)
    assert path.read_text() == original and text(checkout, "Configuration_adv.h") == adv_before


def test_a_required_value_that_differs_refuses(checkout):
    path = checkout / "Marlin/Configuration.h"
    path.write_text(path.read_text().replace("BAUDRATE 250000", "BAUDRATE 115200"))
    with pytest.raises(PatchError, match="BAUDRATE is '115200', expected '250000'"):
        apply_config(checkout)


def test_other_marlin_versions_are_refused_unless_forced(checkout):
    v = checkout / "Marlin/src/inc/Version.h"
    v.write_text(v.read_text().replace("bugfix-2.1.x", "2.1.2.5"))
    with pytest.raises(PatchError, match="Marlin is 2.1.2.5, this patch targets bugfix-2.1.x"):
        apply_config(checkout)
    assert apply_config(checkout, force=True)
    v.write_text(v.read_text().replace("2.1.2.5", "bugfix-2.1.x"))
    c = checkout / "Marlin/Configuration.h"
    c.write_text(c.read_text().replace("02010300", "02010205"))
    with pytest.raises(PatchError, match="CONFIGURATION_H_VERSION is 02010205"):
        apply_config(checkout)


def test_duplicate_defines_are_refused(checkout):
    c = checkout / "Marlin/Configuration.h"
    c.write_text(c.read_text() + "#define SPEAKER\n")
    with pytest.raises(PatchError, match="appears 2 times"):
        apply_config(checkout)


def test_dry_run_writes_nothing(checkout):
    before = text(checkout)
    assert apply_config(checkout, dry_run=True)
    assert text(checkout) == before


def test_patch_and_machine_limits_come_from_one_file(tmp_path):
    changed = tmp_path / "settings.toml"
    changed.write_text(SETTINGS_PATH.read_text().replace(
        "steps_per_unit = [80, 100, 400, 8.8889]", "steps_per_unit = [80, 100, 400, 44.4444]"))
    assert load_machine(changed).steps_per_unit[3] == 44.4444
    (edit,) = [e for e in plan(load_settings(changed)) if e.name == "DEFAULT_AXIS_STEPS_PER_UNIT"]
    assert edit.value == "{ 80, 100, 400, 44.4444 }"
    assert load_machine().steps_per_unit[3] == 8.8889


def test_script_runs_standalone_with_one_line_errors(checkout, tmp_path):
    script = ROOT / "firmware/marlin_patch/apply.py"
    r = subprocess.run([sys.executable, str(script), str(checkout)], capture_output=True,
                       text=True)
    assert r.returncode == 0 and "changed 44 settings; all 61 verified" in r.stdout
    r = subprocess.run([sys.executable, str(script), str(tmp_path / "nowhere")],
                       capture_output=True, text=True)
    assert r.returncode == 2
    assert r.stderr.startswith("apply.py: error: no Configuration.h")
    assert len(r.stderr.strip().splitlines()) == 1


def test_the_emulator_follows_the_settings_file(tmp_path):
    from dmdsm.marlin_patch import checksum
    from dmdsm.sim.boards.stage.marlin import MarlinEmulator

    changed = tmp_path / "settings.toml"
    changed.write_text(SETTINGS_PATH.read_text().replace(
        "steps_per_unit = [80, 100, 400, 8.8889]", "steps_per_unit = [80, 100, 400, 20]"))
    for path, steps in ((SETTINGS_PATH, 800), (changed, 1800)):
        m = MarlinEmulator(load_machine(path))
        for n, cmd in enumerate(["G1 A90 F6000", "M400", "M114"], 1):
            body = f"N{n} {cmd}"
            m.receive(f"{body}*{checksum(body)}\n".encode(), 0.0)
        out = m.step(10.0).decode()
        # X counts from its power-up home position, X_MIN_POS -10 mm, at 80 steps/mm
        assert f"Count X:-800 Y:0 Z:0 A:{steps}" in out


def test_the_host_envelope_follows_the_settings_file(tmp_path):
    import numpy as np

    from dmdsm.host.links.safety import UnsafeMove, check_move

    changed = tmp_path / "settings.toml"
    changed.write_text(SETTINGS_PATH.read_text().replace(
        "max_pos = [410, 410, 455, 360]", "max_pos = [300, 410, 455, 360]"))
    start, target = np.zeros(3), np.array([350.0, 0, 0])
    check_move(start, target, load_machine())
    with pytest.raises(UnsafeMove, match="X350 is outside the machine envelope"):
        check_move(start, target, load_machine(changed))


@given(st.integers(0, 2**31 - 1), st.text(st.characters(min_codepoint=32, max_codepoint=126,
                                                         exclude_characters="*;"), max_size=80))
def test_a_numbered_line_carries_marlins_checksum(n, command):
    # Marlin (GCodeQueue::get_serial_commands) XORs every byte before '*', then compares
    line = numbered(n, command)
    body, _, tail = line.rstrip("\n").rpartition("*")
    assert body == f"N{n} {command}" and line.endswith("\n")
    assert int(tail) == reduce(operator.xor, body.encode(), 0) == checksum(body) < 256


@settings(max_examples=300, deadline=None)
@given(body=st.text(st.characters(min_codepoint=32, max_codepoint=126)) | st.text())
def test_checksum_is_marlins_xor_of_the_bytes_before_the_last_star(body):
    """queue.cpp: strrchr(command, '*'), then XOR of every byte before it."""
    line = f"{body}*{checksum(body)}"
    before, _, after = line.rpartition("*")
    assert int(after) == functools.reduce(operator.xor, before.encode(), 0)
    assert 0 <= checksum(body) <= 255


def test_checksum_of_the_reprap_example_and_one_definition_for_host_and_emulator():
    from dmdsm.host.links import stage
    from dmdsm.host.scan import fly
    from dmdsm.sim.boards.stage import block, marlin

    assert checksum("N3 T0") == 57  # the RepRap G-code page's example line `N3 T0*57`
    assert marlin.checksum is checksum and stage.numbered is numbered
    assert fly.MINIMAL_STEP_RATE is block.MINIMAL_STEP_RATE is MINIMAL_STEP_RATE
    limits = load_machine()
    assert (stage.RX_BUFFER, stage.MAX_LINE) == (limits.rx_buffer_size - 1,
                                                 limits.max_cmd_size - 1)
