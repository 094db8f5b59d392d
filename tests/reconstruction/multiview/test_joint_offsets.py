"""Per-detector joint offsets in the multiview fit (reconstruction.multiview.offsets): the body frame, the table,
and the fit on cameras that see offset points (with the offsets it recovers the true joints, without it is biased)."""

import dataclasses

import numpy as np
import pytest
import torch

from reconstruction.multiview.fit import FitConfig, fit_capture
from reconstruction.multiview.offsets import (JointOffsetError, JointOffsetTable, apply_offsets, apply_offsets_torch,
                                              body_frame, body_frame_torch, load_offsets)
from reconstruction.synth import SynthConfig, procedural_walker, synthesize_capture
from skycap.skeleton import COCO17, SCORED_JOINTS

#: a detector convention like the real models' on the rendered person (fwd, left, up metres): shoulders out and up,
#: hips out, face points up, ankles up
OFFSETS = np.zeros((17, 3))
OFFSETS[[0, 1, 2, 3, 4], 2] = 0.06
OFFSETS[COCO17["left_shoulder"]] = (0.0, 0.065, 0.05)
OFFSETS[COCO17["right_shoulder"]] = (0.0, -0.065, 0.05)
OFFSETS[COCO17["left_hip"]] = (0.0, 0.035, 0.0)
OFFSETS[COCO17["right_hip"]] = (0.0, -0.035, 0.0)
OFFSETS[[15, 16], 2] = 0.055


def _standing(facing_ned=(1.0, 0.0, 0.0)) -> np.ndarray:
    """Joints of a person standing upright (NED, down = +z) facing ``facing_ned`` (horizontal)."""
    fwd = np.asarray(facing_ned, float) / np.linalg.norm(facing_ned)
    up = np.array([0.0, 0.0, -1.0])
    left = np.cross(up, fwd)
    X = np.zeros((17, 3))
    X[[5, 7, 9, 11, 13, 15]] += 0.18 * left
    X[[6, 8, 10, 12, 14, 16]] -= 0.18 * left
    for idx, h in (([5, 6], 1.45), ([7, 8], 1.15), ([9, 10], 0.85), ([11, 12], 0.95), ([13, 14], 0.5), ([15, 16], 0.1),
                   ([0, 1, 2, 3, 4], 1.65)):
        X[idx] += h * up
    return X


def test_body_frame_axes_and_torch_agree():
    for facing in ((1, 0, 0), (0, 1, 0), (1, -1, 0)):
        X = _standing(facing)
        R = body_frame(X)
        f = np.asarray(facing, float) / np.linalg.norm(facing)
        np.testing.assert_allclose(R[:, 0], f, atol=1e-9)  # forward = the way the person faces
        np.testing.assert_allclose(R[:, 2], [0, 0, -1], atol=1e-9)  # up (NED: -z)
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-9)
        assert np.linalg.det(R) == pytest.approx(1.0)
    J, *_ = procedural_walker(5)
    Rt = body_frame_torch(torch.as_tensor(J))
    np.testing.assert_allclose(Rt.numpy(), body_frame(J), atol=1e-9)
    off = np.stack([OFFSETS, 2 * OFFSETS])
    np.testing.assert_allclose(apply_offsets_torch(torch.as_tensor(J), torch.as_tensor(off))[:, 1].numpy(),
                               apply_offsets(J, 2 * OFFSETS), atol=1e-9)
    # a left shoulder offset "out" lands on the person's left for any heading
    Xo = apply_offsets(_standing((0, 1, 0)), OFFSETS)
    assert Xo[5, 0] > 0.18 + 0.06  # facing east, left is north
    assert Xo[5, 2] == pytest.approx(-1.45 - 0.05)


