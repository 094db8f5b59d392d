"""Onboard person detector: NanoDet in onnxruntime with region-of-interest, tiled and whole-frame modes.
See :mod:`onboard.detector.detector`; model files and their checks in :mod:`onboard.detector.modelfile`."""
