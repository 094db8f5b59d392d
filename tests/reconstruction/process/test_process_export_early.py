"""The Foxglove exporter starts before the fit (it needs the motion only for its last channel): the same MCAP as
the sequential export, topic by topic; a failed or cancelled fit leaves no partial file and no thread; a cached
export step stays a cache hit. On the short recorded flight (``recorded_flight``), the simulator's keypoints."""

from __future__ import annotations

import importlib
import json
import threading
import time

import pytest

from flightdata.folder import FOXGLOVE_FILE
from process_helpers import copy_flight, make_config

pytest.importorskip("foxglove")


def _cfg(out, **over):
    over = {"keypoints.source": "sim", "multiview.fit.iters": 5, "out_dir": str(out), **over}
    return make_config(**over)


def _decode(path) -> dict[str, list]:
    """{topic: [(log time, decoded Foxglove protobuf message)]}."""
    from mcap.reader import make_reader

    out: dict[str, list] = {}
    with open(path, "rb") as f:
        for schema, channel, msg in make_reader(f).iter_messages(log_time_order=True):
            name = schema.name.split(".", 1)[1]
            cls = getattr(importlib.import_module(f"foxglove_schemas_protobuf.{name}_pb2"), name)
            out.setdefault(channel.topic, []).append((msg.log_time, cls.FromString(msg.data)))
    return out


def _early_threads() -> list:
    """The early exporters' threads and processes still running."""
    import multiprocessing

    return ([t for t in threading.enumerate() if t.name.startswith("export-early")]
            + [p for p in multiprocessing.active_children() if p.name.startswith("export-early")])


def _wait_for(path, timeout_s: float = 60.0) -> None:
    t_end = time.monotonic() + timeout_s
    while not path.exists():
        assert time.monotonic() < t_end, f"{path} never appeared: the early exporter did not start before the fit"
        time.sleep(0.02)


def test_early_foxglove_equals_sequential_and_a_cached_export_is_a_hit(recorded_flight, tmp_path):
    from reconstruction.process import process

    flight = copy_flight(recorded_flight, tmp_path / "flight")
    seq = process(flight, _cfg(tmp_path / "seq", **{"export.workers": 0}))
    early = process(flight, _cfg(tmp_path / "early"))
    assert "early" not in seq.steps["export"]
    timing = early.steps["export"]["early"]["foxglove"]
    assert timing["seconds"] > 0 and 0 <= timing["before_motion_s"] <= timing["seconds"]
    assert 0 <= timing["overlap_s"] <= timing["before_motion_s"] and timing["waited_s"] >= 0
    assert early.steps["export"]["exporters"]["foxglove"] == timing["seconds"]
    assert json.loads((early.out_dir / "summary.json").read_text())["steps"]["export"]["early"] == {"foxglove": timing}
    a, b = _decode(seq.outputs["foxglove"]), _decode(early.outputs["foxglove"])
    assert sorted(a) == sorted(b) and "/reconstruction/skeleton" in a and "/drone_1/camera/image" in a
    for topic in a:
        assert len(a[topic]) == len(b[topic]), topic
        assert a[topic] == b[topic], topic  # the same log times and decoded messages
    assert [p.name for p in early.out_dir.iterdir() if p.name.endswith(".partial")] == []
    assert list(early.outputs) == list(seq.outputs)
    assert not _early_threads()
    again = process(flight, _cfg(tmp_path / "early"))
    assert again.steps["export"]["cached"] is True and "early" not in again.steps["export"]
    assert again.outputs == early.outputs and not _early_threads()
    # export.early=false: the exporters start after the fit (as with workers=0); not in the export's cache key
    assert process(flight, _cfg(tmp_path / "early", **{"export.early": False})).steps["export"]["cached"] is True
    off = process(flight, _cfg(tmp_path / "off", **{"export.early": False}))
    assert "early" not in off.steps["export"] and not off.steps["export"]["cached"] and not _early_threads()
    assert _decode(off.outputs["foxglove"]) == b
    # in threads instead of spawned processes: the same file
    thr = process(flight, _cfg(tmp_path / "threads", **{"export.early_pool": "threads"}))
    assert thr.steps["export"]["early"]["foxglove"]["seconds"] > 0 and _decode(thr.outputs["foxglove"]) == b
    assert not _early_threads()


@pytest.mark.parametrize("pool", ["processes", "threads"])
def test_a_failed_fit_leaves_no_partial_file_and_no_thread(recorded_flight, tmp_path, monkeypatch, pool):
    import reconstruction.process.pipeline as pipeline
    from reconstruction.capture import CaptureError
    from reconstruction.process import ProcessError, process

    flight = copy_flight(recorded_flight, tmp_path / "flight")
    out = tmp_path / "out"

    def failing_fit(*a, **k):
        _wait_for(out / f".{FOXGLOVE_FILE}.partial")  # the early export is writing
        raise CaptureError("test: the fit diverged")

    monkeypatch.setattr(pipeline, "fit_capture", failing_fit)
    with pytest.raises(ProcessError, match="no window could be fitted"):
        process(flight, _cfg(out, **{"export.early_pool": pool}))
    assert not _early_threads()
    assert not out.exists()  # neither the partial MCAP nor the folder made for it


@pytest.mark.parametrize("pool", ["processes", "threads"])
def test_a_cancel_during_the_fit_leaves_no_partial_file_and_no_thread(recorded_flight, tmp_path, monkeypatch, pool):
    import reconstruction.process.pipeline as pipeline
    from reconstruction.process import Cancelled, process

    flight = copy_flight(recorded_flight, tmp_path / "flight")
    out = tmp_path / "out"
    cancel = threading.Event()
    fit = pipeline.fit_capture

    def cancelled_fit(*a, **k):
        _wait_for(out / f".{FOXGLOVE_FILE}.partial")
        cancel.set()  # the fit's next progress report raises Cancelled
        return fit(*a, **k)

    monkeypatch.setattr(pipeline, "fit_capture", cancelled_fit)
    with pytest.raises(Cancelled, match="fit"):
        process(flight, _cfg(out, **{"export.early_pool": pool}), cancel=cancel)
    assert not _early_threads()
    assert not out.exists()
