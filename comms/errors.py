"""The comms layer's error type."""

from __future__ import annotations

from skycap.errors import SkycapError


class TransportError(SkycapError):
    """The Zenoh session could not be opened or used (bad endpoint, port in use, closed transport)."""
