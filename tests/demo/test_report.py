"""The demo's report: Figs. 3-4 show their points (a flat face as a row of points, no line
that is not data, the legend off the data), and a stage's status comes from stated criteria:
"ok" only when every figure meets its target, otherwise FAILED naming the figure that missed."""

import json

import matplotlib
import numpy as np
import pytest

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from dmdsm.host.report import plots  # noqa: E402
from dmdsm.host.report.page import Section, html_page, markdown  # noqa: E402

EMPTY = {"P": np.zeros((0, 3)), "level": np.zeros(0, int)}


def _pts(oa: np.ndarray, us: np.ndarray | None = None) -> dict:
    def mod(P):
        if P is None:
            return EMPTY
        return {"P": np.asarray(P, float), "level": np.zeros(len(P), int)}
    return {"oa": mod(oa), "us": mod(us)}


@pytest.fixture
def figures(monkeypatch):
    """The figures contour_figure draws, kept open (it closes them after saving)."""
    kept, close = [], plt.close
    monkeypatch.setattr(plt, "close", lambda fig=None: kept.append(fig or plt.gcf()))
    yield kept
    for fig in kept:
        close(fig)


def _draw(figures, pts, tmp_path, **kw):
    plots.contour_figure(pts, tmp_path / "fig.png", **kw)
    assert (tmp_path / "fig.png").stat().st_size > 0
    fig = figures[-1]
    fig.canvas.draw()
    return fig, fig.axes[0], fig.canvas.get_renderer()


def _display(ax, P):
    return ax.transData.transform(np.asarray(P, float)[:, :2] / 10.0)  # mm -> cm -> pixels


def _segments(ax):
    """Every drawn line segment (cm) but one-point markers."""
    out = []
    for line in ax.get_lines():
        xy = np.column_stack(line.get_data())
        out += [(xy[i], xy[i + 1]) for i in range(len(xy) - 1)]
    return out


def _no_overlap(boxes):
    boxes = [b for b in boxes if b.width > 0]
    return all(not a.overlaps(b) for i, a in enumerate(boxes) for b in boxes[i + 1:])


def test_a_flat_face_shows_its_points_across_a_square_panel(figures, tmp_path):
    """foam_block's quick Fig. 4: one sweep over a flat face (a straight row of points)
    collapsed to a line with overlapping labels; it must show each point, spread."""
    rng = np.random.default_rng(0)
    x = np.arange(-33.5, 32.0, 8.0)
    P = np.column_stack([x, -49.75 + rng.normal(0, 0.08, len(x)), np.full(len(x), 23.0)])
    fig, ax, r = _draw(figures, _pts(P), tmp_path, title="foam_block")
    box = ax.get_window_extent(r)
    assert 0.8 < box.height / box.width < 1.25, (box.width, box.height)  # not a strip
    assert box.height > 0.4 * fig.bbox.height
    d = _display(ax, P)
    assert box.contains(*d.min(axis=0)) and box.contains(*d.max(axis=0))  # all inside
    assert np.ptp(d[:, 0]) > 0.6 * box.width  # the row spans the panel
    assert np.min(np.diff(np.sort(d[:, 0]))) > 10  # each point apart from the next (px)
    for axis in (ax.xaxis, ax.yaxis):  # tick labels readable, none over another
        labels = [t.get_window_extent(r) for t in axis.get_ticklabels() if t.get_text()]
        assert len(labels) >= 3 and _no_overlap(labels)


def test_a_sweep_is_an_open_line_and_a_ring_a_closed_one(figures, tmp_path):
    """The round objects' quick Fig. 4 had a line from the last point back to the first; a
    contour is closed only where the points go all the way round."""
    a = np.radians(np.arange(-125.0, -55.0, 14.0))  # one table angle: a sweep of a can
    arc = 33.0 * np.column_stack([np.cos(a), np.sin(a), np.zeros(len(a))])
    arc[:, 2] = 39.0
    fig, ax, r = _draw(figures, _pts(arc, arc + [0.2, 0.1, 0]), tmp_path, title="soda_can")
    step = np.linalg.norm(arc[1, :2] - arc[0, :2]) / 10.0
    lengths = [np.linalg.norm(b - a) for a, b in _segments(ax)]
    assert lengths and max(lengths) < 1.5 * step, (max(lengths), step)  # no closing line
    b = np.radians(np.arange(0.0, 360.0, 10.0))  # four angles: all the way round
    ring = np.column_stack([33.0 * np.cos(b), 33.0 * np.sin(b), np.full(len(b), 39.0)])
    fig, ax, r = _draw(figures, _pts(ring), tmp_path, title="soda_can")
    closed = [line for line in ax.get_lines() if len(line.get_xdata()) > 2]
    assert len(closed) == 1
    xy = np.column_stack(closed[0].get_data())
    assert np.allclose(xy[0], xy[-1]) and len(xy) == len(ring) + 1
    box, d = ax.get_window_extent(r), _display(ax, ring)
    assert np.ptp(d[:, 0]) > 0.6 * box.width and np.ptp(d[:, 1]) > 0.6 * box.height


