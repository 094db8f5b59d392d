"""systemd's notify protocol (``sd_notify(3)``) for the onboard services: a thin adapter over ``cysystemd``.

A service started by systemd with ``Type=notify`` finds ``NOTIFY_SOCKET`` in its environment and tells systemd

* ``READY=1``: it is up (the agent: the autopilot link and the recorder are; deploy/INSTALL.md);
* ``STATUS=...``: one line of what it is doing or waiting for (``systemctl status`` shows it);
* ``WATCHDOG=1``: it is alive; with ``WatchdogSec=`` systemd sets ``WATCHDOG_USEC`` (and ``WATCHDOG_PID``) and
  kills and restarts a service that does not ping within that time. Pings are sent every quarter of it (systemd
  asks for at least every half), from the loop whose liveness they vouch for: a stuck loop stops them;
* ``STOPPING=1``: it is shutting down.

The datagrams go out through libsystemd's own ``sd_notify`` (the ``cysystemd`` wheels bundle it). Without
``NOTIFY_SOCKET`` (tests, the demo, a shell) every call is a no-op, so the services call it unconditionally.

    notifier = Notifier.from_env()
    notifier.status("connecting to the autopilot")
    notifier.ready("flying")
    while running:
        notifier.watchdog()   # each loop iteration: sends WATCHDOG=1 only when due
    notifier.stopping()
"""

from __future__ import annotations

import logging
import math
import os
import time
from typing import Callable, Mapping

log = logging.getLogger(__name__)

__all__ = ["Notifier", "watchdog_timeout_s", "NotifyError"]

#: a ping every this fraction of WATCHDOG_USEC (sd_watchdog_enabled(3): "at least every half")
PING_FRACTION = 0.25


class NotifyError(RuntimeError):
    """The service runs under systemd's notify protocol but cannot speak it."""


def watchdog_timeout_s(env: Mapping[str, str] | None = None, pid: int | None = None) -> float | None:
    """systemd's watchdog timeout for this process (s), or None when its watchdog is off: ``WATCHDOG_USEC`` unset
    or not a positive integer, or ``WATCHDOG_PID`` naming another process (the rules of ``sd_watchdog_enabled``)."""
    env = os.environ if env is None else env
    usec = env.get("WATCHDOG_USEC", "")
    if not usec:
        return None
    owner = env.get("WATCHDOG_PID", "")
    if owner and owner != str(os.getpid() if pid is None else pid):
        return None
    try:
        value = int(usec)
    except ValueError:
        log.warning("WATCHDOG_USEC=%r is not an integer (microseconds): the systemd watchdog is not pinged", usec)
        return None
    return value * 1e-6 if value > 0 else None


def _libsystemd_send(message: str) -> None:
    from cysystemd._daemon import sd_notify  # libsystemd's sd_notify (the cysystemd wheel bundles libsystemd)

    sd_notify(message, False)


class Notifier:
    """``sd_notify`` messages to systemd (see the module doc); every method is a no-op without ``NOTIFY_SOCKET``.

    ``send`` (one message, ``"KEY=value\\n..."``) and ``clock`` (monotonic s) are for tests; by default the message
    goes through libsystemd. A failed send is logged (once per kind of message) and never raised: the service
    keeps running, and systemd's own timeouts report a service that stays silent.
    """

    def __init__(self, env: Mapping[str, str] | None = None, *, send: Callable[[str], None] | None = None,
                 clock: Callable[[], float] = time.monotonic, pid: int | None = None):
        env = os.environ if env is None else env
        self.enabled = bool(env.get("NOTIFY_SOCKET"))
        #: systemd's watchdog timeout (s), None when off (or without NOTIFY_SOCKET)
        self.watchdog_timeout_s = watchdog_timeout_s(env, pid) if self.enabled else None
        self.ready_sent = False
        self.pings = 0
        self._send = send
        self._clock = clock
        self._t_last_ping_s = -math.inf
        self._status = ""
        self._failed: set[str] = set()
        if self.enabled and send is None:
            try:
                import cysystemd._daemon  # noqa: F401
            except ImportError as e:
                raise NotifyError(
                    f"NOTIFY_SOCKET is set (a systemd Type=notify service) but the sd_notify library is missing "
                    f"({e}); install it in this environment: pip install 'cysystemd>=1.5.4' (a base dependency of "
                    "skycap on Linux), or run the unit with Type=simple") from e
            self._send = _libsystemd_send

    @classmethod
    def disabled(cls) -> "Notifier":
        """A notifier that never sends (an agent run inside tests or the demo)."""
        return cls({})

    @classmethod
    def from_env(cls) -> "Notifier":
        """The process's notifier: enabled when systemd set ``NOTIFY_SOCKET``; says so in the log."""
        n = cls()
        if n.enabled:
            log.info("systemd notify protocol on (%s)", f"watchdog {n.watchdog_timeout_s:.1f} s, pinged every "
                     f"{PING_FRACTION * n.watchdog_timeout_s:.2f} s" if n.watchdog_timeout_s else "watchdog off")
        return n

    @property
    def ping_period_s(self) -> float | None:
        return None if self.watchdog_timeout_s is None else PING_FRACTION * self.watchdog_timeout_s

    def _notify(self, kind: str, message: str) -> bool:
        if not self.enabled or self._send is None:
            return False
        try:
            self._send(message)
        except Exception as e:  # never let the notification take the service down
            if kind not in self._failed:
                self._failed.add(kind)
                log.error("sd_notify %s failed: %s (NOTIFY_SOCKET=%s)", kind, e, os.environ.get("NOTIFY_SOCKET"))
            return False
        return True

    def status(self, text: str) -> None:
        """``STATUS=text`` (one line), sent when it changed."""
        text = " ".join(text.split())
        if text != self._status and self._notify("STATUS", f"STATUS={text}"):
            self._status = text

    def ready(self, status: str = "") -> None:
        """``READY=1`` (once), with a status line."""
        if self.ready_sent:
            self.status(status)
            return
        status = " ".join(status.split())
        if self._notify("READY", "READY=1" + (f"\nSTATUS={status}" if status else "")):
            self.ready_sent = True
            self._status = status or self._status

    def watchdog(self) -> bool:
        """``WATCHDOG=1`` when a quarter of systemd's watchdog timeout has passed since the last ping (call it on
        every iteration of the loop it vouches for); True when it sent one."""
        period = self.ping_period_s
        if period is None:
            return False
        now = self._clock()
        if now - self._t_last_ping_s < period:
            return False
        if not self._notify("WATCHDOG", "WATCHDOG=1"):
            return False
        self._t_last_ping_s = now
        self.pings += 1
        return True

    def stopping(self, status: str = "") -> None:
        """``STOPPING=1``, with a status line."""
        status = " ".join(status.split())
        self._notify("STOPPING", "STOPPING=1" + (f"\nSTATUS={status}" if status else ""))
