"""Hypothesis strategies for protocol messages built from the spec."""

import numpy as np
from hypothesis import strategies as st

from dmdsm.protocol import Message, load_spec
from dmdsm.protocol.spec import SAMPLE_DTYPES, MessageSpec

SPEC = load_spec()


def message_of(ms: MessageSpec, max_samples: int = 300) -> st.SearchStrategy[Message]:
    """Any valid message of one type, with every field anywhere in its wire range."""
    fields = {}
    for fs in ms.scalar_fields:
        if fs.name == "sample_format" and ms.tail is not None and ms.tail.type == "samples":
            fields[fs.name] = st.sampled_from(sorted(SAMPLE_DTYPES))
        elif fs.type == "f32":
            fields[fs.name] = st.floats(width=32, allow_nan=False)
        else:
            lo, hi = fs.int_range()
            fields[fs.name] = st.integers(lo, hi)

    @st.composite
    def build(draw: st.DrawFn) -> Message:
        values = {k: draw(v) for k, v in fields.items()}
        tail = ms.tail
        if tail is not None:
            if tail.type == "str":
                values[tail.name] = draw(st.text(max_size=60))
            elif tail.type == "bytes":
                values[tail.name] = draw(st.binary(max_size=100))
            else:
                dtype = np.dtype(SAMPLE_DTYPES[values["sample_format"]])
                n = draw(st.integers(0, max_samples))
                hi = np.iinfo(dtype).max
                mode = draw(st.sampled_from(["random", "zeros", "nonzero"]))
                seed = draw(st.integers(0, 2**32 - 1))
                rng = np.random.default_rng(seed)
                if mode == "zeros":
                    arr = np.zeros(n, dtype)
                elif mode == "nonzero":
                    arr = np.full(n, 0x0101, dtype)
                else:
                    arr = rng.integers(0, hi, n, dtype=dtype, endpoint=True)
                values[tail.name] = arr
        seq = draw(st.integers(0, 0xFFFF))
        flags = draw(st.integers(0, 255))
        return Message(ms, seq=seq, flags=flags, **values)

    return build()


any_message = st.sampled_from(SPEC.messages).flatmap(message_of)
