"""``skycap log ...``: inspect and recover flight recorder files (:mod:`flightdata.flightlog`) and write a flight as a
Foxglove MCAP (``skycap log foxglove FLIGHT_DIR``, :mod:`flightdata.foxglove`)."""

from __future__ import annotations

from typing import Any

from flightdata import flightlog, foxglove


def register(sub: Any) -> None:
    """Add ``skycap log info|recover|foxglove`` to the skycap CLI."""
    foxglove.register(flightlog.register(sub))
