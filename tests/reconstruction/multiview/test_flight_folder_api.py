"""The flight reader through ``FlightFolder`` (natural drone order, whole flight or one sortie, the recordings it
used) and the library API (``reconstruction.api.reconstruct_flight``, ``multiview.run.run`` with progress)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from reconstruction.synth import procedural_walker
from skycap.frames import R_world_body_from_euler, T_world_cam_from_pose, intrinsics_matrix, project_points

pytest.importorskip("mcap")

K = intrinsics_matrix(1200.0, 1200.0, 640.0, 360.0)


def _record(folder, drone_id: str, ang: float, J: np.ndarray, t_ns: np.ndarray, frames: slice = slice(None)) -> np.ndarray:
    """One sortie of a hovering drone at angle ``ang`` around the walker (``Recorder.new_sortie``): camera_info,
    state at 50 Hz over the frames' span, sim/keypoints2d of ``frames``. Returns its true T_world_cam."""
    from flightdata.recorder import Recorder
    from shared_msgs.messages import CameraInfo, Header, Keypoints2D, PersonKeypoints, VehicleState

    centre = J[:, 11:13].mean((0, 1))
    pos = centre + np.array([7 * np.cos(ang), 7 * np.sin(ang), 0.0])
    pos[2] = -6.0
    d = centre - pos
    yaw = np.arctan2(d[1], d[0])
    pitch = -np.arctan2(-d[2], np.hypot(d[0], d[1]))
    Tc = T_world_cam_from_pose(pos, R_world_body_from_euler(0, 0, yaw), pitch, 0.0)
    idx = np.arange(len(t_ns))[frames]
    hdr = lambda t: Header(schema_version=1, sender_id=drone_id, t_measurement_ns=int(t), t_sent_ns=int(t))  # noqa: E731
    with Recorder.new_sortie(folder, drone_id) as rec:
        rec.record_message("camera_info", CameraInfo(header=hdr(t_ns[idx[0]]), camera_id="cam0", width_px=1280, height_px=720,
                           fx_px=1200.0, fy_px=1200.0, cx_px=640.0, cy_px=360.0, gimbal_pitch_rad=float(pitch)))  # fmt: skip
        for t in np.arange(t_ns[idx[0]], t_ns[idx[-1]] + 1, 20_000_000):
            rec.record_message("state", VehicleState(header=hdr(t), position_ned_m=tuple(map(float, pos)), velocity_ned_m_s=(0.0, 0.0, 0.0),
                               q_world_body=(float(np.cos(yaw / 2)), 0.0, 0.0, float(np.sin(yaw / 2))), position_cov_m2=(0.01, 0.01, 0.01)))  # fmt: skip
        for k, f in enumerate(idx):  # frame indices restart with each sortie, as an agent restart does
            uv, _ = project_points(K, Tc, J[f])
            pk = PersonKeypoints(keypoints_px=tuple(map(float, uv.reshape(-1))), confidence=tuple([0.9] * 17))
            rec.record_message("sim/keypoints2d", Keypoints2D(header=hdr(t_ns[f]), camera_id="cam0", frame_index=int(k), detector="sim",
                               simulated=True, persons=[pk]))  # fmt: skip
    return Tc


@pytest.fixture(scope="module")
def walker():
    J, t_ns, *_ = procedural_walker(24)
    return J, t_ns


def test_drones_are_read_in_natural_order(tmp_path, walker):
    from reconstruction.api import choose_method
    from reconstruction.multiview.flight import read_flight

    J, t_ns = walker
    T10 = _record(tmp_path, "drone_10", 0.0, J, t_ns)  # recorded first, sorts first lexicographically
    T2 = _record(tmp_path, "drone_2", 2.0, J, t_ns)
    cap = read_flight(tmp_path)
    assert [c.name for c in cap.cameras] == ["drone_2", "drone_10"]
    np.testing.assert_allclose(cap.cameras[0].T_world_cam[0], T2, atol=1e-9)
    np.testing.assert_allclose(cap.cameras[1].T_world_cam[0], T10, atol=1e-9)
    assert list(cap.meta["recordings"]) == ["drone_2", "drone_10"]
    assert choose_method(tmp_path) == "multiview"


@pytest.fixture(scope="module")
def two_sortie_flight(tmp_path_factory, walker):
    """drone_1 flew twice (frames 0-11, then 12-23: sorties 1 and 2); drone_2 once over all frames (sortie 1)."""
    J, t_ns = walker
    folder = tmp_path_factory.mktemp("sorties")
    _record(folder, "drone_1", 0.0, J, t_ns, slice(0, 12))
    _record(folder, "drone_1", 0.0, J, t_ns, slice(12, None))
    _record(folder, "drone_2", 2.1, J, t_ns)
    return folder


