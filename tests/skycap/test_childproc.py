"""A launcher's children die with it: SIGKILL the launcher, its child (in its own session) gets SIGTERM."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

LAUNCHER = r"""
import subprocess, sys, time
from skycap.childproc import die_with_parent
p = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"], start_new_session=True,
                     preexec_fn=die_with_parent)
print(p.pid, flush=True)
time.sleep(60)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_a_child_gets_sigterm_when_its_launcher_is_killed():
    launcher = subprocess.Popen([sys.executable, "-c", LAUNCHER], stdout=subprocess.PIPE, text=True)
    child = int(launcher.stdout.readline())
    os.kill(child, 0)  # alive
    launcher.send_signal(signal.SIGKILL)
    launcher.wait()
    t_end = time.monotonic() + 10
    while time.monotonic() < t_end:
        try:
            os.kill(child, 0)
        except ProcessLookupError:
            return  # gone (reaped by init)
        # a zombie until init reaps it: check its state
        try:
            with open(f"/proc/{child}/stat") as f:
                if f.read().split(")")[1].split()[0] == "Z":
                    return
        except FileNotFoundError:
            return
        time.sleep(0.05)
    os.kill(child, signal.SIGKILL)
    pytest.fail("the child outlived its killed launcher")
