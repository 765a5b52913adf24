"""The demo's report: sections of text, tables and figures, written as Markdown and as one
self-contained HTML file (figures embedded as base64 PNG).

A section's status comes from its checks: each states a figure, what it is compared with and
whether it meets it, and the report prints them next to the status, so "ok" always says what
was met and "FAILED" says which figure missed. A stage stopped by Ctrl-C or SIGTERM is
"interrupted", and the stages after it "not run"."""

from __future__ import annotations

import base64
import html
from dataclasses import dataclass, field
from pathlib import Path


@dataclass
class Check:
    """One criterion of a stage: a figure, the target it is compared with, and the verdict."""

    what: str     # e.g. "OA t0 vs the emulator's truth"
    value: str    # the figure as shown, e.g. "error -0.6 std"
    target: str   # what it must meet, e.g. "|error| < 4 std"
    passed: bool

    def line(self) -> str:
        """`met: WHAT VALUE (target: TARGET)` or `MISSED: ...`."""
        return f"{'met' if self.passed else 'MISSED'}: {self.what} {self.value} " \
               f"(target: {self.target})"


@dataclass
class Section:
    """One stage of the demo: a title, paragraphs, tables, figures and whether it passed."""

    title: str
    ok: bool = True
    text: list[str] = field(default_factory=list)
    tables: list[tuple[list[str], list[list[str]]]] = field(default_factory=list)
    figures: list[tuple[Path, str]] = field(default_factory=list)
    seconds: float = 0.0
    values: dict = field(default_factory=dict)  # the figures, for summary.json and tests
    checks: list[Check] = field(default_factory=list)
    state: str = ""  # "" (ran to its end), "interrupted" or "not run"
    views: list[str] = field(default_factory=list)  # 3D model blocks (report.viewer)

    def table(self, header: list[str], rows: list[list[object]]) -> None:
        """Add a table (cells formatted with str)."""
        self.tables.append((header, [[str(c) for c in r] for r in rows]))

    def check(self, what: str, value: str, target: str, passed: bool) -> bool:
        """State a criterion and its verdict; the section is ok only if every one is met."""
        self.checks.append(Check(what, value, target, bool(passed)))
        self.ok = self.ok and bool(passed)
        return bool(passed)

    @property
    def missed(self) -> list[Check]:
        """The criteria not met."""
        return [c for c in self.checks if not c.passed]

    @property
    def status(self) -> str:
        """"ok", "FAILED", "interrupted" or "not run"."""
        return self.state or ("ok" if self.ok else "FAILED")

    @property
    def headline(self) -> str:
        """The status with what made it: "FAILED: apple 50.0 % (paper 79.0 %)"."""
        if self.state or self.ok or not self.missed:
            return self.status
        return "FAILED: " + "; ".join(f"{c.what} {c.value}" for c in self.missed)

    def summary(self) -> dict:
        """This section for summary.json."""
        return {"title": self.title, "ok": bool(self.ok and not self.state),
                "status": self.status, "seconds": self.seconds, "values": self.values,
                "checks": [{"what": c.what, "value": c.value, "target": c.target,
                            "passed": c.passed} for c in self.checks]}


def _banner(interrupted: str) -> list[str]:
    return [f"**Interrupted:** {interrupted}"] if interrupted else []


def markdown(title: str, sections: list[Section], interrupted: str = "") -> str:
    """The report as Markdown (figures linked by file name); `interrupted`: a line saying
    what a signal stopped, shown under the title."""
    out = [f"# {title}", ""]
    for b in _banner(interrupted):
        out += [b, ""]
    for s in sections:
        out += [f"## {s.title} — {s.status} ({s.seconds:.0f} s)", ""]
        if s.checks:
            out += [f"Status {s.status}, from these criteria:", ""]
            out += [f"* {c.line()}" for c in s.checks] + [""]
        for t in s.text:
            out += [t, ""]
        for header, rows in s.tables:
            out.append("| " + " | ".join(header) + " |")
            out.append("|" + "---|" * len(header))
            out += ["| " + " | ".join(r) + " |" for r in rows]
            out.append("")
        for path, caption in s.figures:
            out += [f"![{caption}]({path.name})", ""]
    return "\n".join(out) + "\n"


def _cls(s: Section) -> str:
    return "ok" if s.status == "ok" else "bad"


def html_page(title: str, sections: list[Section], interrupted: str = "") -> str:
    """The report as one HTML file with the figures and the 3D model views inside it (no
    network needed to open it)."""
    e = html.escape
    head = ""
    if any(s.views for s in sections):
        from .viewer import viewer_head

        head = viewer_head()
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>{e(title)}</title>",
             head,
             "<style>body{font-family:sans-serif;max-width:1100px;margin:2em auto;"
             "line-height:1.4}table{border-collapse:collapse;margin:0.5em 0}"
             "td,th{border:1px solid #bbb;padding:3px 8px;text-align:left}"
             "th{background:#eee}.ok{color:#060}.bad{color:#a00}img{max-width:100%}"
             "figcaption{font-size:90%;color:#444}ul.checks{margin:0.3em 0}"
             "</style></head><body>",
             f"<h1>{e(title)}</h1>"]
    if interrupted:
        parts.append(f"<p class='bad'><b>Interrupted:</b> {e(interrupted)}</p>")
    parts.append("<table><tr><th>stage</th><th>result</th><th>time (s)</th></tr>" + "".join(
        f"<tr><td>{e(s.title)}</td><td class='{_cls(s)}'>{e(s.headline)}</td>"
        f"<td>{s.seconds:.0f}</td></tr>" for s in sections) + "</table>")
    for s in sections:
        parts.append(f"<h2>{e(s.title)} <span class='{_cls(s)}'>({e(s.status)})</span></h2>")
        if s.checks:
            parts.append(f"<p>Status {e(s.status)}, from these criteria:</p><ul class='checks'>"
                         + "".join(f"<li class='{'ok' if c.passed else 'bad'}'>{e(c.line())}"
                                   f"</li>" for c in s.checks) + "</ul>")
        parts += [f"<p>{e(t)}</p>" for t in s.text]
        for header, rows in s.tables:
            parts.append("<table><tr>" + "".join(f"<th>{e(h)}</th>" for h in header)
                         + "</tr>" + "".join("<tr>" + "".join(f"<td>{e(c)}</td>" for c in r)
                                             + "</tr>" for r in rows) + "</table>")
        for path, caption in s.figures:
            if path.exists():
                data = base64.b64encode(path.read_bytes()).decode()
                parts.append(f"<figure><img alt='{e(caption)}' src='data:image/png;base64,"
                             f"{data}'><figcaption>{e(caption)}</figcaption></figure>")
        parts += s.views
    parts.append("</body></html>")
    return "\n".join(parts)
