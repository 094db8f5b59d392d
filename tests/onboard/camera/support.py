"""Shared pieces of the camera tests (a module, not the conftest: tests import it by name)."""

from __future__ import annotations

from pathlib import Path

#: a live 30 fps 320x240 test pattern
TEST_PIPELINE = "videotestsrc is-live=true pattern=ball ! video/x-raw,width=320,height=240,framerate=30/1"


def write_calibration(path: Path, width_px: int = 320, height_px: int = 240, *, distortion: bool = True) -> Path:
    dist = "distortion_model = \"plumb_bob\"\ndistortion = [-0.1, 0.01, 0.0, 0.0, 0.0]\n" if distortion else ""
    path.write_text(f"[camera]\nwidth_px = {width_px}\nheight_px = {height_px}\nfx_px = 300.0\nfy_px = 300.0\n"
                    f"cx_px = {width_px / 2 - 0.5}\ncy_px = {height_px / 2 - 0.5}\n{dist}"
                    "\n[calibration]\nboard = \"charuco\"\n")
    return path
