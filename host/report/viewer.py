"""An object's 3D model as an interactive, self-contained HTML view (plotly.js inline, offline).

`model_html` gives one complete page; `model_section` gives one model's block so that
`models_page` (or a page that puts `viewer_head()` in its <head>) holds several models with
plotly.js embedded once. A view colours the surface by material (a colour per class), sigma
(mm) or support (count); unsupported vertices and vertices with no material are grey in every
colouring and say so in the hover. Coordinates are rounded to 0.01 mm, sigma to 0.001 mm and
probabilities to 3 digits. Every string from the caller is escaped, and the page's Content
Security Policy lets only its own two scripts run and nothing be fetched."""

from __future__ import annotations

import base64
import colorsys
import hashlib
import html
import json
import re
from functools import lru_cache

import numpy as np

GREY = "#9a9a9a"          # unsupported / no material / no sigma, in every colouring
MAX_POINTS = 20000        # measured points drawn at most (evenly subsampled beyond)
MODES = ("material", "sigma", "support")
_MODE_LABELS = {"material": "material", "sigma": "sigma (mm)", "support": "support (count)"}
_CONTROL = re.compile("[\x00-\x08\x0b\x0c\x0e-\x1f\x7f-\x9f\ud800-\udfff]")
_STYLE = ("body{font-family:sans-serif;max-width:1100px;margin:1.5em auto;line-height:1.4}"
          ".dmdsm-model{border-top:1px solid #ccc;margin-top:1em}"
          ".dmdsm-notes td,.dmdsm-notes th{padding:1px 8px;text-align:left;vertical-align:top}"
          ".dmdsm-legend{margin:.4em 0;font-size:90%}.dmdsm-sw{display:inline-block;width:1em;"
          "height:1em;vertical-align:middle;margin:0 .3em 0 .8em;border:1px solid #666}"
          ".dmdsm-bar{display:inline-block;width:14em;height:1em;vertical-align:middle;"
          "margin:0 .4em;border:1px solid #666}.dmdsm-plot{height:560px}")


def clean_text(text: object) -> str:
    """`text` as a string with control characters and lone surrogates replaced by U+FFFD."""
    return _CONTROL.sub("\ufffd", str(text))


def _h(text: object) -> str:
    return html.escape(clean_text(text), quote=True)


def _plotly_text(text: object) -> str:
    """`text` for plotly's hover labels, which read tags and entities (but not &quot;)."""
    return html.escape(clean_text(text), quote=False).replace('"', "&#34;").replace("'", "&#39;")


def _script_json(obj: object) -> str:
    """JSON that is safe inside a <script> element: no '<', '>', '&' or non-ASCII left."""
    text = json.dumps(obj, separators=(",", ":"), allow_nan=False, ensure_ascii=True)
    return text.replace("<", "\\u003c").replace(">", "\\u003e").replace("&", "\\u0026")


def _palette() -> list[str]:
    """Distinct saturated colours for classes (greys left out: grey means unsupported)."""
    from plotly.colors import qualitative
    out: list[str] = []
    for c in qualitative.Plotly + qualitative.Dark24 + qualitative.Light24:
        r, g, b = (int(c[i:i + 2], 16) / 255 for i in (1, 3, 5))
        if colorsys.rgb_to_hsv(r, g, b)[1] >= 0.35 and c.lower() not in out:
            out.append(c.lower())
    return out


def _scales() -> dict[str, list[str]]:
    from plotly.colors import sequential
    return {"sigma": list(sequential.Viridis), "support": list(sequential.Plasma)}


@lru_cache(maxsize=1)
def _scripts() -> tuple[str, str]:
    """(plotly.js, the viewer's runtime), checked to be safe to put in <script> elements."""
    from plotly.offline import get_plotlyjs
    plotly_js = get_plotlyjs()
    for text in (plotly_js, _RUNTIME):
        if "</script" in text.lower() or "<!--" in text:
            raise ValueError("a script holds '</script' or '<!--' and cannot be inlined")
    return plotly_js, _RUNTIME


@lru_cache(maxsize=1)
def _csp() -> str:
    digests = [base64.b64encode(hashlib.sha256(s.encode()).digest()).decode()
               for s in _scripts()]
    sources = " ".join(f"'sha256-{d}'" for d in digests)
    return ("default-src 'none'; script-src " + sources + " 'unsafe-eval'; "
            "style-src 'unsafe-inline'; img-src data: blob:")


