"""`dmdsm protocol decode|encode`: a raw serial capture as messages, or frames from JSON."""

from __future__ import annotations

import argparse
import io
import json
import sys
from collections.abc import Iterator
from typing import BinaryIO, TextIO

import numpy as np

from .frame import FrameDecoder, FrameError, encode_frame
from .messages import Message, MessageError, from_jsonable, to_jsonable
from .spec import load_spec

CHUNK = 1 << 16


class ToolError(Exception):
    """A user-facing one-line error (bad file, bad JSON line)."""


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register `protocol decode` and `protocol encode` under a `dmdsm` subcommand parser."""
    p = sub.add_parser("protocol", help="decode or encode raw protocol frames (debugging)")
    psub = p.add_subparsers(dest="protocol_cmd", required=True)
    d = psub.add_parser("decode", help="print the messages in a raw byte capture")
    d.add_argument("file", help="capture file, or - for stdin")
    d.add_argument("--json", action="store_true",
                   help="one JSON object per message (errors and summary go to stderr)")
    d.add_argument("--max-samples", type=int, default=None,
                   help="table mode: samples shown per waveform (default 8)")
    d.set_defaults(func=cmd_decode)
    e = psub.add_parser("encode", help="turn JSON lines (as decode --json prints) into frames")
    e.add_argument("file", nargs="?", default="-", help="JSON-lines file, or - for stdin")
    e.add_argument("-o", "--output", default="-", help="output file (default stdout)")
    e.add_argument("--json", action="store_true",
                   help="with -o FILE: print what was written as one JSON line")
    e.set_defaults(func=cmd_encode)


def _open_binary(path: str) -> BinaryIO:
    if path == "-":
        return sys.stdin.buffer
    try:
        return open(path, "rb")  # noqa: SIM115 - closed by the caller
    except OSError as e:
        raise ToolError(f"cannot read capture {path}: {e.strerror}") from None


def iter_chunks(f: BinaryIO) -> Iterator[bytes]:
    """Chunks of a binary stream until EOF."""
    while chunk := f.read(CHUNK):
        yield chunk


def _summary(msg: Message, max_samples: int) -> str:
    spec = load_spec()
    parts = []
    for fs in msg.spec.fields:
        v = msg.fields[fs.name]
        if isinstance(v, np.ndarray):
            head = " ".join(str(x) for x in v[:max_samples])
            more = " ..." if v.size > max_samples else ""
            stats = f" min={v.min()} max={v.max()}" if v.size else ""
            parts.append(f"{fs.name}[{v.size} x {v.dtype.name}]={head}{more}{stats}")
            continue
        if fs.enum:
            name = spec.enum_name(fs.enum, v)
            v = name if name is not None else f"{v}(undefined)"
        elif fs.name == "spec_hash":
            v = f"{v:016x}"
        parts.append(f"{fs.name}={v}")
    return " ".join(parts)


def _flags_text(flags: int) -> str:
    return ("R" if flags & 1 else "-") + ("T" if flags & 2 else "-") + (
        "?" if flags & ~3 else "")


def cmd_decode(args: argparse.Namespace, out: TextIO | None = None,
               err: TextIO | None = None) -> int:
    """Decode a capture; table or JSON lines on stdout, error summary at the end."""
    out = out or sys.stdout
    err = err or sys.stderr
    f = _open_binary(args.file)
    dec = FrameDecoder(report_errors=True)
    max_samples = 8 if args.max_samples is None else args.max_samples
    if not args.json:
        print(f"{'offset':>8}  {'seq':>5}  fl  {'type':<16} fields", file=out)
    try:
        for chunk in iter_chunks(f):
            for item in dec.feed(chunk):
                if isinstance(item, FrameError):
                    if args.json:
                        print(json.dumps({"error": item.kind, "offset": item.offset,
                                          "length": item.length, "detail": item.detail}),
                              file=err)
                    else:
                        print(f"{item.offset:>8}  {'':>5}  --  {'! ' + item.kind:<16} "
                              f"{item.detail} ({item.length} B)", file=out)
                elif args.json:
                    obj = {"offset": item.offset, **to_jsonable(item)}
                    print(json.dumps(obj), file=out)
                else:
                    print(f"{item.offset:>8}  {item.seq:>5}  {_flags_text(item.flags)}  "
                          f"{item.name:<16} {_summary(item, max_samples)}", file=out)
    finally:
        if f is not sys.stdin.buffer:
            f.close()
    s = dec.stats
    tail = len(dec._buf)
    errors = {k: v for k, v in s.as_dict().items() if k not in ("frames", "bytes") and v}
    text = (f"{s.frames} messages in {s.bytes} bytes; "
            + (", ".join(f"{k}={v}" for k, v in errors.items()) if errors else "no errors")
            + (f"; {tail} bytes of an unfinished frame at the end" if tail else ""))
    if args.json:
        print(json.dumps({"summary": {**s.as_dict(), "unfinished_bytes": tail}}), file=err)
    else:
        print(text, file=out)
    return 0


def _encode_line(no: int, line: str, spec: object) -> bytes | None:
    """The frame of one JSON line (None for blank lines, comments and decode diagnostics)."""
    if not line.strip() or line.lstrip().startswith("#"):
        return None
    try:
        obj = json.loads(line)
    except json.JSONDecodeError as e:
        raise ToolError(f"line {no}: not JSON ({e.msg} at column {e.colno})") from None
    if isinstance(obj, dict) and ("error" in obj or "summary" in obj):
        return None  # decode --json diagnostics
    try:
        return encode_frame(from_jsonable(obj, spec), spec)
    except MessageError as e:
        raise ToolError(f"line {no}: {e}") from None


def cmd_encode(args: argparse.Namespace) -> int:
    """Encode JSON lines into frame bytes."""
    spec = load_spec()
    if args.json and args.output == "-":
        raise ToolError("--json needs -o FILE: without it the frames themselves go to stdout")
    if args.file == "-":  # strict UTF-8 whatever the locale (C gives surrogateescape)
        lines = io.TextIOWrapper(sys.stdin.buffer, encoding="utf-8", errors="strict")
    else:
        try:
            lines = open(args.file, encoding="utf-8")  # noqa: SIM115
        except OSError as e:
            raise ToolError(f"cannot read {args.file}: {e.strerror}") from None
    frames = []
    try:
        no = 0
        for no, line in enumerate(lines, 1):
            frame = _encode_line(no, line, spec)
            if frame is not None:
                frames.append(frame)
    except UnicodeDecodeError:
        raise ToolError(f"near line {no + 1}: not UTF-8 text; encode takes JSON lines (a raw "
                        f"byte capture is read with `dmdsm protocol decode`)") from None
    data = b"".join(frames)
    if args.output == "-":
        sys.stdout.buffer.write(data)
        sys.stdout.buffer.flush()
    else:
        try:
            with open(args.output, "wb") as f:
                f.write(data)
        except OSError as e:
            raise ToolError(f"cannot write {args.output}: {e.strerror}") from None
        if args.json:
            print(json.dumps({"output": args.output, "frames": len(frames), "bytes": len(data)}))
    return 0
