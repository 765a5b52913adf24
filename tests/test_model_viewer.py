"""The 3D model viewer page (host/report/viewer.py): escaping, no fetches, its colourings, and a
real headless chromium (selenium + chromedriver) drawing it offline and switching colouring."""

import html
import io
import json
import re
import shutil
import tempfile
from html.parser import HTMLParser

import numpy as np
import pytest
import trimesh
from PIL import Image, ImageChops

from dmdsm.host.report import viewer

HOSTILE = ('</script><script>window.__pwned=1</script><img src=x onerror="window.__pwned=2">'
           "\"'\x00\x1b&amp;<!--\u2028")
CLASSES = ["wood", "metal", "plastic"]


def small_model(classes=CLASSES):
    """An icosphere of radius 40 mm: the cap below z = -25 mm unsupported, 3 classes by x,
    a few supported vertices with no material."""
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=40.0)
    v = np.asarray(mesh.vertices)
    supported = v[:, 2] > -25.0
    sigma = np.where(supported, 0.05 + 0.004 * (v[:, 2] + 40.0), np.nan)
    support = np.where(supported, 1 + np.round(6 + 5 * np.sin(v[:, 0] / 9.0)), 0).astype(int)
    centres = np.array([-30.0, 0.0, 30.0])[: len(classes)]
    logits = -((v[:, :1] - centres[None, :]) / 15.0) ** 2
    prob = np.exp(logits) / np.exp(logits).sum(axis=1, keepdims=True)
    prob[::37] = np.nan
    return dict(vertices_mm=v, faces=np.asarray(mesh.faces), sigma_mm=sigma, support=support,
                supported=supported, classes=list(classes), material_prob=prob)


class Parsed(HTMLParser):
    """The page's tags, attributes, scripts (type, text) and visible text."""

    def __init__(self, page):
        super().__init__(convert_charrefs=True)
        self.tags, self.scripts, self.text, self._script = [], [], [], None
        self.feed(page)

    def handle_starttag(self, tag, attrs):
        self.tags.append((tag, dict(attrs)))
        if tag == "script":
            self._script = [dict(attrs).get("type", ""), ""]

    def handle_endtag(self, tag):
        if tag == "script" and self._script is not None:
            self.scripts.append(tuple(self._script))
            self._script = None

    def handle_data(self, data):
        if self._script is not None:
            self._script[1] += data
        else:
            self.text.append(data)


def test_hostile_title_class_and_notes_do_not_inject():
    model = small_model(["wood", HOSTILE, "met'al\""])
    page = viewer.model_html(HOSTILE, **model, notes={HOSTILE: HOSTILE, "scan": "1 of 2"})
    p = Parsed(page)
    assert [t for t, _ in p.scripts] == ["", "", "application/json"], "only 3 script elements"
    assert not [t for t, a in p.tags if t == "img"]
    assert not [k for _, a in p.tags for k in a if k.lower().startswith("on")]
    ours = "".join(p.text) + str(p.tags) + p.scripts[2][1]   # plotly.js aside
    assert not re.search("[\x00-\x08\x0b\x0c\x0e-\x1f]", ours), "control characters pass"
    assert viewer.clean_text(HOSTILE) in "".join(p.text), "title shown as text, unchanged"
    data = json.loads(p.scripts[2][1])
    assert html.unescape(data["classes"][1]) == viewer.clean_text(HOSTILE)
    assert data["classes"][2] == "met&#39;al&#34;", "escaped for plotly's labels"
    assert not re.search("[<>\"']", "".join(data["classes"]))


def test_page_fetches_nothing():
    page = viewer.model_html("cup", **small_model(), points_mm=np.zeros((5, 3)))
    p = Parsed(page)
    assert not [a for _, a in p.tags if "src" in a or "href" in a], "no src/href attributes"
    assert not [a for t, a in p.tags if t in ("link", "iframe", "object", "embed")]
    outside_scripts = "".join(p.text) + "".join(str(a) for _, a in p.tags)
    assert not re.search(r"https?://|//[a-z0-9.-]+\.[a-z]{2,}/", outside_scripts, re.I)
    styles = re.findall(r"<style>(.*?)</style>", page, re.S)
    assert styles and not re.search(r"url\(|@import|@font-face", "".join(styles), re.I)
    csp = [a["content"] for t, a in p.tags if a.get("http-equiv") == "Content-Security-Policy"]
    assert csp and csp[0].startswith("default-src 'none'"), "CSP: nothing may be fetched"


