"""The rerun recording written column-wise (:func:`reconstruction.viz.write_rrd`) holds exactly what the former
per-frame ``rec.log`` writer logged: read both ``.rrd`` files back with rerun's own reader and compare entity by
entity, row by row (time, components, values)."""

from __future__ import annotations

import numpy as np
import pytest

from reconstruction.synth import SynthConfig, procedural_walker, synthesize_capture
from skycap.skeleton import COCO17_LIMBS

rr = pytest.importorskip("rerun")
pa = pytest.importorskip("pyarrow")


def _write_rrd_per_frame(path, joints_ned, t_ns, cameras=None, capture=None):
    """The reference: the writer as it was before the columnar API (one ``rec.log`` per entity per frame)."""
    t_ns = np.asarray(t_ns, dtype=np.int64)
    t0 = int(t_ns[0]) if len(t_ns) else 0
    rec = rr.RecordingStream("skycap_reconstruction")
    rec.save(str(path))
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_DOWN, static=True)
    limbs = np.array(COCO17_LIMBS)
    for i in range(len(t_ns)):
        rec.set_time("time", duration=(int(t_ns[i]) - t0) * 1e-9)
        J = joints_ned[i]
        rec.log("world/person/joints", rr.Points3D(J, radii=0.03))
        rec.log("world/person/limbs", rr.LineStrips3D(np.stack([J[limbs[:, 0]], J[limbs[:, 1]]], 1), radii=0.015))
    for cam in cameras or []:
        name = cam["name"]
        tc = np.asarray(cam["t_ns"], dtype=np.int64)
        T = np.asarray(cam["T_world_cam"])
        rec.log(f"world/trajectories/{name}", rr.LineStrips3D([T[:, :3, 3]], radii=0.02), static=True)
        rec.log(f"world/cameras/{name}", rr.Pinhole(image_from_camera=np.asarray(cam["K"]),
                                                    resolution=[cam["width_px"], cam["height_px"]],
                                                    image_plane_distance=1.0), static=True)
        for f in range(len(tc)):
            rec.set_time("time", duration=(int(tc[f]) - t0) * 1e-9)
            rec.log(f"world/cameras/{name}", rr.Transform3D(translation=T[f, :3, 3], mat3x3=T[f, :3, :3]))
    for cam in capture.cameras if capture is not None else []:
        for f in range(cam.num_frames):
            rec.set_time("time", duration=(int(cam.t_frame_ns[f]) - t0) * 1e-9)
            ok = cam.confidence[f, 0] > 0
            rec.log(f"world/cameras/{cam.name}/keypoints", rr.Points2D(cam.keypoints_px[f, 0][ok], radii=3.0))
    rec.flush()
    del rec  # closes the file


def _read(path) -> dict[str, dict]:
    """entity -> {"static": {component: value}, "rows": [(time ns, {component: value}), ...] by time}; rerun's
    bookkeeping (row ids, the ``log_time`` / ``log_tick`` timelines, the recording properties) left out."""
    from rerun.chunk import RrdReader

    out: dict[str, dict] = {}
    for chunk in RrdReader(path).stream():
        if chunk.entity_path.startswith("/__"):
            continue
        rb = chunk.to_record_batch()
        e = out.setdefault(chunk.entity_path, {"static": {}, "rows": []})
        comps = {n: rb.column(n).to_pylist() for n in rb.schema.names if ":" in n}
        if chunk.is_static:
            for n, v in comps.items():
                e["static"][n] = v[-1]
            continue
        times = rb.column("time").cast(pa.int64()).to_pylist()
        for r, t in enumerate(times):
            e["rows"].append((t, {n: v[r] for n, v in comps.items() if v[r] is not None}))
    for e in out.values():
        e["rows"].sort(key=lambda row: row[0])
    return out


@pytest.fixture(scope="module")
def motion():
    J, t_ns, *_ = procedural_walker(25)
    cfg = SynthConfig(miss_rate=0.3, camera_rate_hz=20.0)  # some keypoints missing: frames hold 0..17 points
    capture, _ = synthesize_capture(J, t_ns, cfg, seed=3)
    cameras = [{"name": c.name, "t_ns": c.t_frame_ns, "T_world_cam": c.pose_at(c.t_frame_ns), "K": c.K[-1],
                "width_px": c.width_px, "height_px": c.height_px} for c in capture.cameras]
    return J, t_ns, cameras, capture


def test_columnar_rrd_equals_per_frame_logging(tmp_path, motion):
    from reconstruction.viz import write_rrd

    J, t_ns, cameras, capture = motion
    _write_rrd_per_frame(tmp_path / "ref.rrd", J, t_ns, cameras, capture)
    write_rrd(tmp_path / "new.rrd", J, t_ns, cameras=cameras, capture=capture)
    ref, new = _read(tmp_path / "ref.rrd"), _read(tmp_path / "new.rrd")
    assert sorted(new) == sorted(ref)
    names = {c.name for c in capture.cameras}
    assert set(ref) == {"/world", "/world/person/joints", "/world/person/limbs"} | {
        f"/world/{k}/{n}" for n in names for k in ("cameras", "trajectories")} | {
        f"/world/cameras/{n}/keypoints" for n in names}
    kp_counts = set()
    for ent in ref:
        assert new[ent]["static"] == ref[ent]["static"], ent
        assert len(new[ent]["rows"]) == len(ref[ent]["rows"]), ent
        for (t_new, c_new), (t_ref, c_ref) in zip(new[ent]["rows"], ref[ent]["rows"]):
            assert t_new == t_ref, ent
            assert c_new == c_ref, (ent, t_ref)
        if ent.endswith("/keypoints"):
            kp_counts |= {len(c["Points2D:positions"]) for _, c in ref[ent]["rows"]}
    # the frames and the values are really there (not two equally empty files)
    assert len(ref["/world/person/joints"]["rows"]) == len(t_ns)
    assert ref["/world/person/joints"]["rows"][-1][0] == int(t_ns[-1] - t_ns[0])
    np.testing.assert_allclose(new["/world/person/joints"]["rows"][7][1]["Points3D:positions"], J[7], atol=1e-6)
    assert len(ref["/world/person/limbs"]["rows"][0][1]["LineStrips3D:strips"]) == len(COCO17_LIMBS)
    cam0 = cameras[0]
    assert len(new[f"/world/cameras/{cam0['name']}"]["rows"]) == len(cam0["t_ns"])
    assert len(kp_counts) > 1  # frames with different numbers of seen keypoints were partitioned right


def test_max_frames_and_no_cameras(tmp_path, motion):
    from reconstruction.viz import write_rrd

    J, t_ns, *_ = motion
    write_rrd(tmp_path / "m.rrd", J, t_ns, max_frames=5)
    got = _read(tmp_path / "m.rrd")
    assert set(got) == {"/world", "/world/person/joints", "/world/person/limbs"}
    assert [t for t, _ in got["/world/person/joints"]["rows"]] == [int(t - t_ns[0]) for t in t_ns[:5]]
