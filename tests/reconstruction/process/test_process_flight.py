"""``skycap process`` on a real recorded flight (``skycap demo``, 2 drones) with the real ONNX models: the motion
against the simulator's truth, resume after a cancel without recomputing finished work, an unreadable drone
skipped, windows stitched like one window, the CLI (and its ``reconstruct`` alias)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from process_helpers import TEST_MODELS, copy_flight, make_config

pytestmark = pytest.mark.slow



def test_the_models_give_a_motion_near_the_truth(processed):
    from evaluation.flight import reconstruction_accuracy

    res, _, events = processed["runs"][1]
    assert res.keypoints_source == "+".join(TEST_MODELS) == res.summary["keypoints_source"]
    assert res.method == "multiview" and res.drones == ["drone_1", "drone_2"] and not res.skipped
    assert res.joints_ned.shape == (len(res.t_ns), 17, 3) and np.all(np.isfinite(res.joints_ned))
    for k in ("bvh", "npz", "csv", "trc", "foxglove"):
        assert res.outputs[k].is_file(), k
    # the Foxglove MCAP of the processed flight (flightdata.foxglove; decoded schema by schema in its own tests)
    from mcap.reader import make_reader

    with open(res.outputs["foxglove"], "rb") as f:
        topics = {c.topic for c in make_reader(f).get_summary().channels.values()}
    assert {"/drone_1/camera/image", "/drone_2/camera/annotations", "/tf", "/reconstruction/skeleton"} <= topics, topics
    s = json.loads((res.out_dir / "summary.json").read_text())
    assert s["seconds"] > 0 and s["steps"]["keypoints"]["models"] == TEST_MODELS
    assert all(v["detection"] > 10 for v in s["box_sources"].values()), s["box_sources"]
    acc = reconstruction_accuracy(processed["flight"], motion_npz=res.outputs["npz"])
    # the simulator's person renderer limits what the models see: a loose bound that still catches a broken chain
    # (a wrong camera, frame or joint order is metres off)
    assert acc["frames_scored"] > 10 and acc["mpjpe_mm"] < 600 and acc["pa_mpjpe_mm"] < 250, acc
    steps = [e.step for e in events]
    assert steps.index("keypoints") < steps.index("fit") < steps.index("export")
    assert [e.fraction for e in events if e.step == "export"][-1] == 1.0


def test_a_cancelled_run_resumes_without_recomputing_finished_work(processed):
    from reconstruction.process import Cancelled

    (r1, c1, ev1), (r2, c2, _), (r3, c3, _) = processed["runs"]
    assert isinstance(r1, Cancelled) and "resume" in str(r1)
    assert ev1[-1].step == "keypoints" and c1.crops > 0 and c1.fits == 0
    flight = processed["flight"]
    assert list((flight / "processing" / "keypoints").glob("*.chunks/chunk_*.npz")) == []  # consolidated by run 2
    # run 2: the boxes from the cache, only the keypoint chunks run 1 did not finish
    assert c2.boxes == 0 and r2.steps["boxes"]["cached"]
    per_model_total = r2.stats["frames_computed"] + c1.crops // len(TEST_MODELS)
    assert c1.crops + c2.crops == per_model_total * len(TEST_MODELS)  # no frame ran twice
    assert 0 < c2.crops < per_model_total * len(TEST_MODELS)
    # run 3: everything from the cache, the same motion
    assert (c3.crops, c3.fits, c3.boxes) == (0, 0, 0)
    assert all(r3.steps[s]["cached"] for s in ("boxes", "keypoints", "fit", "export")), r3.steps
    np.testing.assert_array_equal(r3.joints_ned, r2.joints_ned)
    assert not [p for p in flight.rglob(".*.tmp")]  # no temporary file left by the cancel


def test_an_unreadable_drone_is_skipped_while_two_remain(processed, tmp_path, caplog):
    from reconstruction.process import ProcessError, process

    flight = copy_flight(processed["flight"], tmp_path / "f", with_cache=True)
    (flight / "drone_3.s001.mcap").write_bytes(b"this is not a recording " * 100)
    res = process(flight, make_config(**{"boxes.use_smoother": True}))
    assert res.drones == ["drone_1", "drone_2"] and list(res.skipped) == ["drone_3"]
    assert "skipping drone_3" in caplog.text and "not an MCAP file" in res.skipped["drone_3"]
    assert res.summary["skipped"] == res.skipped and res.steps["keypoints"]["cached"]
    (flight / "drone_2.s001.mcap").write_bytes(b"\x89MCAP0\r\n" + b"\x00" * 64)  # the header, then garbage
    with pytest.raises(ProcessError, match="1 usable drone.*needs 2.*drone_2"):
        process(flight, make_config(method="multiview"))


def test_windows_are_stitched_into_the_single_window_motion(processed, tmp_path):
    from reconstruction.process import process

    flight = copy_flight(processed["flight"], tmp_path / "f", with_cache=True)
    one = processed["runs"][1][0]  # the default window (60 s) holds the whole flight
    assert one.steps["fit"]["windows"] == 1
    span = (one.t_ns[-1] - one.t_ns[0]) * 1e-9
    many = process(flight, make_config(out_dir=str(tmp_path / "many"),
                                       **{"windows.window_s": span / 2, "windows.overlap_s": span / 6}))
    assert many.steps["keypoints"]["cached"] and many.steps["fit"]["windows"] >= 2
    t, a, b = np.intersect1d(one.t_ns, many.t_ns, return_indices=True)
    assert len(t) >= 0.9 * len(one.t_ns)
    diff = np.linalg.norm(one.joints_ned[a] - many.joints_ned[b], axis=-1)
    assert np.median(diff) < 0.08, np.median(diff)  # independent fits of the same data
    # no jump at the window boundaries: frame-to-frame motion like the single window's
    step_one = np.linalg.norm(np.diff(one.joints_ned[a], axis=0), axis=-1).max()
    step_many = np.linalg.norm(np.diff(many.joints_ned[b], axis=0), axis=-1).max()
    assert step_many < 1.5 * step_one + 0.05, (step_many, step_one)


def test_the_cli_processes_with_a_progress_report_and_keeps_reconstruct_as_an_alias(processed, tmp_path, capsys):
    from apps.cli import main

    flight = copy_flight(processed["flight"], tmp_path / "f")
    args = [str(flight), "--keypoints", "sim", "--set", "multiview.fit.iters=20", "--set", "export.rrd=false"]
    assert main(["process", *args]) == 0
    out = capsys.readouterr()
    s = json.loads(out.out[out.out.index("{"):])
    assert s["keypoints_source"] == "sim" and s["method"] == "multiview" and s["steps"]["fit"]["cached"] is False
    assert "fit: 100%" in out.err and "export: 100%" in out.err  # the plain progress lines (not a terminal)
    assert json.loads((flight / "reconstruction" / "summary.json").read_text())["keypoints_source"] == "sim"
    assert main(["reconstruct", *args]) == 0  # the former name: the same command, now from the cache
    out = capsys.readouterr().out
    assert json.loads(out[out.index("{"):])["steps"]["fit"]["cached"] is True