def viewer_head() -> str:
    """What a page needs once in its <head> to show `model_section` blocks: a Content
    Security Policy (no fetches; only these scripts run), the style, plotly.js, the runtime."""
    plotly_js, runtime = _scripts()
    return (f'<meta http-equiv="Content-Security-Policy" content="{_h(_csp())}">\n'
            f"<style>{_STYLE}</style>\n<script>{plotly_js}</script>\n<script>{runtime}</script>")


def _legend(mode: str, classes: list[str], palette: list[str], lo: float, hi: float) -> str:
    hidden = "" if mode == "material" else " hidden"
    grey = f'<span class="dmdsm-sw" style="background:{GREY}"></span>'
    if mode == "material":
        body = "".join(f'<span class="dmdsm-sw" style="background:{palette[i % len(palette)]}">'
                       f"</span>{_h(c)}" for i, c in enumerate(classes))
        body += grey + "unsupported or no material"
    else:
        stops = ",".join(_scales()[mode])
        fmt = "{:.3f} mm" if mode == "sigma" else "{:.0f}"
        body = (f"{_MODE_LABELS[mode]}: {fmt.format(lo)}<span class=\"dmdsm-bar\" "
                f"style=\"background:linear-gradient(to right,{stops})\"></span>"
                f"{fmt.format(hi)}{grey}unsupported" + (" or no sigma" if mode == "sigma" else ""))
    return f'<div class="dmdsm-legend" data-mode="{mode}"{hidden}>{body}</div>'


def _range(values: np.ndarray, ok: np.ndarray, ndigits: int) -> tuple[float, float]:
    v = values[ok & np.isfinite(values)]
    if v.size == 0:
        return 0.0, 1.0
    return round(float(v.min()), ndigits), round(float(v.max()), ndigits)


def model_section(title: str, vertices_mm: np.ndarray, faces: np.ndarray,
                  sigma_mm: np.ndarray, support: np.ndarray, supported: np.ndarray,
                  classes: list[str], material_prob: np.ndarray,
                  points_mm: np.ndarray | None = None, notes: dict[str, str] | None = None,
                  max_points: int = MAX_POINTS) -> str:
    """One model's block of HTML (needs `viewer_head()` in the page): vertices_mm (V,3) mm,
    faces (F,3) vertex indices, sigma_mm (V,) mm (NaN: none), support (V,) counts,
    supported (V,) bool, classes (C names), material_prob (V,C) (a row with NaN: no
    material), points_mm (N,3) mm measured points to overlay (at most `max_points` drawn),
    notes: name -> text shown under the title."""
    v = np.asarray(vertices_mm, dtype=float)
    f = np.asarray(faces)
    n = len(v)
    sigma = np.asarray(sigma_mm, dtype=float).reshape(-1)
    sup = np.asarray(support).reshape(-1)
    ok = np.asarray(supported, dtype=bool).reshape(-1)
    prob = np.asarray(material_prob, dtype=float).reshape(n, len(classes)) if n else \
        np.zeros((0, len(classes)))
    if v.ndim != 2 or v.shape[1] != 3 or not np.isfinite(v).all():
        raise ValueError("vertices_mm must be a finite (V, 3) array")
    if f.ndim != 2 or f.shape[1] != 3 or (f.size and (f.min() < 0 or f.max() >= n)):
        raise ValueError("faces must be a (F, 3) array of vertex indices below V")
    if not (len(sigma) == len(sup) == len(ok) == n):
        raise ValueError("sigma_mm, support and supported need one value per vertex")
    no_material = ~np.isfinite(prob).all(axis=1) if len(classes) else np.ones(n, bool)
    material = np.where(no_material, -1, np.argmax(np.nan_to_num(prob, nan=-1.0), axis=1)) \
        if len(classes) else np.full(n, -1)
    pts = np.zeros((0, 3)) if points_mm is None else np.asarray(points_mm, float).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    n_points = len(pts)
    if n_points > max_points:
        pts = pts[np.linspace(0, n_points - 1, max_points).astype(int)]
    palette = _palette()
    s_lo, s_hi = _range(sigma, ok, 3)
    c_lo, c_hi = _range(sup.astype(float), ok, 0)
    data = {
        "xyz": np.rint(v * 100).astype(np.int64).reshape(-1).tolist(),
        "ijk": f.astype(np.int64).reshape(-1).tolist(),
        "sigma": [None if not np.isfinite(s) else round(float(s), 3) for s in sigma],
        "support": sup.astype(np.int64).tolist(),
        "supported": ok.astype(int).tolist(),
        "classes": [_plotly_text(c) for c in classes],
        "material": material.astype(int).tolist(),
        "prob": np.where(no_material[:, None], -1,
                         np.rint(np.nan_to_num(prob) * 1000)).astype(int).reshape(-1).tolist(),
        "points": np.rint(pts * 100).astype(np.int64).reshape(-1).tolist(),
        "palette": palette, "grey": GREY, "scales": _scales(),
        "ranges": {"sigma": [s_lo, s_hi], "support": [c_lo, c_hi]},
    }
    notes_html = "".join(f"<tr><th>{_h(k)}</th><td>{_h(val)}</td></tr>"
                         for k, val in (notes or {}).items())
    shown = f" (showing {len(pts)})" if len(pts) < n_points else ""
    summary = (f"{n} vertices, {len(f)} faces, {int((~ok).sum())} unsupported (grey)"
               + (f", {n_points} measured points{shown}" if n_points else ""))
    options = "".join(f'<option value="{m}">{_MODE_LABELS[m]}</option>' for m in MODES)
    return "\n".join([
        '<section class="dmdsm-model">', f"<h2>{_h(title)}</h2>",
        f'<table class="dmdsm-notes">{notes_html}</table>' if notes_html else "",
        f'<p class="dmdsm-summary">{summary}</p>',
        f'<label>colour by <select class="dmdsm-colour-by">{options}</select></label>',
        *(_legend(m, classes, palette, *(s_lo, s_hi) if m == "sigma" else (c_lo, c_hi))
          for m in MODES),
        '<div class="dmdsm-plot"></div>',
        f'<script type="application/json" class="dmdsm-data">{_script_json(data)}</script>',
        "</section>"])


