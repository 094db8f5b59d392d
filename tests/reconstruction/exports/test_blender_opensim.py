"""The motion files as their users open them: the BVH in Blender (the real ``bpy``, default import settings) and the
TRC in OpenSim (the real ``opensim`` package's TRC reader), both checked against our CSV."""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from reconstruction.export import BLENDER_FPS, BVH_JOINT_FOR_COCO, export_motion, resample_joints, write_joints_trc
from reconstruction.synth import procedural_walker
from skycap.frames import ned_to_yup
from skycap.skeleton import COCO17_NAMES
from tests.helpers.paths import REPO

CHECK = Path(__file__).with_name("blender_import_check.py")


def blender_python() -> str | None:
    """A Python with bpy 5.0: $SKYCAP_BLENDER_PYTHON, the checkout's .venv-blender (scripts/setup.sh), the one beside
    the running venv, or this interpreter when it has bpy."""
    cands = [os.environ.get("SKYCAP_BLENDER_PYTHON"), REPO / ".venv-blender/bin/python",
             Path(sys.prefix).parent / ".venv-blender/bin/python"]
    for c in cands:
        if c and Path(c).is_file():
            return str(c)
    return sys.executable if importlib.util.find_spec("bpy") else None


@pytest.fixture(scope="module")
def motion(tmp_path_factory):
    """12 s of a walking rigid skeleton at 10 Hz (longer than a new Blender scene's 250 frames), exported."""
    J, t_ns, shape, *_ = procedural_walker(120, fps=10.0)
    out = tmp_path_factory.mktemp("motion")
    paths = export_motion(out, J, t_ns, shape=shape, rrd=False)
    csv = np.loadtxt(paths["csv"], delimiter=",", skiprows=1)
    return paths, csv[:, 0], csv[:, 1:].reshape(-1, 17, 3)  # t_s, joints NED from the CSV


#: OpenSim's TRC reader, run in a child process: importing ``opensim`` loads its bundled libcasadi into the process
#: and prepends its folder to PATH / LD_LIBRARY_PATH, after which the casadi package (the formation MPC) no longer
#: imports in that process or its children -- so the test session itself never imports it
_OPENSIM_READ = """
import json, sys
import opensim as osim
t = osim.TimeSeriesTableVec3(sys.argv[1])
rows = [int(r) for r in sys.argv[2:]]
labels = list(t.getColumnLabels())
print("RESULT " + json.dumps({
    "meta": {k: t.getTableMetaDataAsString(k) for k in t.getTableMetaDataKeys()},
    "rows": t.getNumRows(), "labels": labels, "times": list(t.getIndependentColumn()),
    "values": [[[t.getDependentColumn(n)[k].get(a) for a in range(3)] for n in labels] for k in rows]}))
"""


def _csv_at(t_csv_s, J_csv, t_s: float) -> np.ndarray:
    """The CSV's joints (17, 3) at time ``t_s``, linearly interpolated."""
    return np.array([[np.interp(t_s, t_csv_s, J_csv[:, j, a]) for a in range(3)] for j in range(17)])


def test_blender_imports_real_size_and_speed_with_defaults(motion):
    py = blender_python()
    if py is None:
        pytest.skip("no Python with bpy 5.0: scripts/setup.sh makes .venv-blender (pip install bpy==5.0.1, which pins "
                    "numpy < 2 and so cannot share the project's venv), or set SKYCAP_BLENDER_PYTHON")
    paths, t_csv, J_csv = motion
    on_sample = [1, 13, 121, 241]  # scene frames at recorded times (t = (f - 1) / 24 s = 0, 0.5, 5, 10 s)
    between = [2, 100, 250, 286]
    frames = on_sample + between
    r = subprocess.run([py, str(CHECK), str(paths["bvh"]), *map(str, frames)], capture_output=True, text=True,
                       timeout=120)
    line = next((ln for ln in r.stdout.splitlines() if ln.startswith("RESULT ")), None)
    assert r.returncode == 0 and line, f"Blender import failed:\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
    b = json.loads(line[len("RESULT "):])
    assert b["version"].startswith("5.0")
    # a fresh scene, left as it was by the default import: 24 fps, the BVH frame i at scene frame 1 + i
    assert b["before"] == {"fps": 24, "fps_base": 1.0, "frame_start": 1, "frame_end": 250}
    assert (b["fps"], b["fps_base"]) == (24, 1.0) and BLENDER_FPS == 24.0
    n = int(np.floor(t_csv[-1] * BLENDER_FPS + 1e-9)) + 1  # 11.9 s at 24 fps
    assert b["action_frame_range"] == [1.0, float(n)] and n == 286
    assert b["unit_scale"] == 1.0
    assert set(BVH_JOINT_FOR_COCO) <= set(b["bones"]) and len(b["bones"]) == 21
    # real speed and size: the head of each COCO bone at scene frame f is the CSV's joint at (f - 1) / 24 s, in metres;
    # Blender's axes from the BVH's Y-up (importer default forward -Z, up Y): x = north, y = west, z = up
    # (between recorded frames the skeleton's rotations are slerped: close to the CSV's straight-line interpolation)
    for f in frames:
        heads = b["heads"][str(f)]
        got = np.array([heads[nm] for nm in BVH_JOINT_FOR_COCO])
        want_ned = _csv_at(t_csv, J_csv, (f - 1) / BLENDER_FPS)
        want = np.stack([want_ned[:, 0], -want_ned[:, 1], -want_ned[:, 2]], -1)
        tol = 1e-3 if f in on_sample else 2e-2
        assert np.abs(got - want).max() < tol, f"frame {f}: {np.abs(got - want).max() * 1e3:.1f} mm off"
    # one rigid skeleton in every frame: limb lengths do not change between recorded frames
    def shin(f):
        h = b["heads"][str(f)]
        return np.linalg.norm(np.subtract(h["l_knee"], h["l_ankle"]))
    assert max(abs(shin(f) - shin(1)) for f in frames) < 1e-4
    # height: nose-to-ankle span in Blender units equals the metres of the CSV (the skeleton is ~1.6 m to the nose)
    z = np.array([b["heads"]["1"][nm][2] for nm in BVH_JOINT_FOR_COCO])
    assert abs((z.max() - z.min()) - (J_csv[0, :, 2].max() - J_csv[0, :, 2].min())) < 5e-3
    assert 1.2 < z.max() - z.min() < 2.0


