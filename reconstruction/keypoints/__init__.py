"""2D keypoint detectors (COCO-17) for reconstruction: several shipped ONNX models over the same person
crops, single images or whole recordings. See :mod:`reconstruction.keypoints.detectors`.

Light on purpose (imported by ``skycap --help``): only the model names live here.
"""

#: The shipped keypoint models (files in ``reconstruction/keypoints/models/``).
KEYPOINT_MODELS: tuple[str, ...] = ("movenet_lightning", "movenet_thunder", "blazepose_full", "blazepose_lite")
#: Models run when none are named: two different networks (MoveNet and BlazePose).
DEFAULT_MODELS: tuple[str, ...] = ("movenet_thunder", "blazepose_full")