def test_table_roundtrip_and_clear_errors(tmp_path):
    t = JointOffsetTable({"fused:a+b": OFFSETS}, {"fused:a+b": {"flights": ["x", "y"]}})
    back = load_offsets(str(t.save(tmp_path / "o.toml")))
    np.testing.assert_allclose(back.offsets_body_m["fused:a+b"], OFFSETS, atol=1e-4)
    assert back.sources["fused:a+b"]["flights"] == ["x", "y"]
    assert load_offsets("") is None
    np.testing.assert_array_equal(back.for_detectors(["other", "fused:a+b"])[0], 0.0)
    with pytest.raises(JointOffsetError, match="does not exist"):
        load_offsets(str(tmp_path / "missing.toml"))
    (tmp_path / "bad.toml").write_text('[[detector]]\nname = "d"\njoints = ["elbowz"]\noffset_fwd_left_up_mm = [[1, 2, 3]]\n')
    with pytest.raises(JointOffsetError, match="elbowz"):
        load_offsets(str(tmp_path / "bad.toml"))
    builtin = load_offsets("builtin")  # the committed table reads, holds the fused models, offsets of centimetres
    fused = builtin.offsets_body_m["fused:movenet_lightning+blazepose_full"]
    assert 0.01 < np.abs(fused).max() < 0.2


@pytest.fixture(scope="module")
def offset_capture():
    """Three drones (exact poses, 1 px noise) seeing a walker's joints moved by OFFSETS, detector 'det'."""
    J, t_ns, *_ = procedural_walker(15)
    cfg = SynthConfig(noise_px=1.0, outlier_rate=0.0, swap_rate=0.0, miss_rate=0.0, camera_pos_noise_m=0.0,
                      camera_rot_noise_deg=0.0, imu_rates=False, aim_wobble_deg=0.0)
    cap, _ = synthesize_capture(apply_offsets(J, OFFSETS), t_ns, cfg, seed=2)
    cap.cameras = [dataclasses.replace(c, detectors=("det",)) for c in cap.cameras]
    return cap, J, t_ns


def test_fit_with_the_offsets_recovers_the_joints(offset_capture, tmp_path):
    cap, J, t_ns = offset_capture
    table = str(JointOffsetTable({"det": OFFSETS}).save(tmp_path / "o.toml"))
    sj = list(SCORED_JOINTS)
    err = {}
    for name, spec in (("without", ""), ("with", table)):
        res = fit_capture(cap, t_ns, FitConfig(iters=100, refine_cameras=False, joint_offsets=spec), progress=False)
        err[name] = np.linalg.norm(res.joints_ned[:, sj] - J[:, sj], axis=-1)  # (T, 13)
    # without: the fitted shoulders sit where the detector put them (up and out), the face up
    assert err["without"][:, [sj.index(5), sj.index(6)]].mean() > 0.04
    assert err["without"].mean() > 0.025
    # with: the joint centres come back (the noise alone leaves a few mm; measured 7.8 mm against 33 mm without)
    assert err["with"].mean() < 0.012, err["with"].mean(0)
    assert err["with"].mean() < 0.4 * err["without"].mean()


def test_offsets_of_unnamed_detectors_change_nothing(offset_capture, tmp_path):
    cap, J, t_ns = offset_capture
    table = str(JointOffsetTable({"another": OFFSETS}).save(tmp_path / "o.toml"))
    a = fit_capture(cap, t_ns, FitConfig(iters=10, refine_cameras=False, joint_offsets=table), progress=False)
    b = fit_capture(cap, t_ns, FitConfig(iters=10, refine_cameras=False), progress=False)
    np.testing.assert_array_equal(a.joints_ned, b.joints_ned)


def test_a_set_turns_them_on_in_the_product():
    from reconstruction.process.config import ProcessConfig
    from skycap.config import load_config

    assert load_config(ProcessConfig, None, []).multiview.fit.joint_offsets == ""  # off by default (see the README)
    assert load_config(ProcessConfig, None, ['multiview.fit.joint_offsets="builtin"']).multiview.fit.joint_offsets == "builtin"
