"""The export step's exporters run concurrently (threads or spawned processes) and write the same files as one
after the other."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest

from reconstruction.process.config import ProcessConfig
from reconstruction.process.events import ProcessError
from reconstruction.process.export import EXPORTERS, ExportContext, config_snapshot, export_all, register_exporter
from reconstruction.synth import procedural_walker, synthesize_capture


def write_marker(ctx: ExportContext) -> dict[str, Path]:
    """A module-level exporter (picklable: runs in a worker process too)."""
    p = ctx.out_dir / "marker.txt"
    p.write_text(f"{len(ctx.t_ns)} {ctx.config.sortie_or_none} {threading.current_thread().name}")
    return {"marker": p}


@pytest.fixture(scope="module")
def motion():
    J, t_ns, shape, *_ = procedural_walker(30, fps=10.0)
    capture, _ = synthesize_capture(J, t_ns)
    return J, t_ns, shape, capture


def _ctx(motion, out: Path) -> ExportContext:
    J, t_ns, shape, capture = motion
    return ExportContext(flight=None, out_dir=out, t_ns=t_ns, joints_ned=J, capture=capture, method="multiview",
                         config=ProcessConfig(), keypoints_source="sim", shape=shape)


def _files(out: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(out.iterdir()) if p.suffix in (".bvh", ".trc", ".csv")}


def test_threads_write_the_same_files_as_one_after_the_other(motion, tmp_path):
    register_exporter("marker", write_marker)
    try:
        runs = {}
        for name, workers in (("serial", 0), ("threads", 2)):
            out = tmp_path / name
            out.mkdir()
            paths, seconds = export_all(_ctx(motion, out), True, ["marker"], workers, pool="threads")
            assert list(paths)[:5] == ["bvh", "trc", "npz", "csv", "rrd"] and "marker" in paths
            assert all(p.is_file() for p in paths.values())
            assert set(seconds) == {"motion", "rrd", "marker"}
            runs[name] = out
        assert _files(runs["serial"]) == _files(runs["threads"])
        assert "MainThread" in (runs["serial"] / "marker.txt").read_text()
        assert "export" in (runs["threads"] / "marker.txt").read_text()  # ran in a worker thread
        np.testing.assert_array_equal(np.load(runs["serial"] / "motion.npz")["joints_ned"],
                                      np.load(runs["threads"] / "motion.npz")["joints_ned"])
    finally:
        EXPORTERS.pop("marker", None)


def test_an_unpicklable_exporter_runs_in_this_process(motion, tmp_path):
    """pool="processes" sends only picklable exporters to spawned workers (a lambda runs here; nothing is spawned
    for it). The spawned path itself runs in the demo flight's processing (README, Fit start-up and export)."""
    register_exporter("local", lambda ctx: {"local": write_marker(ctx)["marker"]})
    try:
        paths, seconds = export_all(_ctx(motion, tmp_path), False, ["local"], 2, pool="processes")
        assert set(seconds) == {"motion", "local"}
        assert "MainThread" in paths["local"].read_text()
    finally:
        EXPORTERS.pop("local", None)


def test_config_snapshot_keeps_attributes_and_properties():
    cfg = ProcessConfig()
    snap = config_snapshot(cfg)
    assert snap.sortie_or_none == cfg.sortie_or_none
    assert snap.export.extra == cfg.export.extra and snap.keypoints.models == cfg.keypoints.models


def test_unknown_exporter_and_pool_are_refused(motion, tmp_path):
    with pytest.raises(ProcessError, match="no exporter registered"):
        export_all(_ctx(motion, tmp_path), False, ["nope"], 0)
    with pytest.raises(ProcessError, match="export.pool"):
        export_all(_ctx(motion, tmp_path), False, [], 2, pool="fibres")
