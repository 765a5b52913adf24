"""The dmdsm host <-> STM32 protocol: spec, framing and message codec (see docs/protocol.md)."""

from .frame import (
    DecodeStats,
    FrameDecoder,
    FrameError,
    cobs_extension_loaded,
    encode_frame,
    encode_raw,
)
from .messages import Message, MessageError, from_jsonable, pack_payload, to_jsonable
from .spec import Spec, load_spec

__all__ = [
    "DecodeStats", "FrameDecoder", "FrameError", "Message", "MessageError", "Spec",
    "cobs_extension_loaded", "encode_frame", "encode_raw", "from_jsonable", "load_spec",
    "pack_payload", "to_jsonable",
]