def test_modes_legends_and_rounding():
    model = small_model()
    page = viewer.model_html("bowl", **model, notes={"version": "3"})
    p = Parsed(page)
    options = [a["value"] for t, a in p.tags if t == "option"]
    assert options == ["material", "sigma", "support"]
    legends = {a["data-mode"]: "hidden" in a for t, a in p.tags if "data-mode" in a}
    assert legends == {"material": False, "sigma": True, "support": True}
    text = "".join(p.text)
    assert all(c in text for c in CLASSES) and "unsupported or no material" in text
    assert "version" in text and "sigma (mm)" in text
    data = json.loads(p.scripts[2][1])
    v = model["vertices_mm"]
    assert data["xyz"] == np.rint(v * 100).astype(int).reshape(-1).tolist()
    ok = model["supported"]
    assert [s is None for s in data["sigma"]] == list(~ok)
    assert data["material"][0] == -1 and data["prob"][:3] == [-1, -1, -1]
    k = int(np.flatnonzero(ok)[1])
    assert data["material"][k] == int(np.argmax(model["material_prob"][k]))
    assert abs(data["prob"][3 * k] - 1000 * model["material_prob"][k, 0]) <= 0.5
    assert viewer.GREY not in data["palette"] and len(set(data["palette"])) >= 20


def test_several_models_share_one_plotly_and_inputs_are_checked():
    from plotly.offline import get_plotlyjs
    model = small_model()
    sections = [viewer.model_section(f"object {i}", **model) for i in range(3)]
    page = viewer.models_page("objects", sections)
    assert page.count(get_plotlyjs()[-2000:]) == 1 and page.count('class="dmdsm-model"') == 3
    assert page.count("<h1>objects</h1>") == 1
    assert "<h1>" not in viewer.model_html("one", **model)
    bad = dict(model, faces=model["faces"] + len(model["vertices_mm"]))
    with pytest.raises(ValueError):
        viewer.model_section("x", **bad)
    with pytest.raises(ValueError):
        viewer.model_section("x", **dict(model, support=model["support"][:-1]))


def test_measured_points_are_subsampled():
    pts = np.random.default_rng(1).normal(size=(50000, 3)) * 30
    page = viewer.model_html("p", **small_model(), points_mm=pts)
    data = json.loads(Parsed(page).scripts[2][1])
    assert len(data["points"]) == 3 * viewer.MAX_POINTS and "showing 20000" in page


# --- the page in a real browser --------------------------------------------------------------

MAKE_DEPS = "`make deps` installs it (apt: chromium chromium-driver; pip: selenium)"


@pytest.fixture(scope="module")
def browser():
    """Headless chromium (new headless, no sandbox as root, a temporary profile) through
    chromedriver, with the network cut off: offline emulation and a dead proxy."""
    chrome, driver_path = shutil.which("chromium"), shutil.which("chromedriver")
    if chrome is None or driver_path is None:
        pytest.fail(f"chromium / chromedriver not found: {MAKE_DEPS}")
    try:
        from selenium import webdriver
        from selenium.webdriver.chrome.service import Service
    except ImportError:
        pytest.fail(f"the selenium package is missing: {MAKE_DEPS}")
    with tempfile.TemporaryDirectory(prefix="dmdsm-chromium-") as profile:
        opts = webdriver.ChromeOptions()
        opts.binary_location = chrome
        for arg in ("--headless=new", "--no-sandbox", f"--user-data-dir={profile}",
                    "--window-size=1000,1000", "--no-first-run", "--disable-extensions",
                    "--disable-background-networking", "--disable-component-update",
                    "--proxy-server=http://127.0.0.1:9", "--use-angle=swiftshader",
                    "--enable-unsafe-swiftshader", "--disable-dev-shm-usage"):
            opts.add_argument(arg)
        opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})
        driver = webdriver.Chrome(options=opts, service=Service(executable_path=driver_path))
        try:
            driver.set_page_load_timeout(30)
            driver.set_script_timeout(20)
            driver.execute_cdp_cmd("Network.enable", {})
            driver.execute_cdp_cmd("Network.emulateNetworkConditions", {
                "offline": True, "latency": 0, "downloadThroughput": -1,
                "uploadThroughput": -1})
            yield driver
        finally:
            driver.quit()