def _read_in_opensim(trc: Path, rows: list[int]) -> dict:
    """OpenSim's reading of ``trc``: {"meta", "rows", "labels", "times", "values" (the ``rows``' markers)}."""
    if importlib.util.find_spec("opensim") is None:
        pytest.skip("the opensim package is not installed (test extra: pip install opensim)")
    r = subprocess.run([sys.executable, "-c", _OPENSIM_READ, str(trc), *map(str, rows)], capture_output=True,
                       text=True, timeout=120)
    line = next((ln for ln in r.stdout.splitlines() if ln.startswith("RESULT ")), None)
    assert r.returncode == 0 and line, f"OpenSim could not read the TRC:\n{r.stdout[-2000:]}\n{r.stderr[-3000:]}"
    return json.loads(line[len("RESULT "):])


def test_trc_reads_back_in_opensim(motion, tmp_path):
    paths, t_csv, J_csv = motion
    t = _read_in_opensim(paths["trc"], [0, 57, 119])
    meta = t["meta"]
    assert meta["Units"] == "m" and float(meta["DataRate"]) == 10.0 and float(meta["CameraRate"]) == 10.0
    assert int(meta["NumFrames"]) == t["rows"] == 120 and int(meta["NumMarkers"]) == 17
    assert t["labels"] == list(COCO17_NAMES)
    np.testing.assert_allclose(t["times"], t_csv, atol=1e-6)
    got = np.array(t["values"])
    np.testing.assert_allclose(got, ned_to_yup(J_csv[[0, 57, 119]]), atol=1e-6)  # X north, Y up, Z east
    assert got[0, :, 1].max() > 1.4  # Y is up: the nose is ~1.6 m above the ground


def test_trc_resamples_irregular_times_and_marks_gaps(tmp_path):
    J, t_ns, *_ = procedural_walker(31, fps=30.0)
    keep = np.r_[0:10, 11:31]  # one dropped frame: 30 Hz times with a gap
    Jg = J[keep].copy()
    Jg[3, 9] = np.nan  # the left wrist unseen in one frame
    p = write_joints_trc(tmp_path / "gap.trc", Jg, t_ns[keep], rate_hz=30.0)
    t = _read_in_opensim(p, [3, 10])
    assert t["rows"] == 31 and float(t["meta"]["DataRate"]) == 30.0
    np.testing.assert_allclose(t["times"], np.arange(31) / 30.0, atol=1e-6)
    _, Jr = resample_joints(Jg, t_ns[keep], 30.0)
    got = np.array(t["values"], dtype=float)  # (2 rows, 17 markers, 3)
    np.testing.assert_allclose(got[1, COCO17_NAMES.index("nose")], ned_to_yup(Jr[10, 0]), atol=1e-6)
    assert np.isnan(got[0, COCO17_NAMES.index("left_wrist"), 0])


def test_resample_joints_is_linear_and_uniform():
    J, t_ns, *_ = procedural_walker(11, fps=10.0)
    t2, J2 = resample_joints(J, t_ns, 20.0)
    assert len(t2) == 21 and np.all(np.diff(t2) == 50_000_000)
    np.testing.assert_allclose(J2[::2], J, atol=1e-12)
    np.testing.assert_allclose(J2[1], 0.5 * (J[0] + J[1]), atol=1e-12)
    with pytest.raises(ValueError, match="increase"):
        resample_joints(J, t_ns[::-1], 20.0)


def test_blender_bvh_skips_bad_frames(tmp_path):
    from reconstruction.export import write_blender_bvh
    from skycap.bvh import read_bvh

    J, t_ns, shape, *_ = procedural_walker(21, fps=10.0)
    J[5] = np.nan  # a frame without a fit
    t_ns = t_ns.copy()
    t_ns[9] = t_ns[8]  # a repeated time
    path, err = write_blender_bvh(tmp_path / "m.bvh", J, t_ns, shape)
    m = read_bvh(path)
    assert err < 1e-6 and m.num_frames == 49 and m.frame_time_s == pytest.approx(1 / 24, abs=1e-6)
    assert np.isfinite(m.values).all()
    P = m.world_positions()[:, [m.skeleton.index(n) for n in BVH_JOINT_FOR_COCO]]
    from skycap.frames import yup_to_ned

    # t = 0.5 s (BVH frame 12) had no fit: bridged between the recorded frames 4 and 6
    assert np.abs(yup_to_ned(P[12]) - 0.5 * (J[4] + J[6])).max() < 0.03
    np.testing.assert_allclose(yup_to_ned(P[24]), J[10], atol=1e-4)  # t = 1.0 s: a kept recorded frame