def test_the_block_legend_hides_no_data(figures, tmp_path):
    """Fig. 3: the legend sat in the upper right corner over the block's points."""
    from dmdsm.host.scan.points import validate_block

    rng = np.random.default_rng(1)
    s = np.linspace(-1, 1, 13)
    edges = [np.column_stack([25 * s, np.full(13, 15.0)]),
             np.column_stack([25 * s, np.full(13, -15.0)]),
             np.column_stack([np.full(13, 25.0), 15 * s]),
             np.column_stack([np.full(13, -25.0), 15 * s])]
    xy = np.vstack(edges)
    P = np.column_stack([xy + rng.normal(0, 0.05, xy.shape), np.full(len(xy), 18.0)])
    pts = _pts(P, P + rng.normal(0, 0.1, P.shape))
    for m in pts:
        pts[m]["d_std"] = np.full(len(P), 0.1)
    fits = validate_block(pts, (50.0, 30.0))
    fig, ax, r = _draw(figures, pts, tmp_path, size_xy=(50.0, 30.0), fits=fits,
                       title="aluminium_block")
    legend = ax.get_legend().get_window_extent(r).padded(2)
    for m in ("oa", "us"):
        d = _display(ax, pts[m]["P"])
        inside = [legend.contains(x, y) for x, y in d]
        assert not any(inside), f"{sum(inside)} {m} points under the legend"


def test_neighbour_segments_break_at_gaps():
    P = np.array([[-20.0, -30, 0], [-10, -31, 0], [0, -32, 0], [30, -25, 0], [40, -20, 0]])
    runs = plots.neighbour_segments(P)
    assert [len(r) for r in runs] == [3, 2]
    assert plots.neighbour_segments(P[:1]) == []


def test_a_stage_is_ok_only_when_every_figure_meets_its_target():
    sec = Section("5. Material classification")
    sec.check("minirocket, 5 random 3:1 splits:", "every material", ">= 85 %", True)
    assert sec.status == "ok" and sec.headline == "ok"
    sec.check("apple accuracy", "50.0 %", ">= 64 %", False)
    assert not sec.ok and sec.status == "FAILED"
    assert sec.headline == "FAILED: apple accuracy 50.0 %"
    md = markdown("t", [sec])
    assert "## 5. Material classification — FAILED" in md
    assert "* MISSED: apple accuracy 50.0 % (target: >= 64 %)" in md
    assert "* met: minirocket" in md
    page = html_page("t", [sec], interrupted="stopped by Ctrl-C")
    assert "FAILED: apple accuracy 50.0 %" in page and "Interrupted" in page
    s = sec.summary()
    assert s["status"] == "FAILED" and [c["passed"] for c in s["checks"]] == [True, False]


# the quick demo's own figures (issue 30): headed "ok" with apple 50 % and paper LOO 0 %
QUICK = {"minirocket": {"random": {"aluminium": 1.0, "apple": 0.5, "foam": 1.0, "glass": 1.0,
                                   "paper": 1.0, "plastic": 1.0, "steel": 1.0},
                        "loo": {"aluminium": 0.778, "apple": 0.5, "foam": 1.0, "glass": 0.9,
                                "paper": 0.0, "plastic": 0.429, "steel": None},
                        "trials": 5},
         "boss": {"random": {"aluminium": 1.0, "apple": 1.0, "foam": 1.0, "glass": 0.5,
                             "paper": 1.0, "plastic": 1.0, "steel": 1.0}, "trials": 1}}


class FakeDemo:
    """What stage_classify needs of Demo: out, quick and run (canned `classify evaluate`)."""

    def __init__(self, out, results):
        self.out, self.quick, self.results, self.calls = out, True, results, []

    def run(self, *args):
        self.calls.append(args)
        name = args[args.index("--classifiers") + 1]
        return json.dumps({"classifiers": {name: self.results[name]}}) + "\n"


