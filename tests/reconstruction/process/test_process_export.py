"""The export step's exporters run concurrently (threads or spawned processes) and write the same files as one
after the other."""

from __future__ import annotations

import dataclasses
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from reconstruction.process.config import ProcessConfig
from reconstruction.process.events import ProcessError
from reconstruction.process.export import (EARLY_EXPORTERS, EXPORTERS, EarlyExports, ExportContext, MotionUnavailable,
                                          config_snapshot, export_all, register_exporter)
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


def write_late(ctx: ExportContext) -> dict[str, Path]:
    """An early exporter: writes its first part before the motion is known, the motion's part at its end (removing
    its partial file when the fit fails, as the Foxglove exporter does)."""
    part = ctx.out_dir / ".late.txt.partial"
    ctx.out_dir.mkdir(parents=True, exist_ok=True)
    part.write_text(f"{threading.current_thread().name}\n")
    try:
        t_ns, J = ctx.wait_motion()
        with part.open("a") as f:
            f.write(f"{len(t_ns)} {float(J[3, 5, 1]):.6f} {ctx.shape is not None}\n")
    except BaseException:
        part.unlink()
        raise
    return {"late": part.replace(ctx.out_dir / "late.txt")}


def _early_ctx(motion, out: Path) -> ExportContext:
    return dataclasses.replace(_ctx(motion, out), t_ns=None, joints_ned=None, shape=None)


def test_an_early_exporter_waits_for_the_motion_and_writes_the_same_file(motion, tmp_path):
    register_exporter("late", write_late, early=True)
    try:
        seq = tmp_path / "seq"
        seq.mkdir()
        paths_seq, _ = export_all(_ctx(motion, seq), False, ["late"], 0)
        early = EarlyExports(_early_ctx(motion, tmp_path / "early"), ["late"], 2)
        assert early.names == ["late"]
        time.sleep(0.3)  # it runs now, and waits: its first part is written, the file is not
        assert (tmp_path / "early" / ".late.txt.partial").is_file() and not (tmp_path / "early" / "late.txt").exists()
        paths, seconds = export_all(_ctx(motion, tmp_path / "early"), False, ["late"], 2, early=early)
        assert set(seconds) == {"motion", "late"} and list(paths)[-1] == "late"
        assert "export-early" in paths["late"].read_text()
        assert paths["late"].read_text().splitlines()[1] == paths_seq["late"].read_text().splitlines()[1]
        assert paths["late"].read_text().splitlines()[1].endswith("True")  # params / shape handed over too
        t = early.timing["late"]
        assert t["seconds"] >= t["before_motion_s"] >= 0.3 and t["waited_s"] >= 0.2  # it waited for the motion
        assert t["overlap_s"] == pytest.approx(t["before_motion_s"] - t["waited_s"], abs=2e-3)
        assert not [t for t in threading.enumerate() if t.name.startswith("export-early")]
    finally:
        EXPORTERS.pop("late", None)
        EARLY_EXPORTERS.discard("late")


def test_a_failed_fit_stops_the_early_exporters_leaving_no_file_and_no_thread(motion, tmp_path):
    register_exporter("late", write_late, early=True)
    try:
        out = tmp_path / "out"
        early = EarlyExports(_early_ctx(motion, out), ["late"], 2)
        time.sleep(0.3)
        assert (out / ".late.txt.partial").is_file()
        early.abort(ProcessError("no window could be fitted"))
        assert not out.exists()  # the partial file removed, and the folder the early exporter made
        assert not [t for t in threading.enumerate() if t.name.startswith("export-early")]
        with pytest.raises(MotionUnavailable, match="no window could be fitted"):
            early.results()  # the exporter's own error: it stopped at the motion
    finally:
        EXPORTERS.pop("late", None)
        EARLY_EXPORTERS.discard("late")


def test_only_exporters_registered_early_start_early(motion, tmp_path):
    register_exporter("marker", write_marker)
    try:
        early = EarlyExports(_early_ctx(motion, tmp_path), ["marker"], 2)
        assert early.names == [] and not [t for t in threading.enumerate() if t.name.startswith("export-early")]
        paths, seconds = export_all(_ctx(motion, tmp_path), False, ["marker"], 2, early=early)
        assert set(seconds) == {"motion", "marker"}
    finally:
        EXPORTERS.pop("marker", None)
    assert "foxglove" in EARLY_EXPORTERS  # the Foxglove MCAP needs the motion only for its last channel
