"""The physics database the classifier learns from: standing and fly positions, averaged as
the board averages (issue 33: a fly-scanned object's materials)."""

import numpy as np
import pytest

from dmdsm.host.classify.materials import scan_dataset
from dmdsm.host.scan.scanfile import read_scan
from dmdsm.sim.boards.sensor.core_board import averaged_shots
from dmdsm.sim.data.dataset import main, make_database
from dmdsm.sim.physics.objects import household
from dmdsm.sim.physics.scene import Scene
from dmdsm.sim.physics.signals import SensorModel


def test_a_sensor_standing_still_is_one_hit_per_shot_or_one_for_all():
    scene = Scene(objects=household("soda_can"))
    hit = scene.cast(scene.X_R - 40.0 * scene.v / np.linalg.norm(scene.v)
                     + np.array([0.0, 0.0, 50.0]), 0.0)
    one = averaged_shots(hit, SensorModel(), 256, 6, np.random.default_rng(3), seed=2)
    each = averaged_shots([hit] * 6, SensorModel(), 256, 6, np.random.default_rng(3), seed=2)
    np.testing.assert_array_equal(one[0], each[0])
    assert one[1] == each[1]
    with pytest.raises(ValueError):  # a hit per shot or none: never a silent short average
        averaged_shots([hit] * 5, SensorModel(), 256, 6, np.random.default_rng(3))


def test_fly_lines_smear_the_pulse_a_standing_sensor_keeps(tmp_path):
    """On a round object the depth changes over a fly waveform's travel, so its averaged OA
    pulse is spread in time: less of it matches the standing pulse (ranging's SNR) and its
    peak stands lower over the window's RMS than at the same places standing (one seed: the
    same lines, heights and angles). A classifier that learnt only standing pulses read the
    fly-scanned bottle's as apple on 9-16 % of its vertices (bench/model.py)."""
    (still,) = make_database(tmp_path / "still", points=32, seed=4, objects=["soda_can"])
    (fly,) = make_database(tmp_path / "fly", points=32, seed=4, objects=["soda_can"],
                           fly_mm=8.0)
    a, b = (read_scan(p, waveforms=True) for p in (still, fly))
    np.testing.assert_array_equal(a.points["stage_position_mm"], b.points["stage_position_mm"])
    wa, wb = scan_dataset(a), scan_dataset(b)
    both = wa.has["oa"] & wb.has["oa"]
    assert both.sum() >= 10
    snr = a.points["snr_oa_db"][both] - b.points["snr_oa_db"][both]
    crest = np.abs(wa.X["oa"][both]).max(axis=1) - np.abs(wb.X["oa"][both]).max(axis=1)
    assert np.median(snr) > 6.0, snr  # 15 dB here
    assert np.mean(crest > 0) > 2 / 3, crest


def test_the_generator_command_refuses_a_travel_it_cannot_mean(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        main(["--out", str(tmp_path / "db"), "--points", "8", "--fly-mm", "-1"])
    assert e.value.code == 2 and "--fly-mm must be 0..20 mm" in capsys.readouterr().err
