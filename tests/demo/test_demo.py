"""The full demo end to end (`make demo`, the user's first command, with the same plans), its
report's figures checked against the paper's targets and its ± against the emulator's truth."""

import json
import subprocess
import sys

import numpy as np
import pytest  # noqa: E402

from dmdsm.host.scan.plan import modality_for

pytestmark = pytest.mark.realtime  # serves the emulator in a subprocess, in real time

PAPER = {"oa": (0.06, 0.06), "us": (0.15, 0.11)}


def test_demo_meets_the_paper_and_writes_the_report(tmp_path):
    out = tmp_path / "out"
    # a hang fails on the timeout; the wall time itself is a figure the demo prints (summary
    # "seconds"), not checked here: beside the other tests on 2 cores it took 2308 s with
    # stage 6's campaign at four levels and `make check-marlin` running too; beside them and
    # two busy loops it ran past 3600 s (2026-12-07, killed in its sweep stage): the guard is
    # against a hang, so it is 2 h, beyond CI's whole run
    r = subprocess.run([sys.executable, "-m", "dmdsm.host", "demo", "--out", str(out)],
                       capture_output=True, text=True, timeout=7200)
    assert (out / "summary.json").is_file(), (r.returncode, r.stdout[-3000:], r.stderr[-3000:])
    summary = json.loads((out / "summary.json").read_text())
    st = summary["stages"]
    assert st["1"]["ok"], r.stdout + r.stderr
    for m in ("oa", "us"):  # the ranging calibration's t0 within 4 of its std of the truth
        assert abs(st["1"]["values"][m]["z"]) < 4, st["1"]["values"]
    rig = st["2"]["values"]
    assert rig["v_error_deg"] < 2.0 and rig["n_error_deg"] < 0.5 and rig["X_R_error_mm"] < 0.3
    for m, (mean, std) in PAPER.items():
        v = st["3"]["values"][m]
        g = v["true_parameters"]
        # ranging + scanning + reconstruction: the paper's figure within 3 standard errors
        assert g["e_mean_mm"] <= mean + 3 * g["e_std_mm"] / np.sqrt(g["n"]), (m, g)
        assert g["e_std_mm"] <= std + 3 * g["e_std_mm"] / np.sqrt(2 * (g["n"] - 1)), (m, g)
        # with the rig calibration of stage 2
        assert v["calibrated"]["e_mean_mm"] <= mean + 3 * g["e_std_mm"] / np.sqrt(g["n"]), v
        # each distance's own std holds: e over it has an RMS near 1
        assert 0.7 < g["e_over_std_rms"] < 1.4, (m, g)
    house = st["4"]["values"]
    assert {h["material"] for h in house.values()} == {
        "aluminium", "apple", "foam", "glass", "paper", "plastic", "steel"}
    for name, h in house.items():  # the paper's Fig. 4 first row: which modality works
        want_oa = h["material"] not in ("glass", "steel")
        want_us = h["material"] != "foam"
        assert (h["oa_points"] > 0) == want_oa and (h["us_points"] > 0) == want_us, (name, h)
        assert max(h["oa_points"], h["us_points"]) >= 0.5 * h["points"], (name, h)
        fly = h["fly"]  # the same object fly-scanned: the same modalities work
        assert (fly["oa_points"] > 0) == want_oa and (fly["us_points"] > 0) == want_us, (name,
                                                                                       fly)
    rates = summary["household_points_per_s"]
    assert set(rates) == {"step", "fly"} and min(rates.values()) > 0, rates
    cls = st["5"]["values"]
    for name in ("minirocket", "boss"):  # seven materials told apart well above chance (1/7)
        acc = cls[name]["random"]
        assert set(acc) == {"aluminium", "apple", "foam", "glass", "paper", "plastic", "steel"}
        assert np.mean(list(acc.values())) >= 0.6, (name, acc)
    assert np.nanmean(list(cls["minirocket"]["loo"].values())) >= 0.5, cls["minirocket"]
    models = st["6"]["values"]  # the campaign: a model of one object per material
    assert {m["campaign"]["material"] for m in models.values()} == {
        "aluminium", "apple", "foam", "glass", "paper", "plastic", "steel"}
    for name, m in models.items():
        assert m["campaign"]["status"] == "scanned", (name, m["campaign"])
        assert m["truth"]["vertices"] > 0, (name, m["truth"])
        # the sigma with all of the calibration's part and with none of it bracket the
        # error (two full demos of 2026-12-06: as built 0.60-1.04, apart 0.93-1.34)
        assert m["truth"]["z_rms"] < 1.4 and 0.7 < m["truth"]["z_rms_own"] < 1.6, \
            (name, m["truth"])
        auto, fixed = m["coverage_truth"]["auto"], m["coverage_truth"].get("step", {})
        assert max(auto.values()) > max(fixed.values(), default=0), (name, m["coverage_truth"])
        # the same band swept: the laser busy from its first waveform to its last, and the
        # surface covered in it
        assert m["laser_duty_span"]["sweep"] >= 0.5, (name, m["laser_duty_span"])
        # in each modality the material answers in, of the truth in the sweep's own band
        # (2026-12-06, code 7956017: 98.9-100 %; the tissue box's US 64.7 % before its
        # passes and standoff came from reach.box_passes)
        modality = modality_for(m["campaign"]["material"])
        for mod in ("oa", "us") if modality == "both" else (modality,):
            assert m["coverage_levels"]["sweep"][mod] >= 0.95, (name, m["coverage_levels"])
    assert r.returncode == 0 and all(s["ok"] for s in st.values()), r.stdout[-2000:]
    html = (out / "report.html").read_text()
    # Fig. 2, Fig. 3, seven Fig. 4s, three Fig. 5s
    assert html.count("data:image/png;base64,") >= 12
    assert html.count('class="dmdsm-model"') == len(models)  # a 3D view per model
    assert "Table I" in html and "0.06 ± 0.06" in html


def test_the_quick_demo_ends_green(tmp_path):
    """`dmdsm demo --quick`, the first look the help offers, ends with every stage ok and exit
    0 on a machine where nothing is broken. It failed two stages by chance: its ranging fit
    on 24 spots put the block's RMS e / point std at 1.49 (0.5-1.6 over seeds), and one of
    BOSS's six glass windows missed (5/6 < 85 %)."""
    out = tmp_path / "out"
    r = subprocess.run([sys.executable, "-m", "dmdsm.host", "demo", "--quick", "--out",
                        str(out)], capture_output=True, text=True, timeout=1800)
    assert (out / "summary.json").is_file(), (r.returncode, r.stdout[-3000:], r.stderr[-3000:])
    st = json.loads((out / "summary.json").read_text())["stages"]
    failed = {k: s["status"] + ": " + "; ".join(c["what"] + " " + c["value"] for c in s["checks"]
                                                 if not c["passed"])
              for k, s in st.items() if not s["ok"]}
    assert r.returncode == 0 and not failed, (failed, r.stdout[-2000:])
    assert 0.7 < st["3"]["values"]["oa"]["true_parameters"]["e_over_std_rms"] < 1.4
