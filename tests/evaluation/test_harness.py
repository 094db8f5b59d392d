"""evaluation.harness: the flight-grade harness's presets and error model (pure), and one short run with the real
renderer and the real keypoint models."""

import dataclasses
import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from evaluation.harness import HarnessConfig, flight_errors_from_estimator, resolve, run_harness
from reconstruction.process.config import KeypointsConfig
from reconstruction.synth import FlightPoseErrors, SynthConfig, flight_pose_errors, synthesize_capture
from simulator.config import POSITION_GRADES, EstimatorConfig, estimator_for_grade, grade_overrides
from simulator.scene.config import CameraConfig
from skycap.config import ConfigError, load_config


def test_grades_come_from_the_simulator_presets():
    rtk = resolve(HarnessConfig(position_grade="rtk")).synth.flight_errors
    gps = resolve(HarnessConfig(position_grade="gps")).synth.flight_errors
    est = EstimatorConfig()
    assert rtk.pos_bias_std_xy_m == POSITION_GRADES["rtk"]["pos_bias_std_xy_m"] == 0.02
    assert rtk.pos_bias_std_z_m == POSITION_GRADES["rtk"]["pos_bias_std_z_m"]
    assert gps.pos_bias_std_xy_m == est.pos_bias_std_xy_m and gps.pos_bias_std_z_m == est.pos_bias_std_z_m
    for fe in (rtk, gps):  # the rest is the estimator's, whatever the grade
        assert (fe.att_noise_std_deg, fe.att_noise_time_constant_s, fe.pos_bias_time_constant_s, fe.pos_noise_std_m) == (
            est.att_noise_std_deg, est.att_noise_time_constant_s, est.pos_bias_time_constant_s, est.pos_noise_std_m)
    assert grade_overrides("rtk") == ["estimator.pos_bias_std_xy_m=0.02", "estimator.pos_bias_std_z_m=0.03"]
    assert grade_overrides("gps") == []
    assert flight_errors_from_estimator(estimator_for_grade("rtk"), 5.0).margin_s == 5.0
    no_att = resolve(load_config(HarnessConfig, None, ["estimator.att_noise_std_deg=0"])).synth.flight_errors
    assert no_att.att_noise_std_deg == 0 and no_att.pos_bias_std_xy_m == 0.02  # the grade on top of the base


def test_resolve_takes_the_simulators_camera_and_detector():
    cfg = resolve(HarnessConfig(camera=CameraConfig(person_model="anny", width_px=800, height_px=450, rate_hz=15)))
    assert (cfg.synth.width_px, cfg.synth.height_px, cfg.synth.camera_rate_hz) == (800, 450, 15)
    assert cfg.synth.focal_px == pytest.approx(400 / np.tan(np.radians(35)))
    assert cfg.synth.pose_errors == "flight"
    sim = resolve(HarnessConfig(keypoints="sim"))
    assert 1.5 < sim.synth.noise_px < 3.0 and sim.synth.outlier_rate == 0.03  # SimDetectorConfig at 640x360
    exact = load_config(HarnessConfig, None, ["keypoints='sim'", "sim_detector.noise_px=0", "sim_detector.noise_frac_of_height=0",
                                              "sim_detector.outlier_prob=0"])
    assert resolve(exact).synth.noise_px == 0 and resolve(exact).synth.outlier_rate == 0
    white = resolve(HarnessConfig(pose_errors="white"))
    assert white.synth.pose_errors == "white" and white.synth.camera_pos_noise_m == SynthConfig().camera_pos_noise_m


@pytest.mark.parametrize("field, value, match", [("position_grade", "dgps", "position_grade"),
                                                 ("keypoints", "openpose", "keypoints"),
                                                 ("pose_errors", "pink", "pose_errors")])
def test_bad_settings_name_the_choices(field, value, match):
    with pytest.raises(ConfigError, match=match):
        resolve(dataclasses.replace(HarnessConfig(), **{field: value}))
    with pytest.raises(ConfigError, match="person_model='anny'"):
        resolve(HarnessConfig(camera=CameraConfig(person_model="ellipsoids")))


def test_config_round_trips_through_toml(tmp_path):
    from skycap.config import save_config

    cfg = resolve(HarnessConfig(motion="m.bvh", position_grade="gps", keypoints="sim"))
    save_config(cfg, tmp_path / "c.toml")
    back = load_config(HarnessConfig, tmp_path / "c.toml", ["frames=25"])
    assert back.position_grade == "gps" and back.frames == 25 and back.synth.flight_errors == cfg.synth.flight_errors


