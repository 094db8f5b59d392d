"""The Foxglove export of a flight, decoded back with Foxglove's published protobuf schemas
(``foxglove-schemas-protobuf``): every channel, every message.

The flight is written by the real recorder (:class:`flightdata.recorder.Recorder`): two drones orbiting a walking
skeleton (camera frames with real JPEG bytes, camera_info, state, simulated detections and keypoints, onboard target
estimates for one drone) and a third drone whose file is garbage (skipped, not fatal)."""

from __future__ import annotations

import importlib
import math

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

pytest.importorskip("foxglove", reason="foxglove-sdk (recon extra) writes the export")
pytest.importorskip("foxglove_schemas_protobuf", reason="foxglove-schemas-protobuf (test extra) decodes it")

from flightdata.folder import FlightFolder  # noqa: E402
from flightdata.foxglove import R_ENU_NED, FoxgloveExportError, export_foxglove  # noqa: E402
from flightdata.recorder import Recorder  # noqa: E402
from mcap.reader import make_reader  # noqa: E402
from shared_msgs.messages import (  # noqa: E402
    BoundingBox, CameraFrame, CameraInfo, Detections, Keypoints2D, PersonKeypoints, TargetEstimate, VehicleState)
from skycap.frames import T_world_cam_from_pose, intrinsics_matrix, project_points  # noqa: E402
from skycap.skeleton import COCO17_LIMBS  # noqa: E402

T0 = 1_795_000_000_000_000_000
FRAMES, RATE_HZ, W, H = 8, 10.0, 160, 120


class _Motion:
    def __init__(self, t_ns, joints_ned):
        self.t_ns, self.joints_ned = t_ns, joints_ned


#: a standing COCO-17 person (x forward = north, y left = -east, z up = -down), metres
_STAND = np.array([[0.10, 0, 1.60], [0.08, 0.03, 1.63], [0.08, -0.03, 1.63], [0.04, 0.08, 1.60], [0.04, -0.08, 1.60],
                   [0, 0.18, 1.40], [0, -0.18, 1.40], [0, 0.22, 1.12], [0, -0.22, 1.12], [0.05, 0.24, 0.86],
                   [0.05, -0.24, 0.86], [0, 0.10, 0.90], [0, -0.10, 0.90], [0.02, 0.10, 0.48], [0.02, -0.10, 0.48],
                   [0, 0.10, 0.06], [0, -0.10, 0.06]])


def _walker():
    """(joints_ned (FRAMES, 17, 3), t_ns): the person walking north at 1.2 m/s, swinging the wrists."""
    t_s = np.arange(FRAMES) / RATE_HZ
    ned = np.stack([_STAND[:, 0], -_STAND[:, 1], -_STAND[:, 2]], -1)
    J = np.repeat(ned[None], FRAMES, 0)
    J[:, :, 0] += 1.2 * t_s[:, None]
    J[:, 9:11, 0] += 0.1 * np.sin(4 * t_s)[:, None]
    return J, T0 + np.round(t_s * 1e9).astype(np.int64)


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    """(folder, truth): per drone the recorded frames' T_world_cam, JPEG bytes, boxes and keypoints."""
    folder = tmp_path_factory.mktemp("flight")
    J, t_ns = _walker()
    K = intrinsics_matrix(120.0, 120.0, W / 2, H / 2)
    truth = {}
    for di, d in enumerate(("drone_1", "drone_2")):
        rec = Recorder(folder / f"{d}.s001.mcap", node_id=d)
        ang = di * math.pi / 2
        pos = np.array([6 * math.cos(ang), 6 * math.sin(ang), -3.0])
        pos_t = tuple(float(v) for v in pos)
        yaw = ang + math.pi  # looking at the origin
        R_yaw = Rotation.from_euler("z", yaw).as_matrix()
        T = T_world_cam_from_pose(pos, R_yaw, gimbal_pitch_rad=-0.45)
        q = Rotation.from_euler("z", yaw).as_quat()  # x, y, z, w
        for k in range(2 * FRAMES):  # state at 20 Hz
            t = int(T0 + k * 5e7)
            rec.record_message("state", VehicleState(header=VehicleState.make_header(d, t), position_ned_m=pos_t,
                                                     velocity_ned_m_s=(0.0, 0.0, 0.0),
                                                     q_world_body=tuple(float(v) for v in q[[3, 0, 1, 2]])), t)
        info = CameraInfo(header=CameraInfo.make_header(d, T0), camera_id="main", width_px=W, height_px=H, fx_px=120.0,
                          fy_px=120.0, cx_px=W / 2, cy_px=H / 2, distortion_model="plumb_bob",
                          distortion=(0.01, -0.002, 0.0, 0.0, 0.0))
        rec.record_message("camera_info", info, T0)
        frames = []
        for k in range(FRAMES):
            t = int(t_ns[k])
            uv, _ = project_points(K, T, J[k])
            img = np.full((H, W, 3), 40 * di + 5 * k, np.uint8)
            for u, v in uv:
                cv2.circle(img, (int(u), int(v)), 2, (255, 255, 255), -1)
            jpeg = cv2.imencode(".jpg", img)[1].tobytes()
            box = BoundingBox(x_min_px=float(uv[:, 0].min()), y_min_px=float(uv[:, 1].min()),
                              x_max_px=float(uv[:, 0].max()), y_max_px=float(uv[:, 1].max()), score=0.9)
            rec.record_message("camera/image", CameraFrame(header=CameraFrame.make_header(d, t), camera_id="main",
                                                           frame_index=k, encoding="jpeg", width_px=W, height_px=H,
                                                           data=jpeg, T_world_cam=tuple(map(float, T.ravel()))), t + 1000)
            rec.record_message("sim/detections", Detections(header=Detections.make_header(d, t), camera_id="main",
                                                            frame_index=k, detector="simulated", mode="simulated",
                                                            boxes=[box], width_px=W, height_px=H,
                                                            T_world_cam=tuple(map(float, T.ravel()))), t + 2000)
            conf = np.full(17, 0.8)
            conf[3] = 0.0  # left ear unseen: not drawn
            rec.record_message("sim/keypoints2d", Keypoints2D(
                header=Keypoints2D.make_header(d, t), camera_id="main", frame_index=k, detector="sim_noisy_gt",
                simulated=True, persons=[PersonKeypoints(keypoints_px=tuple(map(float, uv.ravel())), confidence=tuple(map(float, conf)))]), t + 3000)
            if di == 0:
                rec.record_message("target", TargetEstimate(
                    header=TargetEstimate.make_header(d, t), position_ned_m=tuple(map(float, J[k, 11:13].mean(0))),
                    velocity_ned_m_s=(1.2, 0.0, 0.0), covariance=tuple(map(float, np.eye(6).ravel()))), t + 4000)
            frames.append({"jpeg": jpeg, "uv": uv, "conf": conf, "box": box, "t": t})
        rec.close()
        truth[d] = {"T": T, "pos": pos, "frames": frames, "K": K}
    (folder / "drone_3.s001.mcap").write_bytes(b"this is not an MCAP file")  # a garbage drone file
    return folder, truth, J, t_ns


