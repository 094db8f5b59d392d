"""``skycap refine`` on a flight folder recorded with the real flight recorder (MCAP): the reader, the
outputs, the evaluation against truth.mcap and the multiview reader's ``use_refined_poses`` hook."""

from __future__ import annotations

import json

import numpy as np
import pytest

from recon_track_scene import CAM, make_scene
from skycap.frames import project_points


def _q_yaw(T):
    R = T[:3, :3] @ np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])  # optical -> FRD forward axis
    yaw = np.arctan2(R[1, 0], R[0, 0])
    return (float(np.cos(yaw / 2)), 0.0, 0.0, float(np.sin(yaw / 2)))


def _write_flight(folder, scene, split_s: float | None = None, ids: list[str] | None = None):
    """The scene recorded per drone (``Recorder.new_sortie``; drone ``d`` named ``ids[d]``, default ``drone_<d+1>``);
    with ``split_s`` each drone's recording is two sorties (before / from ``split_s``), frame indices restarting in
    the second as after an agent restart."""
    from flightdata.folder import FlightFolder
    from flightdata.recorder import Recorder
    from shared_msgs.messages import (BoundingBox, CameraInfo, Detections, Header, Keypoints2D, PersonKeypoints,
                                      SimTruth, VehicleState, VehicleTruth)

    D = scene.drones.shape[1]
    ids = ids or [f"drone_{d + 1}" for d in range(D)]
    t_ns = (scene.t_s * 1e9).round().astype(np.int64)
    spans = [(-np.inf, np.inf)] if split_s is None else [(-np.inf, split_s * 1e9), (split_s * 1e9, np.inf)]

    def hdr(t, s):
        return Header(schema_version=1, sender_id=s, t_measurement_ns=int(t), t_sent_ns=int(t))

    for d, name in enumerate(ids):
        for lo, hi in spans:
            t_first = int(t_ns[(t_ns >= lo) & (t_ns < hi)][0])
            with Recorder.new_sortie(folder, name) as rec:
                rec.record_message("camera_info", CameraInfo(header=hdr(t_first, name), camera_id="cam0", width_px=CAM.width_px,
                                   height_px=CAM.height_px, fx_px=CAM.fx_px, fy_px=CAM.fy_px, cx_px=CAM.cx_px, cy_px=CAM.cy_px), t_first)  # fmt: skip
                for k in range(0, len(t_ns), 2):  # state at 50 Hz: reported = true + offset
                    if not lo <= t_ns[k] < hi:
                        continue
                    p = scene.drones[k, d] + scene.bias[k, d]
                    rec.record_message("state", VehicleState(header=hdr(t_ns[k], name), position_ned_m=tuple(map(float, p)),
                                       velocity_ned_m_s=(0.0, 0.0, 0.0), q_world_body=(1.0, 0.0, 0.0, 0.0)), int(t_ns[k]))  # fmt: skip
                frames = [f for f in scene.frames if f["drone"] == d and lo <= f["t_ns"] < hi]
                for i, f in enumerate(frames):
                    b = f["box"]
                    box = BoundingBox(x_min_px=float(b[0]), y_min_px=float(b[1]), x_max_px=float(b[2]), y_max_px=float(b[3]),
                                      score=0.9, var_x_min_px2=4.0, var_y_min_px2=4.0, var_x_max_px2=4.0, var_y_max_px2=4.0)
                    rec.record_message("detections", Detections(
                        header=hdr(f["t_ns"], name), camera_id="cam0", frame_index=i, detector="simulated", mode="simulated",
                        boxes=[box], width_px=CAM.width_px, height_px=CAM.height_px,
                        T_world_cam=tuple(map(float, f["T_reported"].reshape(-1))), T_world_cam_cov=tuple(map(float, f["cov"].reshape(-1)))),
                        f["t_ns"])  # fmt: skip
                    bt = f["box_true"]
                    gt = PersonKeypoints(keypoints_px=(0.0,) * 34, confidence=(1.0,) * 17,
                                         box=BoundingBox(x_min_px=float(bt[0]), y_min_px=float(bt[1]), x_max_px=float(bt[2]), y_max_px=float(bt[3]), score=1.0))  # fmt: skip
                    rec.record_message("sim/keypoints2d_gt", Keypoints2D(header=hdr(f["t_ns"], name), camera_id="cam0", frame_index=i,
                                       detector="truth", simulated=True, persons=[gt]), f["t_ns"])  # fmt: skip
                    # keypoints for the multiview reader: a vertical line of 17 points through the person
                    k = int(round(f["t_ns"] * 1e-7))
                    pts = scene.person[k] + np.c_[np.zeros((17, 2)), np.linspace(-0.8, 0.8, 17)]
                    uv, _ = project_points(CAM.K, f["T_reported"], pts)
                    rec.record_message("sim/keypoints2d", Keypoints2D(header=hdr(f["t_ns"], name), camera_id="cam0", frame_index=i,
                                       detector="sim", simulated=True, persons=[PersonKeypoints(keypoints_px=tuple(map(float, uv.reshape(-1))),
                                       confidence=(0.9,) * 17)]), f["t_ns"])  # fmt: skip
    with Recorder(FlightFolder(folder).truth_path, node_id="sim") as rec:
        for k in range(0, len(t_ns), 2):
            veh = [VehicleTruth(drone_id=n, position_ned_m=tuple(map(float, scene.drones[k, d])), velocity_ned_m_s=(0.0, 0.0, 0.0),
                                q_world_body=(1.0, 0.0, 0.0, 0.0)) for d, n in enumerate(ids)]  # fmt: skip
            rec.record_message("truth", SimTruth(header=hdr(t_ns[k], "sim"), vehicles=veh,
                               person_joints_ned_m=tuple(map(float, np.tile(scene.person[k], 17))),
                               person_root_ned_m=tuple(map(float, scene.person[k]))), int(t_ns[k]))  # fmt: skip
    return ids


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    pytest.importorskip("mcap")
    folder = tmp_path_factory.mktemp("flight")
    scene = make_scene(seed=11, duration_s=25.0)
    ids = _write_flight(folder, scene)
    return folder, scene, ids


