"""Generates the firmware's C message codec (protocol/c/dmdsm_spec.[ch]) from messages.toml.

Run `python -m dmdsm.protocol.gen_c` after editing the spec; `--check` exits 1 if the
committed files are stale (make test runs it).
"""

from __future__ import annotations

import argparse
import sys
import zlib
from pathlib import Path

from .spec import CRC_SIZE, HEADER, SAMPLE_DTYPES, SCALARS, MessageSpec, Spec, load_spec

OUT_DIR = Path(__file__).with_name("c")
BANNER = "/* Generated from protocol/messages.toml by protocol/gen_c.py: do not edit. */\n"
CTYPES = {"u8": "uint8_t", "u16": "uint16_t", "u32": "uint32_t", "u64": "uint64_t",
          "i8": "int8_t", "i16": "int16_t", "i32": "int32_t", "i64": "int64_t", "f32": "float"}
SIGN_EXTEND = """static int64_t sign_extend(uint64_t v, unsigned n)
{
    uint64_t sign = (uint64_t)1 << (8u * n - 1u);
    return (int64_t)((v ^ sign) - sign);
}

"""
TAIL_KIND = {"bytes": 1, "str": 2, "samples": 3}


def _crc_table() -> list[int]:
    table = []
    for i in range(256):
        c = i
        for _ in range(8):
            c = (c >> 1) ^ 0xEDB88320 if c & 1 else c >> 1
        table.append(c)
    assert zlib.crc32(b"123456789") == 0xCBF43926
    return table


def _header(spec: Spec) -> str:
    up = str.upper
    out = [BANNER, "/* The dmdsm protocol: constants, enums, message structs and codecs. */\n",
           "#ifndef DMDSM_SPEC_H\n#define DMDSM_SPEC_H\n\n",
           "#include <stdbool.h>\n#include <stddef.h>\n#include <stdint.h>\n\n",
           f"#define DMDSM_PROTOCOL_VERSION {spec.version}u\n",
           f"#define DMDSM_SPEC_HASH UINT64_C(0x{spec.hash:016x})\n",
           f"#define DMDSM_MAX_PAYLOAD {spec.max_payload}u\n",
           f"#define DMDSM_MAX_COMMAND_PAYLOAD {spec.max_command_payload}u\n",
           f"#define DMDSM_SYNC_QUIET_MS {spec.sync_quiet_ms}u\n",
           f"#define DMDSM_HEADER_SIZE {HEADER.size}u\n#define DMDSM_CRC_SIZE {CRC_SIZE}u\n",
           "/* largest un-stuffed frame and largest COBS frame between delimiters */\n",
           f"#define DMDSM_MAX_RAW {spec.max_raw}u\n",
           f"#define DMDSM_MAX_ENCODED {spec.max_encoded}u\n",
           "#define DMDSM_ENCODED_SIZE(raw) ((raw) + (raw) / 254u + 1u)\n\n"]
    for name, bit in spec.flags.items():
        out.append(f"#define DMDSM_FLAG_{up(name)} 0x{bit:02x}u /* {spec.flag_docs[name]} */\n")
    for ename, values in spec.enums.items():
        out.append(f"\n/* {spec.enum_docs[ename]['']} */\nenum dmdsm_{ename} {{\n")
        for vname, v in values.items():
            out.append(f"    DMDSM_{up(ename)}_{up(vname)} = {v}, "
                       f"/* {spec.enum_docs[ename][vname]} */\n")
        out.append("};\n")
    out.append("\nenum dmdsm_msg_type {\n")
    for m in spec.messages:
        out.append(f"    DMDSM_MSG_{up(m.name)} = 0x{m.id:02x},\n")
    out.append("};\n")
    for m in spec.messages:
        to = "device" if m.dir == "host" else "host"
        out.append(f"\n/* {m.name}: {m.doc} ({m.dir} -> {to}) */\n")
        out.append(f"#define DMDSM_{up(m.name)}_FIXED_SIZE {m.fixed.size}u\n")
        out.append(f"struct dmdsm_{m.name} {{\n")
        for f in m.scalar_fields:
            unit = f" [{f.unit}]" if f.unit else ""
            out.append(f"    {CTYPES[f.type]} {f.name}; /* {f.doc}{unit} */\n")
        if m.tail:
            out.append(f"    const uint8_t *{m.tail.name}; /* {m.tail.doc} */\n")
            out.append(f"    size_t {m.tail.name}_len; /* bytes */\n")
        if not m.fields:
            out.append("    uint8_t unused_; /* no fields */\n")
        out.append("};\n")
        out.append(f"size_t dmdsm_pack_{m.name}(const struct dmdsm_{m.name} *m, uint8_t *out);\n")
        out.append(f"bool dmdsm_unpack_{m.name}(const uint8_t *p, size_t len, "
                   f"struct dmdsm_{m.name} *m);\n")
        if any(f.min is not None or f.max is not None for f in m.fields):
            out.append(f"/* 0 if every field is within its range, else 1 + index of the first "
                       f"that is not */\nunsigned dmdsm_check_{m.name}"
                       f"(const struct dmdsm_{m.name} *m);\n")
    out.append("""
/* static facts about one message type */
struct dmdsm_msg_info {
    uint8_t id;
    uint8_t from_host;   /* 1: host -> device command, 0: device -> host */
    uint8_t tail_kind;   /* 0 none, 1 bytes, 2 str, 3 samples */
    uint16_t fixed_size; /* bytes of fixed fields */
    uint8_t reply;       /* type id of the success reply (commands), else 0 */
    const char *name;
};

/* info for a type id, or NULL if the type is not in the spec */
const struct dmdsm_msg_info *dmdsm_msg_info(uint8_t type);
/* true if a payload of this length (and sample_format) fits the message type */
bool dmdsm_payload_ok(uint8_t type, const uint8_t *payload, size_t len);
/* writes "field=value ..." (tails as name:len=N:crc=8 hex digits); returns chars
 * that a large enough buffer needs, like snprintf */
int dmdsm_msg_format(uint8_t type, const uint8_t *payload, size_t len,
                     char *out, size_t cap);
/* zlib/IEEE CRC-32 table, reflected polynomial 0xEDB88320 */
extern const uint32_t dmdsm_crc32_table[256];

#endif /* DMDSM_SPEC_H */
""")
    return "".join(out)


