"""Child processes that cannot outlive their launcher.

A launcher (the demo, ``skycap gs --sim``) starts simulators, cameras and agents in their own sessions (so that
it can signal each group). If the launcher itself dies (a crash, SIGKILL), those children would keep running,
flying and holding ports: :func:`die_with_parent` (a ``preexec_fn``) asks the Linux kernel to send the child
SIGTERM when its parent exits (``prctl(PR_SET_PDEATHSIG)``); an agent then lands and closes its recording as on
any SIGTERM. Elsewhere it does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import signal
import sys

_PR_SET_PDEATHSIG = 1


def die_with_parent() -> None:
    """``preexec_fn`` of :class:`subprocess.Popen`: SIGTERM to this child when the launcher exits (Linux)."""
    if not sys.platform.startswith("linux"):
        return
    libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
    if libc.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0) != 0:
        return  # best effort: the launcher still stops its children on a clean exit
    if os.getppid() == 1:  # the launcher died before prctl took effect
        os.kill(os.getpid(), signal.SIGTERM)
