"""``probe`` on a live test pattern, and the ``skycap camera`` command line."""

from __future__ import annotations

import json
import math
import threading
import time

import cv2
import numpy as np
import pytest

from apps.cli import main as skycap_main
from onboard.camera.config import CameraConfig
from onboard.camera.errors import CameraSourceError
from onboard.camera.probe import format_report, probe
from onboard.camera.sources import GStreamerSource, open_source
from tests.onboard.camera.support import TEST_PIPELINE


def test_probe_figures_on_videotestsrc(gst) -> None:
    r = probe(open_source(CameraConfig(source="gstreamer", uri=TEST_PIPELINE), open_now=False), seconds=1.5)
    assert (r.width_px, r.height_px) == (320, 240) and r.frames >= 35 and r.dropped == 0
    assert r.fps_mean == pytest.approx(30.0, abs=1.0) and r.interval_mean_ms == pytest.approx(33.3, abs=1.0)
    assert r.interval_std_ms < 5.0 and r.non_monotonic == 0
    assert 0 <= r.latency_mean_ms < 20.0 and r.latency_p99_ms < 100.0
    table = format_report(r)
    assert "interval jitter std" in table and "capture->receive p99" in table and "320x240" in table
    d = r.to_dict()
    assert json.loads(json.dumps(d))["frames"] == r.frames


def test_probe_of_a_source_that_gives_nothing(gst) -> None:
    with pytest.raises(CameraSourceError, match="no frame"):
        probe(GStreamerSource("videotestsrc num-buffers=0 ! video/x-raw,width=64,height=48"), seconds=1.0,
              open_timeout_s=2.0)


def test_cli_probe_json_on_an_image_folder(tmp_path, capsys) -> None:
    for i in range(8):
        cv2.imwrite(str(tmp_path / f"im{i}.jpg"), np.full((48, 64, 3), 20 * i, np.uint8))
    rc = skycap_main(["camera", "probe", f"file:{tmp_path}", "--rate", "40", "--seconds", "5", "--json",
                      "--latency-s", "0.03"])
    out = json.loads(capsys.readouterr().out)
    assert rc == 0 and out["frames"] == 8 and (out["width_px"], out["height_px"]) == (64, 48)
    assert out["fps_mean"] == pytest.approx(40.0, rel=0.25) and out["latency_mean_ms"] == pytest.approx(30.0, abs=1)


def test_cli_errors_are_one_line(capsys) -> None:
    assert skycap_main(["camera", "probe", "v4l2:/dev/video98"]) == 2
    err = capsys.readouterr().err
    assert "/dev/video98 not found" in err and "v4l2-ctl --list-devices" in err and "Traceback" not in err
    assert skycap_main(["camera", "probe", "no-such-thing"]) == 2
    assert "not understood" in capsys.readouterr().err


def test_cli_serve_publishes_until_stopped(gst, tmp_path, bus_pair, calibration) -> None:
    """serve() as ``skycap camera serve --config agent.toml`` runs it, stopped as SIGTERM would."""
    from comms.transport import TransportConfig
    from onboard.camera.service import serve
    from onboard.config import AgentConfig
    from shared_msgs import keys
    from shared_msgs.messages import CameraStatus
    from skycap.config import load_config

    a, b = bus_pair
    toml = tmp_path / "agent.toml"
    toml.write_text(f'drone_id = "drone_3"\nfleet = "f9"\n[camera]\nsource = "gstreamer"\nuri = "{TEST_PIPELINE}"\n'
                    f'calibration_file = "{calibration}"\n')
    ep = a.config.listen[0]
    cfg = load_config(AgentConfig, toml, [f'transport.connect=["{ep}"]'])
    got: list = []
    b.subscribe(keys.drone_key("f9", "drone_3", keys.CAMERA_STATUS), got.append, CameraStatus)
    stop = threading.Event()
    rc: list[int] = []
    t = threading.Thread(target=lambda: rc.append(serve(cfg, stop=stop)))
    t.start()
    t0 = time.monotonic()
    while time.monotonic() - t0 < 8 and not any(rx.msg.connected for rx in got):
        time.sleep(0.05)
    stop.set()
    t.join(10)
    t0 = time.monotonic()
    while time.monotonic() - t0 < 3 and got[-1].msg.detail != "stopped":
        time.sleep(0.05)
    assert rc == [0] and any(rx.msg.connected for rx in got) and not math.isnan(got[-1].msg.rate_hz)
    assert got[-1].msg.detail == "stopped"