def _put(f_type: str, expr: str, off: str) -> str:
    if f_type == "f32":
        return (f"    {{ uint32_t u_; memcpy(&u_, &{expr}, 4); "
                f"put_le(out + {off}, u_, 4); }}\n")
    n = SCALARS[f_type][1]
    return f"    put_le(out + {off}, (uint64_t)(uint{8 * n}_t){expr}, {n});\n"


def _get(f_type: str, dst: str, off: str) -> str:
    n = SCALARS[f_type][1]
    if f_type == "f32":
        return f"    {{ uint32_t u_ = (uint32_t)get_le(p + {off}, 4); memcpy(&{dst}, &u_, 4); }}\n"
    return f"    {dst} = ({CTYPES[f_type]})get_le(p + {off}, {n});\n"


def _message_code(m: MessageSpec) -> str:
    out = [f"\nsize_t dmdsm_pack_{m.name}(const struct dmdsm_{m.name} *m, uint8_t *out)\n{{\n"]
    if not m.fields:
        out.append("    (void)m;\n    (void)out;\n")
    off = 0
    for f in m.scalar_fields:
        out.append(_put(f.type, f"m->{f.name}", str(off)))
        off += SCALARS[f.type][1]
    if m.tail:
        out.append(f"    if (m->{m.tail.name}_len)\n        memcpy(out + {off}, "
                   f"m->{m.tail.name}, m->{m.tail.name}_len);\n")
        out.append(f"    return {off}u + m->{m.tail.name}_len;\n}}\n")
    else:
        out.append(f"    return {off}u;\n}}\n")
    out.append(f"\nbool dmdsm_unpack_{m.name}(const uint8_t *p, size_t len, "
               f"struct dmdsm_{m.name} *m)\n{{\n")
    out.append(f"    if (!dmdsm_payload_ok(0x{m.id:02x}, p, len))\n        return false;\n")
    if not m.fields:
        out.append("    m->unused_ = 0;\n")
    off = 0
    for f in m.scalar_fields:
        out.append(_get(f.type, f"m->{f.name}", str(off)))
        off += SCALARS[f.type][1]
    if m.tail:
        out.append(f"    m->{m.tail.name} = p + {off};\n    m->{m.tail.name}_len = len - {off}u;\n")
    out.append("    return true;\n}\n")
    checks = [(i, f) for i, f in enumerate(m.fields) if f.min is not None or f.max is not None]
    if checks:
        out.append(f"\nunsigned dmdsm_check_{m.name}(const struct dmdsm_{m.name} *m)\n{{\n")
        for i, f in checks:
            conds = []
            if f.min is not None and f.min > 0:
                conds.append(f"m->{f.name} < {f.min}u")
            if f.max is not None:
                conds.append(f"m->{f.name} > {f.max}u")
            if conds:
                out.append(f"    if ({' || '.join(conds)})\n        return {i + 1}u;\n")
        out.append("    return 0;\n}\n")
    return "".join(out)


