"""Package data: the shipped ONNX keypoint models (see README.md here)."""