def _decode_all(path):
    """{topic: [decoded protobuf message]} for every message, checked against its channel's Foxglove schema."""
    out = {}
    with open(path, "rb") as f:
        reader = make_reader(f)
        for schema, channel, msg in reader.iter_messages(log_time_order=True):
            assert channel.message_encoding == "protobuf" and schema.encoding == "protobuf"
            assert schema.name.startswith("foxglove."), schema.name
            name = schema.name.split(".", 1)[1]
            cls = getattr(importlib.import_module(f"foxglove_schemas_protobuf.{name}_pb2"), name)
            m = cls.FromString(msg.data)
            assert m.ByteSize() == len(msg.data)  # every byte is a field of the schema
            out.setdefault(channel.topic, []).append((msg.log_time, m))
    return out


def _ns(ts) -> int:
    return ts.seconds * 1_000_000_000 + ts.nanos


def _R(q) -> np.ndarray:
    return Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()


@pytest.fixture(scope="module")
def exported(flight, tmp_path_factory):
    folder, truth, J, t_ns = flight
    out = tmp_path_factory.mktemp("fox") / "flight.foxglove.mcap"
    res = export_foxglove(folder, _Motion(t_ns, J), out)
    return res, _decode_all(out)


def test_every_channel_decodes_and_counts_match(flight, exported):
    res, msgs = exported
    assert set(res.skipped) == {"drone_3"}  # the garbage file is skipped, not fatal
    assert {t: len(v) for t, v in msgs.items()} == res.counts
    for d in ("drone_1", "drone_2"):
        assert res.counts[f"/{d}/camera/image"] == res.counts[f"/{d}/camera/annotations"] == FRAMES
        assert res.counts[f"/{d}/camera/calibration"] == 1
    assert res.counts["/reconstruction/skeleton"] == FRAMES and res.counts["/person/track"] == FRAMES
    assert res.counts["/tf"] == 1 + 2 * (2 * FRAMES) + 2 * FRAMES  # static + bodies + cameras


