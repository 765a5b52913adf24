"""The demo's report: sections of text, tables and figures, written as Markdown and as one
self-contained HTML file (figures embedded as base64 PNG)."""

from __future__ import annotations

import base64
import html
from dataclasses import dataclass, field
from pathlib import Path


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

    def table(self, header: list[str], rows: list[list[object]]) -> None:
        """Add a table (cells formatted with str)."""
        self.tables.append((header, [[str(c) for c in r] for r in rows]))


def markdown(title: str, sections: list[Section]) -> str:
    """The report as Markdown (figures linked by file name)."""
    out = [f"# {title}", ""]
    for s in sections:
        out += [f"## {s.title} — {'ok' if s.ok else 'FAILED'} ({s.seconds:.0f} s)", ""]
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


def html_page(title: str, sections: list[Section]) -> str:
    """The report as one HTML file with the figures inside it."""
    e = html.escape
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>{e(title)}</title>",
             "<style>body{font-family:sans-serif;max-width:1100px;margin:2em auto;"
             "line-height:1.4}table{border-collapse:collapse;margin:0.5em 0}"
             "td,th{border:1px solid #bbb;padding:3px 8px;text-align:left}"
             "th{background:#eee}.ok{color:#060}.bad{color:#a00}img{max-width:100%}"
             "figcaption{font-size:90%;color:#444}</style></head><body>",
             f"<h1>{e(title)}</h1>"]
    parts.append("<table><tr><th>stage</th><th>result</th><th>time (s)</th></tr>" + "".join(
        f"<tr><td>{e(s.title)}</td><td class='{'ok' if s.ok else 'bad'}'>"
        f"{'ok' if s.ok else 'FAILED'}</td><td>{s.seconds:.0f}</td></tr>" for s in sections)
        + "</table>")
    for s in sections:
        parts.append(f"<h2>{e(s.title)} <span class='{'ok' if s.ok else 'bad'}'>"
                     f"({'ok' if s.ok else 'FAILED'})</span></h2>")
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
    parts.append("</body></html>")
    return "\n".join(parts)
