"""The Anny person render (camera.person_model = "anny"): the posed mesh sits on the joints, its silhouette
covers the projected joints, it is shaded and casts a shadow, it is reproducible from its seeds, and the
real keypoint models find the joints on it."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from simulator.scene.anny_body import _LIMBS, MATERIALS, AnnyBodies
from simulator.scene.anny_raster import rasterize
from simulator.scene.camera import PinholeCamera, camera_pose
from simulator.scene.config import CameraConfig, PersonConfig, SceneConfig
from simulator.scene.person import PersonSim
from simulator.scene.render import Renderer
from skycap.config import ConfigError

SIZE = (640, 360)


def _view(cc: CameraConfig, root: np.ndarray, radius_m: float, height_m: float, azimuth_rad: float) -> np.ndarray:
    pos = np.array([root[0] + radius_m * math.cos(azimuth_rad), root[1] + radius_m * math.sin(azimuth_rad), -height_m])
    yaw = math.atan2(root[1] - pos[1], root[0] - pos[0])
    x, y, z, w = Rotation.from_euler("ZYX", [yaw, 0, 0]).as_quat()
    return camera_pose(cc, pos, np.array([w, x, y, z]), -math.atan2(height_m - 0.9, radius_m))


@pytest.fixture(scope="module")
def scene():
    cc = CameraConfig(width_px=SIZE[0], height_px=SIZE[1], person_model="anny", blur_sigma_px=0.0, noise_std=0.0)
    cam = PinholeCamera.from_config(cc)
    st = PersonSim().state_at(1.3)  # walking
    T = _view(cc, st.root_ned_m, 5.0, 2.5, 0.8)
    r = Renderer(cam, cc, PersonConfig(body_seed=2))
    frame = r.render(T, st.joints_ned_m)
    empty = r.render(T, None).image
    no_shadow = Renderer(cam, cc, PersonConfig(body_seed=2), shadows=False).render(T, st.joints_ned_m).image
    return dict(cc=cc, cam=cam, st=st, T=T, r=r, frame=frame, empty=empty, no_shadow=no_shadow)


def test_posed_mesh_joints_land_on_the_target_joints():
    bodies = AnnyBodies.load()
    p = bodies.person(seed=5)
    j = PersonSim().state_at(7.0).joints_ned_m
    A = p.segment_transforms(j)
    r = p.rest_joints
    for s, _, a, b in _LIMBS:  # each limb segment carries its rest bone's ends onto the target's
        for k in (a, b):
            np.testing.assert_allclose(A[s, :, :3] @ r[k] + A[s, :, 3], j[k], atol=1e-9)
    np.testing.assert_allclose(p.pose(r), p.rest_vertices, atol=1e-9)  # rest joints -> rest mesh
    v = p.pose(j)
    assert np.all(np.isfinite(v))
    # the mesh stays a body: its extent is about the skeleton's, a little larger (flesh, head top, feet)
    ext_v, ext_j = np.ptp(v, axis=0), np.ptp(j, axis=0)
    assert np.all(ext_v > ext_j) and np.all(ext_v < ext_j + 0.6)


def test_shapes_and_outfits_vary_with_the_seed():
    bodies = AnnyBodies.load()
    assert bodies.num_shapes >= 8 and len(bodies.faces) < 5000
    people = [bodies.person(seed=s) for s in range(6)]
    assert len({p.shape_index for p in people}) >= 3
    assert len({tuple(np.round(p.vertex_bgr[p.material == MATERIALS.index("shirt")].mean(0))) for p in people}) >= 3
    for p in people:  # every material is present somewhere
        assert set(np.unique(p.material)) >= {MATERIALS.index(m) for m in ("skin", "hair", "shirt", "shoes")}


def test_rasterizer_depth_test_and_coverage():
    # two overlapping squares, the nearer one drawn first: the nearer one must win where they overlap
    uv = np.array([[2, 2], [12, 2], [12, 12], [2, 12], [6, 6], [18, 6], [18, 18], [6, 18]], float)
    depth = np.array([1.0] * 4 + [2.0] * 4)
    faces = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    col = np.array([[1.0]] * 4 + [[2.0]] * 4)
    r = rasterize(uv, depth, faces, col, (0, 0, 20, 20))
    assert r.mask.sum() == 10 * 10 + 12 * 12 - 6 * 6
    assert r.color[8, 8, 0] == 1.0 and r.color[15, 15, 0] == 2.0
    assert r.depth[8, 8] == pytest.approx(1.0) and not r.mask[0, 0]
    # back-face culling keeps only counter-clockwise (positive area, y down) triangles
    assert not rasterize(uv, depth, faces[:, [0, 2, 1]], col, (0, 0, 20, 20), cull_back=True).mask.any()


def test_silhouette_covers_the_projected_joints(scene):
    img, empty, gt = scene["no_shadow"], scene["empty"], scene["frame"].gt  # without shadow: the body alone
    diff = np.abs(img.astype(int) - empty.astype(int)).sum(-1)
    person = scene["frame"].person_roi_px
    mask = np.zeros(diff.shape, bool)
    x0, y0, x1, y1 = person
    mask[y0:y1, x0:x1] = diff[y0:y1, x0:x1] > 30
    mask = cv2.dilate(mask.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    h = gt.box_px[3] - gt.box_px[1]
    assert 120 < h < 300  # a 5 m view at 640x360
    uv = np.round(gt.uv_px - 0.5).astype(int)
    inside = mask[uv[:, 1], uv[:, 0]]
    assert inside[gt.visible].all(), f"joints outside the silhouette: {np.nonzero(~inside & gt.visible)[0]}"
    # and the silhouette is a body, not a blob: it does not fill its box (a standing person fills about half of it)
    area = mask[int(gt.box_px[1]) : int(gt.box_px[3]), int(gt.box_px[0]) : int(gt.box_px[2])].mean()
    assert 0.2 < area < 0.8


def test_person_is_shaded_and_casts_a_shadow(scene):
    img, no_shadow, empty = scene["frame"].image, scene["no_shadow"], scene["empty"]
    gt = scene["frame"].gt
    # shadow: ground pixels outside the person's box darkened by the shadow pass only
    darker = (no_shadow.astype(int).sum(-1) - img.astype(int).sum(-1)) > 40
    x0, y0, x1, y1 = (int(v) for v in gt.box_px)
    darker[y0:y1, x0:x1] = False
    assert darker.sum() > 300
    # shading: the person's pixels span a range of brightness (lit and unlit sides), more than flat colours
    roi = scene["frame"].person_roi_px
    diff = np.abs(no_shadow.astype(int) - empty.astype(int)).sum(-1) > 30
    px = img[roi[1] : roi[3], roi[0] : roi[2]][diff[roi[1] : roi[3], roi[0] : roi[2]]]
    lum = px.astype(float).mean(-1)
    assert np.percentile(lum, 90) - np.percentile(lum, 10) > 40


def test_render_is_reproducible_from_its_seeds(scene):
    cc = CameraConfig(width_px=320, height_px=180, person_model="anny", blur_sigma_px=0.6, noise_std=2.0, noise_seed=4)
    cam = PinholeCamera.from_config(cc)
    T = _view(cc, scene["st"].root_ned_m, 6.0, 3.0, 2.0)
    j = scene["st"].joints_ned_m

    def frames(body_seed: int, noise_seed: int = 4) -> list[np.ndarray]:
        r = Renderer(cam, CameraConfig(**{**cc.__dict__, "noise_seed": noise_seed}), PersonConfig(body_seed=body_seed))
        return [r.render(T, j).image for _ in range(2)]

    a, b = frames(1), frames(1)
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    assert not np.array_equal(a[0], a[1])  # the sensor noise changes from frame to frame
    assert not np.array_equal(a[0], frames(1, noise_seed=5)[0])
    assert np.abs(a[0].astype(int) - frames(4)[0].astype(int)).sum() > 10_000  # another body and outfit


def test_config_selects_and_validates_the_person_model():
    with pytest.raises(ConfigError, match="person_model"):
        SceneConfig(camera=CameraConfig(person_model="mesh")).validate()
    with pytest.raises(ConfigError, match="noise_std"):
        CameraConfig(noise_std=-2.0).validate()
    r = Renderer(PinholeCamera.from_config(CameraConfig()), CameraConfig(), PersonConfig())
    assert r.anny is None  # the default stays the ellipsoid person


def test_real_keypoint_model_finds_the_joints(scene):
    from reconstruction.keypoints.detectors import load_model

    model = load_model("movenet_thunder")
    cc = CameraConfig(width_px=SIZE[0], height_px=SIZE[1], person_model="anny")  # with its blur and noise
    cam = PinholeCamera.from_config(cc)
    sim = PersonSim()
    errs = []
    for k, (t, az) in enumerate(((1.3, 0.8), (4.0, 2.5), (9.0, 4.2))):  # walking, standing, jumping
        st = sim.state_at(t)
        T = _view(cc, st.root_ned_m, 6.0, 3.0, az)
        fr = Renderer(cam, cc, PersonConfig(body_seed=k)).render(T, st.joints_ned_m)
        b = fr.gt.box_px
        kp = model.predict([fr.image], np.array([[b[0], b[1], b[2] - b[0], b[3] - b[1]]]))[0]
        e = np.linalg.norm(kp[:, :2] - fr.gt.uv_px, axis=1) / (b[3] - b[1])
        errs.append(e[fr.gt.visible])
    e = np.concatenate(errs)
    assert np.median(e) < 0.05, f"median error {np.median(e):.3f} of the box height"
    assert np.mean(e < 0.15) > 0.85


def test_camera_effects_default_per_person_model():
    assert CameraConfig().camera_effects() == (0.0, 0.0)  # the ellipsoid person renders as before
    assert CameraConfig(person_model="anny").camera_effects() == (0.6, 2.0)
    assert CameraConfig(person_model="anny", blur_sigma_px=0.0, noise_std=1.0).camera_effects() == (0.0, 1.0)
    with pytest.raises(ConfigError, match="blur_sigma_px"):
        CameraConfig(blur_sigma_px=-0.5).validate()


def test_camera_node_renders_the_anny_person(scene):
    from shared_msgs import keys
    from simulator.scene.camera_node import SIM_KEYPOINTS2D_GT, CameraNode, CameraTruth

    cfg = SceneConfig(camera=CameraConfig(width_px=320, height_px=180, person_model="anny"), person=PersonConfig(body_seed=7))
    st = scene["st"]
    pos = np.array([st.root_ned_m[0] - 6.0, st.root_ned_m[1], -3.0])
    truth = CameraTruth(1_000_000_000, pos, np.array([1.0, 0.0, 0.0, 0.0]), -math.atan2(2.1, 6.0), st.joints_ned_m)
    node = CameraNode("drone_1", cfg, lambda: truth, lambda topic, msg: None)
    assert node.renderer.anny is not None
    out = node.step()
    img = cv2.imdecode(np.frombuffer(out[keys.CAMERA_IMAGE].data, np.uint8), cv2.IMREAD_COLOR)
    assert img.shape == (180, 320, 3)
    gt = out[SIM_KEYPOINTS2D_GT].persons[0]
    b = gt.box
    assert 40 < b.y_max_px - b.y_min_px < 150
    # the person is in the box: its pixels differ from the empty scene's there
    T = camera_pose(cfg.camera, pos, truth.q_world_body, truth.gimbal_pitch_rad)
    empty = Renderer(node.cam, cfg.camera, cfg.person).render(T, None).image
    roi = (slice(int(b.y_min_px), int(b.y_max_px)), slice(int(b.x_min_px), int(b.x_max_px)))
    assert np.mean(np.abs(img[roi].astype(int) - empty[roi].astype(int)).sum(-1) > 40) > 0.2


def test_each_drone_camera_has_its_own_image_noise():
    from simulator.scene.camera_node import CameraNode

    cfg = SceneConfig(camera=CameraConfig(width_px=64, height_px=36, noise_std=2.0, noise_seed=4))
    a, b, a2 = (CameraNode(d, cfg, lambda: None, lambda t, m: None).renderer for d in ("drone_1", "drone_2", "drone_1"))
    assert a._noise_rng.bit_generator.state == a2._noise_rng.bit_generator.state  # reproducible per drone
    assert a._noise_rng.bit_generator.state != b._noise_rng.bit_generator.state  # not shared between drones
