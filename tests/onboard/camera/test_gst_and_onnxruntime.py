"""GStreamer and onnxruntime in one process (the agent captures its camera and runs the detector): an exception
inside onnxruntime after a camera was opened must stay an exception. libgstreamer brings libunwind into the
global symbol scope; without ``onboard.camera.gst._keep_gcc_unwinder`` this aborted the process (run in a child
process so that a regression fails this test instead of killing the test session)."""

from __future__ import annotations

import subprocess
import sys

import pytest

from tests.helpers.paths import REPO

SCRIPT = r"""
import sys
from onboard.camera.errors import CameraSourceError
from onboard.camera.sources import GStreamerSource
src = GStreamerSource("videotestsrc is-live=true num-buffers=5 ! video/x-raw,width=64,height=48")
src.open()
assert src.read(5.0) is not None
src.close()
import onnxruntime as ort
path = sys.argv[1]
open(path, "wb").write(b"not an onnx model" * 10)
try:
    ort.InferenceSession(path, providers=["CPUExecutionProvider"])
except Exception as e:
    print("raised", type(e).__name__)
"""


def test_an_onnxruntime_exception_after_opening_a_camera_is_an_exception(gst, tmp_path):
    r = subprocess.run([sys.executable, "-c", SCRIPT, str(tmp_path / "bad.onnx")], cwd=REPO, capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 0 and "raised" in r.stdout, (r.returncode, r.stdout, r.stderr[-2000:])
