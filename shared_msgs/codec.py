"""Encode and decode skycap messages (MessagePack via msgspec), refusing malformed or wrong-version input.

    data = encode(msg)                       # bytes, with a "type" tag
    msg = decode(data)                       # any skycap message
    state = decode(data, VehicleState)       # or exactly this type

Errors are :class:`MessageError` naming what is wrong (field path, expected type, versions) and what to
do about it; a decoder never returns a half-valid message.
"""

from __future__ import annotations

import math
from typing import TypeVar, Union

import msgspec

from shared_msgs.messages import MESSAGE_TYPES, Header, Message, now_ns
from skycap.errors import SkycapError

T = TypeVar("T", bound=Message)

__all__ = ["MessageError", "encode", "decode", "stamp_sent", "TYPE_BY_TAG"]

TYPE_BY_TAG: dict[str, type[Message]] = {t.__struct_config__.tag: t for t in MESSAGE_TYPES}

_encoder = msgspec.msgpack.Encoder()
_any_decoder = msgspec.msgpack.Decoder(Union[MESSAGE_TYPES])  # type: ignore[valid-type]
_typed_decoders: dict[type, msgspec.msgpack.Decoder] = {}


class _Probe(msgspec.Struct):
    type: str
    header: Header


_probe_decoder = msgspec.msgpack.Decoder(_Probe)


class MessageError(SkycapError):
    """Input that is not a valid skycap message of a supported version."""


def encode(msg: Message) -> bytes:
    """MessagePack bytes of ``msg`` (its ``header.t_sent_ns`` as set; see :func:`stamp_sent`)."""
    if not isinstance(msg, Message):
        raise TypeError(f"encode() takes a skycap message, got {type(msg).__name__}")
    return _encoder.encode(msg)


def stamp_sent(msg: T, t_sent_ns: int | None = None) -> T:
    """Set the header's time of sending (the transport calls this right before publishing)."""
    msg.header.t_sent_ns = now_ns() if t_sent_ns is None else int(t_sent_ns)
    return msg


def decode(data: bytes | bytearray | memoryview, expected: type[T] | None = None, source: str = "") -> T:
    """Decode and validate one message; ``expected`` restricts the type; ``source`` names where it came from."""
    where = f" from {source}" if source else ""
    try:
        probe = _probe_decoder.decode(data)
    except (msgspec.DecodeError, msgspec.ValidationError) as e:
        raise MessageError(
            f"malformed skycap message{where}: {e}; the sender must encode with shared_msgs.codec.encode"
        ) from None
    cls = TYPE_BY_TAG.get(probe.type)
    if cls is None:
        raise MessageError(
            f"unknown message type {probe.type!r}{where}; known: {', '.join(sorted(TYPE_BY_TAG))}. "
            f"Sender and receiver run different skycap versions: update both"
        )
    if probe.header.schema_version != cls.SCHEMA_VERSION:
        raise MessageError(
            f"{probe.type} schema version {probe.header.schema_version}{where} from sender "
            f"{probe.header.sender_id!r}, this build speaks version {cls.SCHEMA_VERSION}; "
            f"update skycap on the {'older' if probe.header.schema_version < cls.SCHEMA_VERSION else 'receiving'} side"
        )
    if expected is not None and cls is not expected:
        raise MessageError(f"expected a {expected.__struct_config__.tag} message{where}, got {probe.type}")
    dec = _typed_decoders.get(cls)
    if dec is None:
        dec = _typed_decoders[cls] = msgspec.msgpack.Decoder(cls)
    try:
        msg = dec.decode(data)
    except (msgspec.DecodeError, msgspec.ValidationError) as e:
        raise MessageError(f"invalid {probe.type} message{where} from {probe.header.sender_id!r}: {e}") from None
    _check_finite(msg, probe.type, where)
    return msg  # type: ignore[return-value]


def _check_finite(obj, tag: str, where: str, path: str = "$") -> None:
    """Refuse NaN and infinities anywhere in a message (they are never valid measurements here)."""
    if isinstance(obj, float):
        if not math.isfinite(obj):
            raise MessageError(f"invalid {tag} message{where}: non-finite number {obj} at `{path}`")
    elif isinstance(obj, (tuple, list)):
        for i, v in enumerate(obj):
            if isinstance(v, (float, msgspec.Struct, tuple, list, dict)):
                _check_finite(v, tag, where, f"{path}[{i}]")
    elif isinstance(obj, dict):
        for k, v in obj.items():
            _check_finite(v, tag, where, f"{path}.{k}")
    elif isinstance(obj, msgspec.Struct):
        for f in obj.__struct_fields__:
            v = getattr(obj, f)
            if isinstance(v, (float, msgspec.Struct, tuple, list, dict)):
                _check_finite(v, tag, where, f"{path}.{f}")