def test_the_classification_stage_fails_naming_the_materials_that_miss(tmp_path):
    from dmdsm.host.demo.session import stage_classify

    sec = stage_classify(FakeDemo(tmp_path, QUICK))
    assert sec.status == "FAILED"
    head = sec.headline
    assert "apple 50.0%" in head and "glass 50.0%" in head, head
    assert "paper 0.0%" in head and "plastic 42.9%" in head, head
    assert "aluminium" not in head
    (mr_head, mr_rows), (boss_head, boss_rows) = sec.tables
    # a material with no other object of it has no leave-one-out figure, and says why
    assert dict((r[0], r[3]) for r in mr_rows)["steel"].startswith("untested")
    # BOSS's leave-one-out column carries its reason
    assert boss_head[3].startswith("leave one object out: not run: ")
    assert "--classifiers boss" in boss_head[3]
    assert {r[3] for r in boss_rows} == {"not run"}


def test_the_classification_stage_is_ok_when_every_material_meets_it(tmp_path):
    from dmdsm.host.demo.session import stage_classify

    good = {n: {**r, "random": {c: 0.99 for c in r["random"]}} for n, r in QUICK.items()}
    good["minirocket"]["loo"] = {c: 0.9 for c in QUICK["minirocket"]["loo"]}
    sec = stage_classify(FakeDemo(tmp_path, good))
    assert sec.status == "ok", sec.headline
    assert len(sec.checks) == 3 and all(c.passed for c in sec.checks)


def test_the_block_stage_names_the_figure_that_misses():
    from dmdsm.host.demo.session import block_checks

    def e(mean, std, rms, n=40):
        return {"e_mean_mm": mean, "e_std_mm": std, "e_over_std_rms": rms, "n": n}

    sec = Section("3. Aluminium block validation")
    block_checks(sec, "oa", e(0.098, 0.081, 1.49), e(0.084, 0.081, 1.49))
    block_checks(sec, "us", e(0.157, 0.128, 1.0), e(0.150, 0.127, 1.0))
    assert sec.status == "FAILED"
    assert [c.what for c in sec.missed] == ["OA RMS e / point std"], sec.headline
    assert "1.49" in sec.headline
    sec = Section("3.")
    block_checks(sec, "oa", e(0.20, 0.05, 1.0, 160), e(0.054, 0.049, 0.9, 160))
    assert [c.what for c in sec.missed] == ["OA e mean (stage 2 calibration)"]


def test_the_rig_stage_states_its_criteria():
    from dmdsm.host.demo.run import rig_checks

    sec = Section("2. Scanner calibration", ok=False,
                  values={"v_error_deg": 0.3, "n_error_deg": 0.7, "X_R_error_mm": 0.1})
    rig_checks(sec)
    assert [c.passed for c in sec.checks] == [True, False, True]
    assert sec.headline == "FAILED: n error vs the emulator's truth 0.700 deg"


def test_a_material_short_of_its_figure_by_one_window_in_six_is_not_a_miss():
    """The quick demo tests 4-8 windows a material: BOSS's glass at 5/6 (83.3 %) against the
    85 % floor failed the whole stage, though a classifier right 85 % of the time does that
    badly 62 % of the time. A shortfall passes only where chance explains it: 290 of 360
    (80.6 %) does not, nor 0 of 6, nor a figure with no counts to judge it by."""
    from dmdsm.host.demo.session import classify_checks, short_by_chance

    assert short_by_chance(5, 6, 0.85) and short_by_chance(5, 14, 0.5)
    assert not short_by_chance(290, 360, 0.85) and not short_by_chance(0, 6, 0.85)
    assert not short_by_chance(0, 0, 0.85)
    r = {"random": {"glass": 5 / 6, "steel": 290 / 360, "paper": 1.0},
         "loo": {"glass": 5 / 14, "steel": 1 / 14, "paper": None}}
    sec = Section("5.")
    classify_checks(sec, "boss", r, "2 random 3:1 splits",
                    {"glass": (5, 6), "steel": (290, 360), "paper": (4, 4)},
                    {"glass": (5, 14), "steel": (1, 14)})
    rand, loo = sec.checks
    assert not rand.passed and rand.value == "steel 80.6% < 85.0% (290/360)"
    assert not loo.passed and loo.value == "steel 7.1% (1/14)"
    sec = Section("5.")  # without counts the figure alone decides, as before
    classify_checks(sec, "boss", r, "2 random 3:1 splits")
    assert sec.checks[0].value == "glass 83.3% < 85.0%; steel 80.6% < 85.0%"
    assert sec.checks[1].value == "glass 35.7%; steel 7.1%"
