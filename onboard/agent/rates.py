"""Event rates for the agent's health report."""

from __future__ import annotations

import time
from collections import deque

__all__ = ["RateMeter"]


class RateMeter:
    """Events per second over a sliding window (for the health report)."""

    def __init__(self, window_s: float = 2.0):
        self.window_s = window_s
        self._t: deque[float] = deque()

    def tick(self, t_s: float | None = None) -> None:
        self._t.append(time.monotonic() if t_s is None else t_s)

    def rate_hz(self, t_s: float | None = None) -> float:
        now = time.monotonic() if t_s is None else t_s
        while self._t and self._t[0] < now - self.window_s:
            self._t.popleft()
        return len(self._t) / self.window_s
