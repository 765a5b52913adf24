"""Renders the message reference in docs/protocol.md from messages.toml (`--check`: stale?)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .spec import SCALARS, Spec, load_spec

DOC = Path(__file__).resolve().parents[1] / "docs" / "protocol.md"
BEGIN = "<!-- BEGIN GENERATED: python -m dmdsm.protocol.gen_docs -->"
END = "<!-- END GENERATED -->"


def render(spec: Spec | None = None) -> str:
    """Markdown tables of every message, enum and flag in the spec."""
    spec = spec or load_spec()
    out = [BEGIN, "", f"Spec hash: `{spec.hash:016x}` · protocol version {spec.version} · "
           f"max payload {spec.max_payload} B · max encoded frame {spec.max_encoded} B "
           f"(firmware accepts commands up to {spec.max_command_payload} B of payload)", ""]
    out += ["### Flags", "", "| bit | name | meaning |", "|---|---|---|"]
    for name, bit in spec.flags.items():
        out.append(f"| 0x{bit:02x} | `{name}` | {spec.flag_docs[name]} |")
    out.append("")
    for m in spec.messages:
        arrow = "host → device" if m.dir == "host" else "device → host"
        reply = f"; answered by `{m.reply}` (or `nak`)" if m.reply else ""
        out += [f"### 0x{m.id:02X} `{m.name}` ({arrow})", "", f"{m.doc}{reply}.", ""]
        if not m.fields:
            out += ["Empty payload.", ""]
            continue
        out += ["| offset | field | type | unit | range / enum | meaning |",
                "|---|---|---|---|---|---|"]
        off = 0
        for f in m.fields:
            rng = f"`{f.enum}`" if f.enum else (
                f"{f.min if f.min is not None else ''}..{f.max if f.max is not None else ''}"
                if f.min is not None or f.max is not None else "")
            where = str(off) if not f.is_tail else f"{off}.."
            out.append(f"| {where} | `{f.name}` | {f.type} | {f.unit} | {rng} | {f.doc} |")
            if not f.is_tail:
                off += SCALARS[f.type][1]
        out += ["", f"Fixed part: {m.fixed.size} B.", ""]
    out += ["### Enums", ""]
    for ename, values in spec.enums.items():
        out.append(f"`{ename}` ({spec.enum_docs[ename]['']}): " + ", ".join(
            f"{v} = `{k}`" for k, v in values.items()))
        out.append("")
    out.append(END)
    return "\n".join(out)


def splice(text: str, generated: str) -> str:
    """The doc text with its generated section replaced."""
    a = text.index(BEGIN)
    b = text.index(END) + len(END)
    return text[:a] + generated + text[b:]


def main(argv: list[str] | None = None) -> int:
    """Rewrite (or with --check, verify) the generated part of docs/protocol.md."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true")
    args = ap.parse_args(argv)
    text = DOC.read_text(encoding="utf-8")
    new = splice(text, render())
    if args.check:
        if new != text:
            print(f"{DOC} is stale: run python -m dmdsm.protocol.gen_docs", file=sys.stderr)
            return 1
        return 0
    DOC.write_text(new, encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
