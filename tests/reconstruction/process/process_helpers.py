"""Helpers of the ``skycap process`` tests (the test config, copying a flight)."""

from __future__ import annotations

import shutil

#: two different networks (MoveNet Lightning is the fast MoveNet; BlazePose a different network and data)
TEST_MODELS = ["movenet_lightning", "blazepose_full"]


def make_config(**over):
    """A ProcessConfig for the tests: the real models, small chunks, a short fit."""
    from reconstruction.process.config import ProcessConfig

    cfg = ProcessConfig()
    cfg.keypoints.models = list(TEST_MODELS)
    cfg.keypoints.chunk_frames = 16
    cfg.keypoints.batch_size = 16
    cfg.multiview.fit.iters = 40
    cfg.export.rrd = False
    for k, v in over.items():
        obj = cfg
        *path, last = k.split(".")
        for p in path:
            obj = getattr(obj, p)
        setattr(obj, last, v)
    return cfg.validate()


def copy_flight(src, dst, with_cache: bool = False):
    """The flight's recordings and files (not its outputs; its ``processing/`` cache with ``with_cache``)."""
    dst.mkdir(parents=True)
    for p in src.iterdir():
        if p.is_file() and not p.name.startswith("summary"):
            shutil.copy2(p, dst / p.name)
    if with_cache and (src / "processing").is_dir():
        shutil.copytree(src / "processing", dst / "processing")
    return dst
