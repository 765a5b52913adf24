"""rosbag2's metadata.yaml for an MCAP file, so that ROS 2 (Humble) opens the bag folder as it is.

`ros2 bag info/play` (Humble) opens a bag *folder*: metadata.yaml (version 5) naming the
storage (`mcap`), the files, the topics with their types, serialization (`cdr`) and offered
QoS, and the counts and times; the .mcap beside it. `bag_metadata` computes all of it from a
finished MCAP file's own summary (statistics, channels, schemas: the `mcap` reader), or, for a
file that ended without one (a recording stopped by a full disk), from its records read
through. Times in nanoseconds (the MCAP's log times); duration = last - first, as rosbag2
counts it. The YAML is written by hand in the layout Humble writes (block style, strings
double-quoted where a bare word would not read back as the same string); rosbag2's reindex
(`ros2 bag reindex BAG mcap`) writes the same information.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

from ..files import OutputError, atomic_output, check_folder, check_output, one_line, write_failed

VERSION = 5          # the metadata version ROS 2 Humble writes and reads
METADATA = "metadata.yaml"
STORAGE = "mcap"
_PLAIN = re.compile(r"/?[A-Za-z_][A-Za-z0-9_./-]*")  # /topic, pkg/msg/Type, name_0.mcap
_WORDS = {"true", "false", "yes", "no", "on", "off", "null", "y", "n"}  # YAML 1.1 non-strings


def bag_file(bag: Path, flag: str = "--bag") -> Path:
    """The MCAP file of a bag folder: BAG/NAME_0.mcap, NAME the folder's name (as
    `ros2 bag record -o BAG` names it). Checks, touching nothing, that BAG is a folder or a
    new name in an existing writable folder and that its MCAP and metadata.yaml may be
    written (files.check_output); OutputError (one line) otherwise."""
    bag = Path(bag)
    name = Path(os.path.abspath(bag)).name or "bag"
    mcap = bag / f"{name}_0.mcap"
    if os.path.lexists(bag) and not bag.is_dir():
        raise OutputError(f"{bag} is not a folder: {flag} names the bag's folder (created if "
                          f"missing), e.g. {flag} {bag.with_suffix('')}_bag")
    if bag.is_dir():
        for path in (mcap, bag / METADATA):
            check_output(path, True, flag)
        return mcap
    check_folder(bag, f"create the bag {bag}", f"another {flag}", flag)
    return mcap


def make_bag_dir(bag: Path, flag: str = "--bag") -> bool:
    """Create the bag folder if it is missing (its parent must exist); True if created."""
    try:
        os.mkdir(bag)
    except FileExistsError:
        return False
    except OSError as e:
        raise write_failed(Path(bag), e, flag) from None
    return True


def drop_metadata(bag: Path) -> None:
    """Remove an earlier metadata.yaml (the file it points to, through a link) before the
    bag's MCAP is replaced, so that no metadata.yaml ever describes another file."""
    try:
        os.unlink(os.path.realpath(Path(bag) / METADATA))
    except FileNotFoundError:
        pass


def bag_metadata(mcap_path: Path, name: str | None = None) -> dict:
    """rosbag2's bag information (the `rosbag2_bagfile_information` mapping, version 5) of one
    MCAP file, named `name` in the bag (default: its own name): from its summary, or from its
    records read through when it has none. Times in ns. ValueError (one line) if the file is
    no MCAP the `mcap` reader can read."""
    from mcap.exceptions import McapError

    path = Path(mcap_path)
    try:
        with open(path, "rb") as f:
            channels, schemas, counts, start, end = _from_summary(f) or _read_through(f)
    except (McapError, EOFError, ValueError, KeyError, OSError) as e:
        raise ValueError(f"cannot read {path} as MCAP ({one_line(str(e) or type(e).__name__, 120)})"
                         ) from None
    total = sum(counts.values())
    start, duration = (start, end - start) if total else (0, 0)
    name = name or path.name
    topics = [{"topic_metadata": {"name": ch.topic,
                                  "type": schemas[ch.schema_id].name if ch.schema_id in schemas
                                  else "",
                                  "serialization_format": ch.message_encoding,
                                  "offered_qos_profiles": ch.metadata.get(
                                      "offered_qos_profiles", "")},
               "message_count": counts.get(cid, 0)} for cid, ch in sorted(channels.items())]
    times = {"starting_time": {"nanoseconds_since_epoch": start},
             "duration": {"nanoseconds": duration}}
    return {"version": VERSION, "storage_identifier": STORAGE,
            "duration": times["duration"], "starting_time": times["starting_time"],
            "message_count": total, "topics_with_message_count": topics,
            "compression_format": "", "compression_mode": "",
            "relative_file_paths": [name],
            "files": [{"path": name, **times, "message_count": total}]}