def test_images_calibration_and_annotations(flight, exported):
    _, truth, _, _ = flight
    _, msgs = exported
    for d, tr in truth.items():
        imgs = msgs[f"/{d}/camera/image"]
        anns = {_ns(a.timestamp): a for _, a in msgs[f"/{d}/camera/annotations"]}
        for (log_t, img), fr in zip(imgs, tr["frames"]):
            assert img.data == fr["jpeg"] and img.format == "jpeg" and img.frame_id == f"{d}/camera"
            assert _ns(img.timestamp) == log_t == fr["t"]
            a = anns[fr["t"]]  # the annotations carry the image's timestamp (the Image panel pairs them by it)
            loops = [p for p in a.points if p.type == p.LINE_LOOP]
            b = fr["box"]
            np.testing.assert_allclose([(q.x, q.y) for q in loops[0].points], [
                (b.x_min_px, b.y_min_px), (b.x_max_px, b.y_min_px), (b.x_max_px, b.y_max_px), (b.x_min_px, b.y_max_px)])
            pts = next(p for p in a.points if p.type == p.POINTS)
            seen = fr["conf"] > 0
            np.testing.assert_allclose([(q.x, q.y) for q in pts.points], fr["uv"][seen], atol=1e-9)
            lines = next(p for p in a.points if p.type == p.LINE_LIST)
            n_limbs = sum(seen[i] and seen[j] for i, j in COCO17_LIMBS)
            assert len(lines.points) == 2 * n_limbs
            assert a.texts[0].text.startswith("person 0.90")
        (_, cal), = msgs[f"/{d}/camera/calibration"]
        assert cal.frame_id == f"{d}/camera" and (cal.width, cal.height) == (W, H)
        np.testing.assert_allclose(np.reshape(cal.K, (3, 3)), tr["K"])
        assert cal.distortion_model == "plumb_bob" and list(cal.D) == pytest.approx([0.01, -0.002, 0, 0, 0])


def test_transforms_scene_and_skeleton(flight, exported):
    _, truth, J, t_ns = flight
    _, msgs = exported
    tfs = [t for _, m in msgs["/tf"] for t in m.transforms]
    static = [t for t in tfs if t.child_frame_id == "ned"]
    assert len(static) == 1 and static[0].parent_frame_id == "world"
    np.testing.assert_allclose(_R(static[0].rotation), R_ENU_NED, atol=1e-12)  # down is -up: the scene stands upright
    for d, tr in truth.items():
        cams = [t for t in tfs if t.child_frame_id == f"{d}/camera"]
        assert len(cams) == FRAMES and all(t.parent_frame_id == "ned" for t in cams)
        c = cams[3]
        np.testing.assert_allclose(_R(c.rotation), tr["T"][:3, :3], atol=1e-9)
        np.testing.assert_allclose([c.translation.x, c.translation.y, c.translation.z], tr["T"][:3, 3], atol=1e-9)
        # the camera frame is the optical one (z forward): the person is in front of it
        p_cam = np.linalg.inv(tr["T"]) @ np.r_[J[3, 0], 1.0]
        assert p_cam[2] > 0
        bodies = [t for t in tfs if t.child_frame_id == f"{d}/body"]
        assert len(bodies) == 2 * FRAMES
        np.testing.assert_allclose([bodies[0].translation.x, bodies[0].translation.y, bodies[0].translation.z], tr["pos"])
    (_, drones), = msgs["/drones"]
    assert sorted(e.frame_id for e in drones.entities) == ["drone_1/body", "drone_2/body"]
    assert all(e.frame_locked and len(e.cubes) == 1 for e in drones.entities)
    for k, (log_t, upd) in enumerate(msgs["/reconstruction/skeleton"]):
        (e,) = upd.entities
        assert e.frame_id == "ned" and _ns(e.timestamp) == log_t == t_ns[k]
        np.testing.assert_allclose([(s.pose.position.x, s.pose.position.y, s.pose.position.z) for s in e.spheres], J[k])
        assert len(e.lines[0].points) == 2 * len(COCO17_LIMBS)
    track = [u.entities[0] for _, u in msgs["/person/track"]]
    assert track[0].id == "person/drone_1" and len(track[-1].lines[0].points) == FRAMES
    p = track[-1].spheres[0].pose.position
    np.testing.assert_allclose([p.x, p.y, p.z], J[-1, 11:13].mean(0))


def test_refuses_to_overwrite_and_needs_a_readable_drone(flight, exported, tmp_path):
    folder, *_ = flight
    res, _ = exported
    with pytest.raises(FoxgloveExportError, match="already exists"):
        export_foxglove(folder, None, res.path)
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "drone_1.s001.mcap").write_bytes(b"garbage")
    with pytest.raises(FoxgloveExportError, match="no drone recording could be read"):
        export_foxglove(bad, None, tmp_path / "x.mcap")
    assert not (tmp_path / "x.mcap").exists() and not list(tmp_path.glob(".x.mcap*"))


def test_cli_writes_the_flight_with_its_reconstruction(flight, tmp_path):
    from apps.cli import main

    folder, _, J, t_ns = flight
    motion = tmp_path / "motion.npz"
    np.savez(motion, t_ns=t_ns, joints_ned=J)
    ids = FlightFolder(folder).drone_ids()
    assert main(["log", "foxglove", str(folder), "--motion", str(motion)]) == 0
    out = FlightFolder(folder).foxglove_path  # the default: in the flight folder, never read as a recording
    assert len(_decode_all(out)["/reconstruction/skeleton"]) == FRAMES
    assert FlightFolder(folder).drone_ids() == ids == ["drone_1", "drone_2", "drone_3"]
