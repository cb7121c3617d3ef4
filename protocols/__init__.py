"""linereg's wire contract: versioned msgpack messages, key expressions, limits (see SPEC.md).

This layer encodes and validates bytes only; it never opens a network session.
"""

from .arrays import decode_array, encode_array
from .codec import (
    decode_error,
    decode_reply,
    decode_request,
    encode_error,
    encode_reply,
    encode_request,
    message_type,
    pack,
    request_id,
    unpack,
)
from .errors import ERROR_CODES, ProtocolError
from .messages import PROTOCOL_VERSION, Error, Limits, LocalizeReply, LocalizeRequest, Prior
from .session import SessionClose, SessionClosed, SessionOpen, SessionOpened, TrackReply, TrackRequest

__all__ = [
    "ERROR_CODES",
    "PROTOCOL_VERSION",
    "Error",
    "Limits",
    "LocalizeReply",
    "LocalizeRequest",
    "Prior",
    "ProtocolError",
    "SessionClose",
    "SessionClosed",
    "SessionOpen",
    "SessionOpened",
    "TrackReply",
    "TrackRequest",
    "decode_array",
    "decode_error",
    "decode_reply",
    "decode_request",
    "encode_array",
    "encode_error",
    "encode_reply",
    "encode_request",
    "message_type",
    "pack",
    "request_id",
    "unpack",
]
