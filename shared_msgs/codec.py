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

__all__ = ["MessageError", "encode", "decode", "validate", "stamp_sent", "TYPE_BY_TAG"]

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
    upgrade = probe.header.schema_version in cls.READABLE_VERSIONS
    if probe.header.schema_version != cls.SCHEMA_VERSION and not upgrade:
        older = probe.header.schema_version < cls.SCHEMA_VERSION
        raise MessageError(
            f"{probe.type} schema version {probe.header.schema_version} sent by {probe.header.sender_id!r}{where}, "
            f"this build speaks version {cls.SCHEMA_VERSION}; update skycap on "
            f"{'the sender (older side)' if older else 'this receiving side (older side)'}"
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
    _check_shapes(msg, probe.type, where, probe.header.sender_id)
    if upgrade:  # an older version whose fields are a subset of today's: it is now a current message
        msg.header.schema_version = cls.SCHEMA_VERSION
    return msg  # type: ignore[return-value]


def validate(msg: Message) -> Message:
    """Raise :class:`MessageError` if ``msg`` could not be decoded by a receiver (NaN/inf, wrong lengths,
    header version not the type's); returns ``msg``. The transport calls it before publishing."""
    tag = type(msg).__struct_config__.tag
    if msg.header.schema_version != type(msg).SCHEMA_VERSION:
        raise MessageError(
            f"{tag} message has header.schema_version {msg.header.schema_version}, this build speaks "
            f"{type(msg).SCHEMA_VERSION}; build headers with {type(msg).__name__}.make_header()"
        )
    _check_finite(msg, tag, "")
    _check_shapes(msg, tag, "", msg.header.sender_id)
    return msg


# Fixed lengths of flattened arrays: (message type, field) -> allowed lengths, what they hold.
_LENGTHS: dict[tuple[str, str], tuple[tuple[int, ...], str]] = {
    ("camera_info", "T_body_cam"): ((0, 16), "a row-major 4x4 transform (or empty)"),
    ("camera_frame", "T_world_cam"): ((0, 16), "a row-major 4x4 transform (or empty)"),
    ("detections", "T_world_cam"): ((16,), "a row-major 4x4 transform"),
    ("detections", "T_world_cam_cov"): ((0, 36), "a row-major 6x6 covariance (or empty)"),
    ("target_estimate", "covariance"): ((36,), "a row-major 6x6 covariance"),
    ("sim_truth", "person_joints_ned_m"): ((51,), "COCO-17 joints, (x, y, z) each"),
}
_DISTORTION_LENGTHS = {"none": (0,), "plumb_bob": (5,)}


def _check_len(values, allowed: tuple[int, ...], what: str, tag: str, where: str, sender: str, path: str) -> None:
    if len(values) not in allowed:
        raise MessageError(
            f"invalid {tag} message{where} from {sender!r}: `{path}` has {len(values)} values, expected "
            f"{' or '.join(map(str, allowed))} ({what})"
        )


def _check_shapes(msg: Message, tag: str, where: str, sender: str) -> None:
    """Refuse flattened arrays of the wrong length (they would be reshaped wrongly downstream)."""
    for (t, field), (allowed, what) in _LENGTHS.items():
        if t == tag:
            _check_len(getattr(msg, field), allowed, what, tag, where, sender, f"$.{field}")
    if tag == "camera_info":
        allowed = _DISTORTION_LENGTHS[msg.distortion_model]
        _check_len(msg.distortion, allowed, f"{msg.distortion_model} coefficients", tag, where, sender, "$.distortion")
    elif tag == "keypoints2d":
        for i, p in enumerate(msg.persons):
            _check_len(p.keypoints_px, (34,), "17 (u, v) pairs", tag, where, sender, f"$.persons[{i}].keypoints_px")
            _check_len(p.confidence, (17,), "17 confidences", tag, where, sender, f"$.persons[{i}].confidence")


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
