"""The contract between skycap's drones, ground station and tools: typed, versioned messages
(:mod:`shared_msgs.messages`), their codec (:mod:`shared_msgs.codec`) and the Zenoh key expressions
(:mod:`shared_msgs.keys`)."""

from shared_msgs.codec import MessageError, decode, encode, stamp_sent, validate
from shared_msgs.messages import *  # noqa: F401,F403
from shared_msgs.messages import __all__ as _msg_all

__all__ = ["MessageError", "decode", "encode", "stamp_sent", "validate", *_msg_all]