def test_refine_cli_writes_refined_track_and_evaluates(flight, capsys):
    from apps.cli import main

    folder, scene, ids = flight
    assert main(["refine", str(folder), "--person-height-m", "1.69"]) == 0
    out = capsys.readouterr().out
    assert "offline smoother" in out and "pos_err_rep" in out
    z = np.load(folder / "refined_track.npz")
    assert [str(s) for s in z["drone_ids"]] == ids
    N = len(z["t_ns"])
    assert z["position_ned_m"].shape == (N, 3) and z["covariance"].shape == (N, 6, 6)
    assert z["offset_ned_m"].shape == (N, 3, 3)
    for d in ids:
        S = len(z[f"{d}.state_t_ns"])
        assert z[f"{d}.position_refined_ned_m"].shape == (S, 3)
        assert z[f"{d}.roi_px"].shape == (len(z[f"{d}.frame_index"]), 4)
    s = json.loads((folder / "refined_track.json").read_text())
    ev = s["evaluation"]
    f = ev["fleet"]
    # the evaluation removes the fleet-common offset's window mean (the flight summary's definition); it drifts
    # (60 s Gauss-Markov) by ~0.3 m over this flight, hence the loose bound (test_smoother checks 0.15 m with
    # the drifting common offset removed)
    assert f["person_rmse_fleet_frame_m_smoothed"] < 0.4, f
    assert f["person_rmse_fleet_frame_m_smoothed"] <= f["person_rmse_fleet_frame_m_forward"] + 1e-6, f
    for d, row in ev["drones"].items():
        assert row["position_err_fleet_frame_m_refined"] < row["position_err_fleet_frame_m_reported"], (d, row)
        assert row["roi_frames"] > 150 and row["person_in_roi_rate_smoothed"] > 0.97, (d, row)
        assert row["box_iou_smoothed_median"] > 0.6, (d, row)


def test_multiview_reader_uses_the_refined_positions(flight):
    from reconstruction.multiview.flight import read_flight
    from reconstruction.track.flight import load_refined_offsets

    folder, scene, ids = flight
    if not (folder / "refined_track.npz").is_file():
        from reconstruction.track.flight import RefineConfig, refine_flight

        refine_flight(folder, RefineConfig(person_height_m=1.69))
    plain = read_flight(folder)
    refined = read_flight(folder, use_refined_poses=True)
    offsets = load_refined_offsets(folder)
    for cp, cr in zip(plain.cameras, refined.cameras):
        t, off = offsets[cp.name]
        expect = np.stack([np.interp(cp.t_pose_ns, t, off[:, k]) for k in range(3)], -1)
        np.testing.assert_allclose(cp.T_world_cam[:, :3, 3] - cr.T_world_cam[:, :3, 3], expect, atol=1e-9)
        np.testing.assert_allclose(cp.T_world_cam[:, :3, :3], cr.T_world_cam[:, :3, :3])
        # and they are nearer the truth (relative to the fleet's common offset)
        d = int(cp.name.split("_")[1]) - 1
        tt = cp.t_pose_ns * 1e-9
        true = np.stack([np.interp(tt, scene.t_s, scene.drones[:, d, k]) for k in range(3)], -1)
        common = np.mean([np.stack([np.interp(tt, scene.t_s, scene.bias[:, j, k]) for k in range(3)], -1) for j in range(3)], axis=0)
        e_plain = np.sqrt(np.mean(np.sum((cp.T_world_cam[:, :3, 3] - true - common) ** 2, -1)))
        e_ref = np.sqrt(np.mean(np.sum((cr.T_world_cam[:, :3, 3] - true - common) ** 2, -1)))
        assert e_ref < 0.5 * e_plain, (cp.name, e_plain, e_ref)