def test_a_drone_with_two_sorties_is_read_whole_or_by_sortie(two_sortie_flight, walker):
    from reconstruction.capture import CaptureError
    from reconstruction.flight import read_capture
    from reconstruction.multiview.flight import read_flight

    J, t_ns = walker
    folder = two_sortie_flight
    whole = read_flight(folder)  # default: the whole flight, sorties chained in order
    assert [c.name for c in whole.cameras] == ["drone_1", "drone_2"]
    np.testing.assert_array_equal(whole.cameras[0].t_frame_ns, t_ns)
    uv, _ = project_points(K, whole.cameras[0].T_world_cam[0], J[15])
    np.testing.assert_allclose(whole.cameras[0].keypoints_px[15, 0], uv, atol=1e-6)  # a frame of sortie 2
    assert whole.meta["sortie"] is None
    assert whole.meta["recordings"] == {"drone_1": ["drone_1.s001.mcap", "drone_1.s002.mcap"], "drone_2": ["drone_2.s001.mcap"]}

    first = read_flight(folder, sortie=1)
    np.testing.assert_array_equal(first.cameras[0].t_frame_ns, t_ns[:12])
    np.testing.assert_array_equal(first.cameras[1].t_frame_ns, t_ns)
    assert first.meta["recordings"] == {"drone_1": ["drone_1.s001.mcap"], "drone_2": ["drone_2.s001.mcap"]}

    second = read_capture(folder, sortie=2)  # only drone_1 flew sortie 2
    assert [c.name for c in second.cameras] == ["drone_1"]
    np.testing.assert_array_equal(second.cameras[0].t_frame_ns, t_ns[12:])
    assert second.meta["sortie"] == 2 and second.meta["recordings"] == {"drone_1": ["drone_1.s002.mcap"]}
    with pytest.raises(CaptureError, match="at least 2"):
        read_flight(folder, sortie=2)  # the multiview method needs two drones


def test_unknown_sortie_names_the_sorties(two_sortie_flight):
    from flightdata.folder import FlightFolderError
    from reconstruction.api import reconstruct_flight

    with pytest.raises(FlightFolderError, match="no recording of sortie 3.*drone_1.*\\[1, 2\\]"):
        reconstruct_flight(two_sortie_flight, "multiview", sortie=3)


def test_reconstruct_cli_sortie_writes_the_recordings_into_the_summary(two_sortie_flight, tmp_path, capsys):
    from apps.cli import main

    out = tmp_path / "rec"
    assert main(["reconstruct", str(two_sortie_flight), "--method", "multiview", "--sortie", "1", "--mv-out", str(out)]) == 0
    printed = json.loads(capsys.readouterr().out)
    s = json.loads((out / "summary.json").read_text())
    assert s == printed
    assert s["sortie"] == 1
    assert s["recordings"] == {"drone_1": ["drone_1.s001.mcap"], "drone_2": ["drone_2.s001.mcap"]}
    assert s["cameras"] == 2 and s["frames"] > 0
    for k in ("frames", "cameras", "fit_seconds", "outputs"):  # the summary's fields before sorties, unchanged
        assert k in s
    assert (out / "config.toml").is_file() and (out / "capture.npz").is_file()
    # the motion files and the processed flight as a Foxglove MCAP (export.extra = ["foxglove"] by default)
    assert set(s["outputs"]) == {"bvh", "trc", "npz", "csv", "rrd", "foxglove"}
    assert all(Path(p).is_file() for p in s["outputs"].values()), s["outputs"]


def test_run_directly_reports_progress(two_sortie_flight, tmp_path):
    from reconstruction.api import reconstruct_flight
    from reconstruction.multiview.fit import FitConfig
    from reconstruction.multiview.flight import read_flight
    from reconstruction.multiview.run import MultiviewConfig, MultiviewResult, run

    cfg = MultiviewConfig(fit=FitConfig(iters=20), rrd=False)
    calls = []
    cap = read_flight(two_sortie_flight)
    res = run(cap, cfg, progress=lambda stage, done, total: calls.append((stage, done, total)))
    assert isinstance(res, MultiviewResult) and res.out_dir is None and res.outputs == {}
    assert res.joints_ned.shape == (len(res.t_ns), 17, 3) and np.all(np.isfinite(res.joints_ned))
    fit = [c for c in calls if c[0] == "fit"]
    assert fit[0] == ("fit", 0, 20) and fit[-1] == ("fit", 20, 20)
    assert [c[1] for c in fit] == sorted(c[1] for c in fit)
    assert res.summary["recordings"] == {"drone_1": ["drone_1.s001.mcap", "drone_1.s002.mcap"], "drone_2": ["drone_2.s001.mcap"]}

    calls.clear()
    res = reconstruct_flight(two_sortie_flight, "multiview", cfg, out_dir=tmp_path / "o",
                             progress=lambda stage, done, total: calls.append((stage, done, total)))
    stages = [c[0] for c in calls]
    assert calls[:2] == [("read", 1, 2), ("read", 2, 2)]
    assert "fit" in stages and calls[-1] == ("export", 1, 1)
    assert set(res.outputs) == {"bvh", "trc", "npz", "csv"} and all(p.is_file() for p in res.outputs.values())
    assert json.loads((tmp_path / "o" / "summary.json").read_text()) == res.summary


def test_library_errors_name_the_fix(two_sortie_flight):
    from reconstruction.api import ReconstructionError, reconstruct_flight
    from reconstruction.monocular.reconstruct import MonocularRunConfig
    from reconstruction.multiview.fit import FitConfig
    from reconstruction.multiview.run import MultiviewConfig

    with pytest.raises(ReconstructionError, match="MultiviewConfig"):
        reconstruct_flight(two_sortie_flight, "multiview", MonocularRunConfig())
    with pytest.raises(ReconstructionError, match="unknown reconstruction method"):
        reconstruct_flight(two_sortie_flight, "stereo")
    with pytest.raises(ReconstructionError, match="product, paper"):
        MultiviewConfig(fit=FitConfig(method="magic"))
    with pytest.raises(ReconstructionError, match="variant"):
        MonocularRunConfig(variant="fisheye")