def _from_summary(f: object) -> tuple | None:
    """(channels, schemas, counts per channel id, first ns, last ns) from the summary section;
    None if the file has none (or no statistics in it)."""
    from mcap.reader import make_reader

    summary = make_reader(f).get_summary()
    if summary is None or summary.statistics is None:
        return None
    st = summary.statistics
    return (summary.channels, summary.schemas, dict(st.channel_message_counts),
            st.message_start_time, st.message_end_time)


def _read_through(f: object) -> tuple:
    """The same from every record of the data section (chunks opened)."""
    from mcap.records import Channel, Message, Schema
    from mcap.stream_reader import StreamReader

    f.seek(0)
    channels, schemas, counts = {}, {}, {}
    start, end = None, 0
    for r in StreamReader(f).records:
        if isinstance(r, Schema):
            schemas[r.id] = r
        elif isinstance(r, Channel):
            channels[r.id] = r
        elif isinstance(r, Message):
            counts[r.channel_id] = counts.get(r.channel_id, 0) + 1
            start = r.log_time if start is None else min(start, r.log_time)
            end = max(end, r.log_time)
    return channels, schemas, counts, start or 0, end


def metadata_yaml(info: dict) -> str:
    """The metadata.yaml text of bag information (bag_metadata's): the mapping under
    `rosbag2_bagfile_information`, in block style as Humble writes it; every string that a
    YAML reader would not take back as the same string as a bare word is double-quoted
    (offered_qos_profiles always is, as rosbag2 writes it)."""
    return "\n".join(["rosbag2_bagfile_information:", *_block(info, 2)]) + "\n"


def _block(value: dict, indent: int) -> list[str]:
    pad, out = " " * indent, []
    for key, v in value.items():
        if isinstance(v, dict):
            out += [f"{pad}{key}:", *_block(v, indent + 2)]
        elif isinstance(v, list) and v:
            out.append(f"{pad}{key}:")
            for item in v:
                if isinstance(item, dict):
                    lines = _block(item, indent + 4)
                    out += [f"{pad}  - {lines[0].lstrip()}", *lines[1:]]
                else:
                    out.append(f"{pad}  - {_scalar(item)}")
        elif isinstance(v, list):
            out.append(f"{pad}{key}: []")
        else:
            out.append(f"{pad}{key}: "
                       f"{_quoted(v) if key == 'offered_qos_profiles' else _scalar(v)}")
    return out


def _scalar(v: object) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    s = str(v)
    return s if _PLAIN.fullmatch(s) and s.lower() not in _WORDS else _quoted(s)


def _quoted(s: str) -> str:
    """A YAML double-quoted scalar: escapes for the quote, the backslash and every character
    that is not printable (line breaks included)."""
    out = []
    for c in str(s):
        if c in '"\\':
            out.append("\\" + c)
        elif c == "\n":
            out.append("\\n")
        elif c.isprintable():
            out.append(c)
        else:
            out.append(f"\\u{ord(c):04x}" if ord(c) <= 0xFFFF else f"\\U{ord(c):08x}")
    return '"' + "".join(out) + '"'


def write_bag_metadata(bag: Path, mcap_path: Path, flag: str = "--bag") -> dict:
    """Write BAG/metadata.yaml for the finished MCAP file of that bag, atomically (a
    temporary file renamed: files.atomic_output); the bag information. OutputError (one
    line) if the file cannot be read back or the YAML written."""
    try:
        info = bag_metadata(mcap_path)
    except ValueError as e:
        raise OutputError(f"{e}: no {METADATA} written; `ros2 bag reindex {bag} mcap` "
                          f"makes one") from None
    with atomic_output(Path(bag) / METADATA, flag=flag) as tmp:
        tmp.write_text(metadata_yaml(info), encoding="utf-8")
    return info