def test_refine_errors_are_clear(tmp_path, flight):
    import shutil

    from flightdata.folder import FlightFolderError
    from reconstruction.multiview.flight import read_flight
    from reconstruction.track.flight import refine_flight
    from reconstruction.track.smoother import SmootherError

    with pytest.raises(FlightFolderError, match="no drone recordings"):
        refine_flight(tmp_path)
    for f in flight[0].glob("drone_*.mcap"):
        shutil.copy(f, tmp_path / f.name)
    with pytest.raises(SmootherError, match="run `skycap refine"):
        read_flight(tmp_path, use_refined_poses=True)


def test_refine_names_its_recordings_and_reports_progress(flight):
    from reconstruction.track.flight import RefineConfig, RefineResult, refine_flight

    folder, scene, ids = flight
    calls = []
    res = refine_flight(folder, RefineConfig(person_height_m=1.69), write=False,
                        progress=lambda stage, done, total: calls.append((stage, done, total)))
    assert isinstance(res, RefineResult) and res.paths == {}
    s = res.summary
    assert s["sortie"] is None
    assert s["recordings"] == {d: [f"{d}.s001.mcap"] for d in ids}
    assert calls[:3] == [("read", 1, 3), ("read", 2, 3), ("read", 3, 3)]
    for step in [("measurements", 3, 3), ("smooth", 1, 1), ("boxes", 3, 3), ("evaluate", 1, 1)]:
        assert step in calls, (step, calls)
    assert calls[-1] == ("evaluate", 1, 1)
    assert s["drones"] == ids and [str(d) for d in res.arrays["drone_ids"]] == ids


@pytest.fixture(scope="module")
def split_flight(tmp_path_factory):
    """The scene of :func:`flight`, each drone recorded as two sorties (split at 12 s)."""
    pytest.importorskip("mcap")
    folder = tmp_path_factory.mktemp("split_flight")
    scene = make_scene(seed=11, duration_s=25.0)
    ids = _write_flight(folder, scene, split_s=12.0)
    return folder, scene, ids


def test_refine_a_flight_of_two_sorties_whole_and_by_sortie(flight, split_flight, capsys):
    from apps.cli import main
    from reconstruction.track.flight import RefineConfig, refine_flight

    folder, scene, ids = split_flight
    cfg = RefineConfig(person_height_m=1.69)
    one = refine_flight(flight[0], cfg, write=False)
    whole = refine_flight(folder, cfg, write=False)
    assert whole.summary["recordings"] == {d: [f"{d}.s001.mcap", f"{d}.s002.mcap"] for d in ids}
    # the whole flight read from two sorties is the flight read from one: the same track and the same evaluation
    # (frame indices restart in sortie 2; the true boxes are matched per sortie)
    np.testing.assert_array_equal(whole.arrays["t_ns"], one.arrays["t_ns"])
    np.testing.assert_allclose(whole.arrays["position_ned_m"], one.arrays["position_ned_m"], rtol=0, atol=1e-9)
    same = lambda a, b: json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)  # noqa: E731  (NaN == NaN)
    assert same(whole.summary["evaluation"], one.summary["evaluation"]), (whole.summary["evaluation"], one.summary["evaluation"])
    for k in ("frames", "frames_used", "frames_rejected", "measurements", "span_s"):
        assert whole.summary[k] == one.summary[k], k

    assert main(["refine", str(folder), "--person-height-m", "1.69", "--sortie", "2"]) == 0
    assert "offline smoother" in capsys.readouterr().out
    s = json.loads((folder / "refined_track.json").read_text())
    assert s["sortie"] == 2 and s["recordings"] == {d: [f"{d}.s002.mcap"] for d in ids}
    z = np.load(folder / "refined_track.npz")
    assert z["t_ns"][0] >= 12e9 and z["t_ns"][-1] == one.arrays["t_ns"][-1]
    assert s["frames"] < one.summary["frames"]


def test_refine_reads_drones_in_natural_order(tmp_path):
    from reconstruction.track.flight import read_recordings

    scene = make_scene(seed=11, duration_s=6.0)
    _write_flight(tmp_path, scene, ids=["drone_10", "drone_2", "drone_1"])
    recs = read_recordings(tmp_path)
    assert [r.drone_id for r in recs] == ["drone_1", "drone_2", "drone_10"]
    assert recs[2].files == ("drone_10.s001.mcap",)