def test_flight_pose_errors_have_the_estimator_statistics():
    fe = flight_errors_from_estimator(estimator_for_grade("gps"))
    tp = np.arange(0, 10, 0.1)
    bias, att = [], []
    for s in range(300):
        dp, dr = flight_pose_errors(np.random.default_rng(s), tp, fe)
        bias.append(dp.mean(0))
        att.append(dr[::10])  # 1 s apart: tau 1 s, nearly independent
    bias, att = np.array(bias), np.degrees(np.concatenate(att))
    np.testing.assert_allclose(bias.std(0), [1.0, 1.0, 0.5], rtol=0.15)  # 60 s bias: constant over a 10 s clip
    np.testing.assert_allclose(att.std(0), [0.0, 0.0, 1.0], rtol=0.1, atol=1e-12)  # yaw only (gimbal camera)
    body = dataclasses.replace(fe, attitude_axes="all")
    att_all = np.degrees(np.concatenate([flight_pose_errors(np.random.default_rng(s), tp, body)[1][::10] for s in range(300)]))
    np.testing.assert_allclose(att_all.std(0), 1.0, rtol=0.1)
    yaw = att.reshape(300, -1, 3)[:, :, 2]  # (seed, second): 1 s apart correlate exp(-1 s / tau) = 1/e
    assert np.corrcoef(yaw[:, 3], yaw[:, 4])[0, 1] == pytest.approx(np.exp(-1.0), abs=0.12)
    assert abs(np.corrcoef(yaw[:, 0], yaw[:, 9])[0, 1]) < 0.15  # 9 s apart: independent


def test_synth_flight_mode_errs_as_the_estimator():
    t = np.arange(60) * int(1e9 / 30)
    J = np.zeros((60, 17, 3)) + np.linspace(0, 1, 17)[None, :, None] * np.array([0, 0.2, -1.7])
    fe = flight_errors_from_estimator(estimator_for_grade("rtk"))
    cap, truth = synthesize_capture(J, t, SynthConfig(pose_errors="flight", flight_errors=fe), seed=0)
    for cam, T_true in zip(cap.cameras, truth.T_world_cam_true):
        dpos = np.linalg.norm(cam.T_world_cam[:, :3, 3] - T_true[:, :3, 3], axis=-1)
        drot = np.degrees(Rotation.from_matrix(np.swapaxes(T_true[:, :3, :3], 1, 2) @ cam.T_world_cam[:, :3, :3]).magnitude())
        assert dpos.max() < 0.25 and 0.05 < drot.mean() < 3.0
        assert cam.omega_cam_radps is None and cam.vel_world_mps is not None  # velocity only, as a flight
        assert cam.pos_sigma_m[0] == pytest.approx(fe.pos_sigma_m()) and cam.rot_sigma_deg[0] == pytest.approx(1.0)
        # yaw only: the camera's error turns about the world's down axis, the optical axis keeps its tilt
        tilt = lambda T: np.degrees(np.arcsin(T[:, 2, 2]))  # noqa: E731  (z axis's down component)
        np.testing.assert_allclose(tilt(cam.T_world_cam), tilt(T_true), atol=1e-9)
    with pytest.raises(ConfigError, match="pose_errors"):
        synthesize_capture(J, t, SynthConfig(pose_errors="brown"))
    white_a, _ = synthesize_capture(J, t, SynthConfig(), seed=0)
    white_b, _ = synthesize_capture(J, t, SynthConfig(flight_errors=FlightPoseErrors(pos_bias_std_xy_m=3.0)), seed=0)
    np.testing.assert_array_equal(white_a.cameras[0].T_world_cam, white_b.cameras[0].T_world_cam)  # white: unchanged


def test_harness_runs_the_models_on_rendered_frames(cmu_dir, tmp_path):
    """A 0.3 s clip, 2 drones, the real renderer (Anny) and keypoint models, a short fit: every frame sees the
    person, the models' keypoints place the joints within a person's size, the outputs name the sources."""
    cfg = HarnessConfig(motion=str(cmu_dir / "002" / "002_01.bvh"), out=str(tmp_path / "h"), frames=3, export=False,
                        start=1, context_s=0.1,
                        synth=SynthConfig(pose_errors="flight", drones=2))
    cfg.fit.iters = 40
    m = run_harness(cfg, progress=False)
    assert m["keypoints_source"] == "models:" + "+".join(KeypointsConfig().models) and m["position_grade"] == "rtk"
    assert m["frames"] == 3 and m["context_frames"] == 2  # one frame of flight before and after the scored clip
    assert m["frames_without_person"] == 0 and m["rendered_frames"] >= 2 * 2
    assert 0 < m["keypoint_err_median_frac_of_height"] < 0.1 and m["person_height_px_median"] > 30
    assert m["mpjpe_mm"] < 300 and m["w_mpjpe_mm"] < 800 and m["camera_pos_err_m_before"] < 0.2
    saved = json.loads((tmp_path / "h" / "metrics.json").read_text())
    assert saved["position_grade"] == "rtk" and "per_group_mm" in saved
    assert load_config(HarnessConfig, tmp_path / "h" / "config.toml").synth.flight_errors.pos_bias_std_xy_m == 0.02
