"""Body models behind one small interface, so the fitting code does not care which model is used.

:class:`BodyModel` (a ``torch.nn.Module``)::

    joints = model(root_orient, pose, transl, shape)   # -> (B, 17, 3) COCO-17, world frame, metres

    root_orient (B, 3)   axis-angle, body frame (x = left, y = up, z = forward) -> world
    pose        (B, P, 3) axis-angle local joint rotations (P = model.num_pose)
    transl      (B, 3)   world position of the model's root (the pelvis = mid-hip for the skeleton model)
    shape       (B, S) or (S,)

Differentiable in every input, batched over B, on any torch device/dtype of its inputs.

Models:

* :class:`SkeletonBodyModel` (default for fitting): the COCO-17 kinematic skeleton of
  :mod:`reconstruction.body.skeleton17` — 11 rotating joints, 16 shape numbers (bone lengths and
  head geometry). Its shape prior (mean, covariance) is derived from the Anny body model's COCO
  keypoint regressor over adult phenotypes (:mod:`reconstruction.body.derive_from_anny`, committed
  file, CC0). Because its joints ARE joint centres with free bone lengths, it adapts to a motion
  capture subject's skeleton (the evaluation ground truth) instead of carrying the systematic offset
  between a mesh model's surface-regressed COCO points and mocap joint centres.
* :class:`AnnyBodyModel`: the full Anny mesh model (``pip install anny``; Apache-2.0 code, CC0 assets)
  with its COCO regressor; pose = 104 bone rotations, shape = 6 phenotype numbers in [0, 1]. First
  start ~75 s and a ~790 MB cache in ``ANNY_CACHE_DIR``. Anny's SMPL/SMPL-X interop (non-commercial
  data downloaded on demand) is never called.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from reconstruction.body import skeleton17 as sk

ANNY_SHAPE_FILE = Path(__file__).with_name("data") / "skeleton17_anny_shape.npz"

# Anny's rest frame (x = left, y = back, z = up) -> body frame (x = left, y = up, z = forward)
_C_BODY_ANNY = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


class BodyModel(torch.nn.Module):
    """Interface: parameters -> COCO-17 joints (see module docstring)."""

    num_pose: int
    num_shape: int

    def forward(self, root_orient, pose, transl, shape) -> torch.Tensor:  # pragma: no cover - interface
        raise NotImplementedError

    def mean_shape(self) -> torch.Tensor:
        raise NotImplementedError

    def shape_energy(self, shape: torch.Tensor) -> torch.Tensor:
        """Squared Mahalanobis distance of shape(s) (..., S) from the population; (...,)."""
        raise NotImplementedError


class SkeletonBodyModel(BodyModel):
    """COCO-17 kinematic skeleton (11 joints x 3, 16 shape numbers); see :mod:`skeleton17`."""

    num_pose = sk.NUM_POSE
    num_shape = sk.NUM_SHAPE

    def __init__(self, shape_file: Path | None = ANNY_SHAPE_FILE, shape_floor_m: float = 0.02):
        super().__init__()
        if shape_file is not None and Path(shape_file).is_file():
            z = np.load(shape_file)
            mean, cov = z["mean"], z["cov"]
        else:
            mean, cov = sk.DEFAULT_SHAPE, np.diag(np.full(sk.NUM_SHAPE, 0.03**2))
        # floor of 2 cm per number: Anny's COCO points are surface-regressed, a mocap subject's are joint
        # centres; the floor keeps Anny's proportions from overruling what the images measure
        cov = cov + np.eye(len(mean)) * shape_floor_m**2
        self.register_buffer("shape_mean", torch.tensor(mean, dtype=torch.float64))
        self.register_buffer("shape_prec", torch.tensor(np.linalg.inv(cov), dtype=torch.float64))

    def forward(self, root_orient, pose, transl, shape):
        R_root = sk.axis_angle_to_matrix(root_orient)
        R_loc = sk.axis_angle_to_matrix(pose)
        return sk.forward_kinematics_torch(R_root, R_loc, transl, shape)[:, sk.COCO_TO_NODE]

    def mean_shape(self) -> torch.Tensor:
        return self.shape_mean.clone()

    def shape_energy(self, shape):
        d = shape - self.shape_mean.to(shape)
        return torch.einsum("...i,ij,...j->...", d, self.shape_prec.to(shape), d)


class AnnyBodyModel(BodyModel):
    """Anny mesh model + its COCO keypoint regressor (first 17 = COCO-17).

    ``pose`` (B, 104, 3) local bone rotations (axis-angle), ``shape`` (B, 6) phenotypes in [0, 1]
    (gender, age, muscle, weight, height, proportions); ``transl`` is where Anny's origin goes.
    """

    def __init__(self, cache_dir: str | Path | None = None):
        super().__init__()
        import os

        if cache_dir is not None:
            os.environ["ANNY_CACHE_DIR"] = str(cache_dir)
        import anny
        from anny.paths import set_anny_cache_path

        if cache_dir is not None:
            set_anny_cache_path(cache_dir)
        self.anny = anny.Anny()
        self.regressor = anny.KeypointsRegressor.coco(self.anny)
        self.num_pose = int(self.anny.bone_count)
        self.num_shape = len(self.anny.phenotype_labels)
        self.register_buffer("C", torch.tensor(_C_BODY_ANNY, dtype=self.anny.dtype))

    def forward(self, root_orient, pose, transl, shape):
        dt = self.anny.dtype
        B = pose.shape[0]
        T = torch.eye(4, dtype=dt, device=pose.device).repeat(B, self.num_pose, 1, 1)
        T[:, :, :3, :3] = sk.axis_angle_to_matrix(pose.to(dt))
        if shape.dim() == 1:
            shape = shape.expand(B, -1)
        out = self.anny(pose_parameters=T, phenotype_kwargs=shape.to(dt))
        kp = self.regressor(out)[:, :17]  # Anny frame
        kp_body = kp @ self.C.T
        R = sk.axis_angle_to_matrix(root_orient.to(dt))
        return (kp_body @ R.transpose(-1, -2) + transl.to(dt)[:, None]).to(pose.dtype)

    def mean_shape(self) -> torch.Tensor:
        return torch.full((self.num_shape,), 0.5, dtype=self.anny.dtype)

    def shape_energy(self, shape):
        return (((shape - 0.5) / 0.25) ** 2).sum(-1)