WAIT_AFTERPLOT = """
const [n, done] = arguments, sec = document.querySelector('.dmdsm-model');
const frames = () => requestAnimationFrame(() => requestAnimationFrame(
    () => done(Number(sec.dataset.afterplot))));
if (Number(sec.dataset.afterplot || 0) > n) frames();
else sec.addEventListener('dmdsm-afterplot', frames, {once: true});
"""
COLOURS = "return document.querySelector('.dmdsm-plot').data[0].vertexcolor;"
ON_HOVER = """
const gd = document.querySelector('.dmdsm-plot');
window.hovered = new Promise(resolve => gd.on('plotly_hover', e => requestAnimationFrame(
    () => resolve([e.points[0].pointNumber, document.querySelector('.hovertext').textContent]))));
"""


def shot(element):
    """The element's screenshot as RGB."""
    return Image.open(io.BytesIO(element.screenshot_as_png)).convert("RGB")


def test_chromium_draws_the_model_and_switches_colouring(browser, tmp_path):
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import Select
    model = small_model(["wood", HOSTILE, "metal"])
    path = tmp_path / "model.html"
    path.write_text(viewer.model_html(HOSTILE, **model, notes={"note": HOSTILE},
                                      points_mm=model["vertices_mm"][::5] * 1.02))
    browser.get(path.as_uri())
    assert browser.execute_async_script(WAIT_AFTERPLOT, 0) >= 1, "plotly_afterplot"
    assert browser.execute_script("return window.__pwned") is None
    title = browser.find_element(By.CSS_SELECTOR, ".dmdsm-model h2").text
    assert title.startswith("</script><script>window.__pwned=1</script><img")
    plot = browser.find_element(By.CSS_SELECTOR, ".dmdsm-plot")
    first = shot(plot)
    assert len(first.getcolors(1 << 24)) > 3000, "the plot area is blank (WebGL?)"
    unsupported = np.flatnonzero(~model["supported"]).tolist()
    colours = {"material": browser.execute_script(COLOURS)}
    count = int(browser.execute_script(
        "return document.querySelector('.dmdsm-model').dataset.afterplot"))
    for mode in ("sigma", "support"):
        Select(browser.find_element(By.CSS_SELECTOR, ".dmdsm-colour-by")).select_by_value(mode)
        count = browser.execute_async_script(WAIT_AFTERPLOT, count)
        colours[mode] = browser.execute_script(COLOURS)
        legend = browser.find_element(By.CSS_SELECTOR, f'.dmdsm-legend[data-mode="{mode}"]')
        assert legend.is_displayed()
    after = shot(plot)
    diff = np.asarray(ImageChops.difference(first, after).convert("L")) > 24
    assert diff.mean() > 0.05, "switching colour-by did not change the drawn colours"
    assert colours["material"] != colours["sigma"] != colours["support"]
    for mode, c in colours.items():
        assert {c[i] for i in unsupported} == {viewer.GREY}, f"unsupported grey in {mode}"
        assert viewer.GREY not in {c[i] for i in np.flatnonzero(model["supported"])[1:30:2]}
    hover = browser.execute_script("return document.querySelector('.dmdsm-plot').data[0].text")
    assert "UNSUPPORTED" in hover[unsupported[0]] and "sigma none" in hover[unsupported[0]]
    buttons = browser.execute_script("return [...document.querySelectorAll('.modebar-btn')]"
                                     ".map(b => b.getAttribute('data-title'))")
    assert "Zoom" in buttons and not [b for b in buttons if "Share" in b or "Studio" in b]
    browser.execute_script(ON_HOVER)   # a real mouse over the surface: plotly's hover label
    ActionChains(browser).move_to_element_with_offset(plot, 0, 60).perform()
    ActionChains(browser).move_to_element_with_offset(plot, 2, 50).perform()
    vertex, label = browser.execute_async_script("window.hovered.then(arguments[0])")
    assert label == html.unescape(hover[vertex].replace("<br>", ""))
    assert label.startswith(f"vertex {vertex}x") and viewer.clean_text(HOSTILE) in label
    assert browser.execute_script("return window.__pwned") is None
    assert browser.execute_script("return performance.getEntriesByType('resource').length") == 0
    errors = [e for e in browser.get_log("browser") if e["level"] in ("SEVERE", "ERROR")]
    assert not errors, f"console errors: {errors}"