def models_page(title: str, sections: list[str], intro: str = "", heading: bool = True) -> str:
    """One complete page holding several `model_section` blocks (plotly.js embedded once);
    `intro`: a line of text under the title; `heading`: show the title as the page's <h1>."""
    body = (f"<h1>{_h(title)}</h1>\n" if heading else "") + \
        (f"<p>{_h(intro)}</p>\n" if intro else "")
    return (f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">\n'
            f"<title>{_h(title)}</title>\n{viewer_head()}\n</head><body>\n"
            + body + "\n".join(sections) + "\n</body></html>\n")


def model_html(title: str, vertices_mm: np.ndarray, faces: np.ndarray, sigma_mm: np.ndarray,
               support: np.ndarray, supported: np.ndarray, classes: list[str],
               material_prob: np.ndarray, points_mm: np.ndarray | None = None,
               notes: dict[str, str] | None = None) -> str:
    """One complete page viewing one model (arguments as `model_section`, lengths in mm)."""
    return models_page(title, [model_section(title, vertices_mm, faces, sigma_mm, support,
                                             supported, classes, material_prob, points_mm,
                                             notes)], heading=False)


# The runtime: plots each .dmdsm-model when it scrolls into view (at most LIVE_MAX WebGL
# views live at once), switches the colouring, and counts plotly_afterplot events on the
# section (data-afterplot, event "dmdsm-afterplot") so that a test can wait for drawing.
_RUNTIME = r"""
(function () {
  "use strict";
  var LIVE_MAX = 8, live = [];
  function rgb(h) { return [1, 3, 5].map(function (i) { return parseInt(h.substr(i, 2), 16); }); }
  function scaleColour(stops, t) {
    t = Math.min(1, Math.max(0, isFinite(t) ? t : 0));
    var x = t * (stops.length - 1), i = Math.min(stops.length - 2, Math.floor(x)), f = x - i;
    return "rgb(" + [0, 1, 2].map(function (k) {
      return Math.round(stops[i][k] + (stops[i + 1][k] - stops[i][k]) * f); }).join(",") + ")";
  }
  function colours(d, mode) {
    var n = d.support.length, out = new Array(n), i;
    if (mode === "material") {
      for (i = 0; i < n; i++) {
        out[i] = d.supported[i] && d.material[i] >= 0 ?
          d.palette[d.material[i] % d.palette.length] : d.grey;
      }
      return out;
    }
    var v = d[mode], r = d.ranges[mode], stops = d.scales[mode].map(rgb);
    var span = r[1] - r[0] || 1;
    for (i = 0; i < n; i++) {
      out[i] = d.supported[i] && v[i] !== null ? scaleColour(stops, (v[i] - r[0]) / span) : d.grey;
    }
    return out;
  }
  function hover(d) {
    var n = d.support.length, C = d.classes.length, out = new Array(n), i, c, s;
    for (i = 0; i < n; i++) {
      s = "vertex " + i + "<br>x " + (d.xyz[3 * i] / 100).toFixed(2) + "  y " +
        (d.xyz[3 * i + 1] / 100).toFixed(2) + "  z " + (d.xyz[3 * i + 2] / 100).toFixed(2) +
        " mm<br>sigma " + (d.sigma[i] === null ? "none" : d.sigma[i].toFixed(3) + " mm") +
        "<br>support " + d.support[i] +
        (d.supported[i] ? "<br>supported" : "<br><b>UNSUPPORTED</b> (grey)");
      if (d.material[i] < 0) { s += "<br>material: none"; } else {
        s += "<br>material: " + d.classes[d.material[i]];
        for (c = 0; c < C; c++) {
          s += "<br>  " + d.classes[c] + " " + (d.prob[i * C + c] / 1000).toFixed(3);
        }
      }
      out[i] = s;
    }
    return out;
  }
  function axis(a, k, div) {
    var out = [], i;
    for (i = k; i < a.length; i += 3) { out.push(a[i] / div); }
    return out;
  }
  function signal(sec) {
    sec.dataset.afterplot = String((Number(sec.dataset.afterplot) || 0) + 1);
    sec.dispatchEvent(new CustomEvent("dmdsm-afterplot"));
  }
  function plot(sec) {
    var d = sec.dmdsm, gd = sec.querySelector(".dmdsm-plot"), mode = sec.dmdsmMode;
    d.hover = d.hover || hover(d);
    var traces = [{type: "mesh3d", name: "model", x: axis(d.xyz, 0, 100),
      y: axis(d.xyz, 1, 100), z: axis(d.xyz, 2, 100), i: axis(d.ijk, 0, 1),
      j: axis(d.ijk, 1, 1), k: axis(d.ijk, 2, 1),
      vertexcolor: colours(d, mode), text: d.hover, hoverinfo: "text", showlegend: false}];
    if (d.points.length) {
      traces.push({type: "scatter3d", mode: "markers", name: "measured points",
        x: axis(d.points, 0, 100), y: axis(d.points, 1, 100), z: axis(d.points, 2, 100),
        marker: {size: 1.5, color: "#111"}, hovertemplate: "%{x:.2f}, %{y:.2f}, %{z:.2f} mm"});
    }
    var layout = {margin: {l: 0, r: 0, t: 0, b: 0}, showlegend: d.points.length > 0,
      legend: {x: 0, y: 1}, scene: {aspectmode: "data", xaxis: {title: {text: "x (mm)"}},
        yaxis: {title: {text: "y (mm)"}}, zaxis: {title: {text: "z (mm)"}}}};
    Plotly.newPlot(gd, traces, layout, {displaylogo: false, responsive: true, showLink: false,
      showSendToCloud: false, showEditInChartStudio: false,
      modeBarButtonsToRemove: ["sendDataToCloud", "editInChartStudio"]});
    gd.on("plotly_afterplot", function () { signal(sec); });
    sec.dmdsmPlotted = true;
    live.push(sec);
    for (var i = 0; live.length > LIVE_MAX && i < live.length; i++) {
      if (!live[i].dmdsmVisible) { Plotly.purge(live[i].querySelector(".dmdsm-plot"));
        live[i].dmdsmPlotted = false; live.splice(i, 1); i--; }
    }
  }
  function setMode(sec, mode) {
    sec.dmdsmMode = mode;
    sec.querySelectorAll(".dmdsm-legend").forEach(function (el) {
      el.hidden = el.dataset.mode !== mode; });
    if (sec.dmdsmPlotted) {
      Plotly.restyle(sec.querySelector(".dmdsm-plot"), {vertexcolor: [colours(sec.dmdsm, mode)]},
        [0]);
    }
  }
  function init() {
    var secs = document.querySelectorAll(".dmdsm-model"), observer = null;
    if (window.IntersectionObserver) {
      observer = new IntersectionObserver(function (entries) {
        entries.forEach(function (e) {
          e.target.dmdsmVisible = e.isIntersecting;
          if (e.isIntersecting && !e.target.dmdsmPlotted) { plot(e.target); }
        });
      }, {rootMargin: "300px"});
    }
    secs.forEach(function (sec) {
      var sel = sec.querySelector(".dmdsm-colour-by");
      sec.dmdsm = JSON.parse(sec.querySelector(".dmdsm-data").textContent);
      sec.dmdsmMode = sel.value;
      sel.addEventListener("change", function () { setMode(sec, sel.value); });
      if (observer) { observer.observe(sec); } else { plot(sec); }
    });
  }
  if (document.readyState === "loading") {
    document.addEventListener("DOMContentLoaded", init);
  } else { init(); }
})();
"""