def _format_case(m: MessageSpec) -> str:
    out = [f"    case 0x{m.id:02x}: {{\n"]
    off = 0
    for f in m.scalar_fields:
        n = SCALARS[f.type][1]
        if f.type == "f32":
            out.append(f"        {{ uint32_t u_ = (uint32_t)get_le(payload + {off}, 4); float v_; "
                       f"memcpy(&v_, &u_, 4);\n          put(&w, \"{f.name}=%.9g \", "
                       f"(double)v_); }}\n")
        elif f.type.startswith("i"):
            out.append(f"        put(&w, \"{f.name}=%lld \", (long long)sign_extend("
                       f"get_le(payload + {off}, {n}), {n}));\n")
        else:
            out.append(f"        put(&w, \"{f.name}=%llu \", (unsigned long long)"
                       f"get_le(payload + {off}, {n}));\n")
        off += n
    if m.tail:
        out.append(f"        put(&w, \"{m.tail.name}:len=%lu:crc=%08lx \", (unsigned long)"
                   f"(len - {off}u),\n            (unsigned long)crc32_of(payload + {off}, "
                   f"len - {off}u));\n")
    out.append("        break;\n    }\n")
    return "".join(out)


def _source(spec: Spec) -> str:
    by_name = spec.by_name
    out = [BANNER, "/* The dmdsm protocol: message packing, checks and the CRC table. */\n\n",
           "#include \"dmdsm_spec.h\"\n\n#include <stdarg.h>\n#include <stdio.h>\n"
           "#include <string.h>\n\n"]
    out.append("""static void put_le(uint8_t *out, uint64_t v, unsigned n)
{
    for (unsigned i = 0; i < n; i++)
        out[i] = (uint8_t)(v >> (8u * i));
}

static uint64_t get_le(const uint8_t *p, unsigned n)
{
    uint64_t v = 0;
    for (unsigned i = 0; i < n; i++)
        v |= (uint64_t)p[i] << (8u * i);
    return v;
}

%SIGN_EXTEND%static uint32_t crc32_of(const uint8_t *p, size_t n)
{
    uint32_t c = 0xFFFFFFFFu;
    while (n--)
        c = dmdsm_crc32_table[(c ^ *p++) & 0xFFu] ^ (c >> 8);
    return c ^ 0xFFFFFFFFu;
}

struct writer {
    char *out;
    size_t cap;
    size_t len;
};

static void put(struct writer *w, const char *fmt, ...)
{
    va_list ap;
    va_start(ap, fmt);
    size_t room = w->len < w->cap ? w->cap - w->len : 0;
    int n = vsnprintf(room ? w->out + w->len : NULL, room, fmt, ap);
    va_end(ap);
    if (n > 0)
        w->len += (size_t)n;
}

static const struct dmdsm_msg_info infos[] = {
""")
    signed = any(f.type.startswith("i") for m in spec.messages for f in m.fields)
    out[-1] = out[-1].replace("%SIGN_EXTEND%", SIGN_EXTEND if signed else "")
    for m in spec.messages:
        tail = TAIL_KIND[m.tail.type] if m.tail else 0
        reply = by_name[m.reply].id if m.reply else 0
        out.append(f"    {{0x{m.id:02x}, {int(m.dir == 'host')}, {tail}, {m.fixed.size}, "
                   f"0x{reply:02x}, \"{m.name}\"}},\n")
    out.append("};\n\nconst struct dmdsm_msg_info *dmdsm_msg_info(uint8_t type)\n{\n"
               "    for (size_t i = 0; i < sizeof infos / sizeof infos[0]; i++)\n"
               "        if (infos[i].id == type)\n            return &infos[i];\n"
               "    return NULL;\n}\n")
    out.append("\nbool dmdsm_payload_ok(uint8_t type, const uint8_t *payload, size_t len)\n{\n"
               "    const struct dmdsm_msg_info *mi = dmdsm_msg_info(type);\n"
               "    if (mi == NULL || len < mi->fixed_size)\n        return false;\n"
               "    switch (type) {\n")
    for m in spec.messages:
        if m.tail and m.tail.type == "samples":
            off = 0
            for f in m.scalar_fields:
                if f.name == "sample_format":
                    break
                off += SCALARS[f.type][1]
            out.append(f"    case 0x{m.id:02x}:\n        switch (payload[{off}]) {{\n")
            for code, dtype in SAMPLE_DTYPES.items():
                out.append(f"        case {code}:\n            return (len - mi->fixed_size) % "
                           f"{int(dtype[-1])}u == 0;\n")
            out.append("        default:\n            return false;\n        }\n")
    out.append("    default:\n        return mi->tail_kind != 0 || len == mi->fixed_size;\n"
               "    }\n}\n")
    for m in spec.messages:
        out.append(_message_code(m))
    out.append("\nint dmdsm_msg_format(uint8_t type, const uint8_t *payload, size_t len,\n"
               "                     char *out, size_t cap)\n{\n"
               "    struct writer w = {out, cap, 0};\n"
               "    if (cap)\n        out[0] = '\\0';\n"
               "    if (!dmdsm_payload_ok(type, payload, len))\n        return -1;\n"
               "    switch (type) {\n")
    for m in spec.messages:
        out.append(_format_case(m))
    out.append("    default:\n        return -1;\n    }\n"
               "    if (w.len && w.len <= cap)\n        out[w.len - 1] = '\\0';\n"
               "    return w.len ? (int)w.len - 1 : 0;\n}\n")
    table = _crc_table()
    out.append("\nconst uint32_t dmdsm_crc32_table[256] = {\n")
    for i in range(0, 256, 6):
        out.append("    " + ", ".join(f"0x{v:08x}u" for v in table[i:i + 6]) + ",\n")
    out.append("};\n")
    return "".join(out)


def generate(spec: Spec | None = None) -> dict[str, str]:
    """File name -> generated text for the C codec."""
    spec = spec or load_spec()
    return {"dmdsm_spec.h": _header(spec), "dmdsm_spec.c": _source(spec)}


def stale_files(out_dir: Path = OUT_DIR) -> list[str]:
    """Names of generated files whose committed text differs from the spec's."""
    return [name for name, text in generate().items()
            if not (out_dir / name).exists()
            or (out_dir / name).read_text(encoding="utf-8") != text]


def main(argv: list[str] | None = None) -> int:
    """Write (or with --check, verify) the generated C files."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="exit 1 if the files are stale")
    ap.add_argument("--out", type=Path, default=OUT_DIR, help="output folder")
    args = ap.parse_args(argv)
    if args.check:
        stale = stale_files(args.out)
        for name in stale:
            print(f"{args.out / name} is stale: run python -m dmdsm.protocol.gen_c",
                  file=sys.stderr)
        return 1 if stale else 0
    args.out.mkdir(parents=True, exist_ok=True)
    for name, text in generate().items():
        (args.out / name).write_text(text, encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
