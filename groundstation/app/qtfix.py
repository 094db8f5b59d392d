"""A guard against a PySide6 reference-count bug: with PySide6 6.12 on Python 3.11, every call of a Qt method that
returns nothing (``QPainter.drawLine``, ``setPen``, ``fillRect``, ...) drops one reference to ``None`` without
having taken it. Python 3.11's ``None`` is not immortal (3.12's is), so after enough calls its count reaches 0 and
the process aborts with "Fatal Python error: none_dealloc: deallocating None" (the ground-station bench died so
after a minute of the 3D tab, in the fleet table's refresh).

:class:`NoneRefGuard` keeps ``None``'s count from falling below where it was at start: :meth:`NoneRefGuard.check`
(the window calls it on a 1 Hz timer, the 3D views after each paint) adds back one reference for each one lost,
straight to CPython's count (a list of held references would give them up again when freed at exit and abort
there). Over-counting (a real reference dropped) costs nothing: None is never freed; nothing is done on
Python >= 3.12 or outside CPython.
"""

from __future__ import annotations

import ctypes
import logging
import platform
import sys

log = logging.getLogger(__name__)

__all__ = ["NoneRefGuard", "NONE_GUARD"]


class NoneRefGuard:
    def __init__(self):
        self.active = sys.version_info < (3, 12) and platform.python_implementation() == "CPython"
        self.floor = sys.getrefcount(None) if self.active else 0
        self.restored = 0  #: references given back so far
        self._warned = False

    def check(self) -> int:
        """Give ``None`` back the references lost since the last check; returns how many."""
        if not self.active:
            return 0
        lost = self.floor - sys.getrefcount(None)
        if lost <= 0:
            return 0
        ctypes.c_ssize_t.from_address(id(None)).value += lost  # ob_refcnt, the object's first field
        self.restored += lost
        if not self._warned:
            self._warned = True
            log.warning("PySide6 reference-count bug: %d references to None lost by Qt calls; compensating "
                        "(see groundstation/app/qtfix.py; gone with Python >= 3.12)", lost)
        return lost


NONE_GUARD = NoneRefGuard()
