"""Package data: the shipped ONNX person detector (see README.md here)."""
