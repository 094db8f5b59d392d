"""``skycap process`` killed with SIGKILL (no cleanup, no cancel) resumes without recomputing finished work: a real
``skycap process`` subprocess on the short recorded flight with the real ONNX models is killed once in the keypoint
step and once in the fit step, then run to the end; the keypoint chunks and the fit windows finished before each kill
are not computed again (counters in the summary, cache files untouched) and the result equals an uninterrupted run's."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from process_helpers import copy_flight, make_config

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[3]


def _start(flight: Path, cfg_path: Path) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    return subprocess.Popen([sys.executable, "-m", "apps.cli", "process", str(flight), "--config", str(cfg_path)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=ROOT)


def _kill_when(proc: subprocess.Popen, ready, timeout_s: float = 600.0) -> None:
    """SIGKILL ``proc`` as soon as ``ready()`` is true (polled every 10 ms)."""
    t_end = time.monotonic() + timeout_s
    while not ready():
        if proc.poll() is not None:
            out, err = proc.communicate()
            pytest.fail(f"skycap process ended (exit {proc.returncode}) before the kill point:\n{err[-3000:]}")
        assert time.monotonic() < t_end, "the kill point was never reached"
        time.sleep(0.01)
    proc.send_signal(signal.SIGKILL)
    proc.communicate(timeout=30)
    assert proc.returncode == -signal.SIGKILL


def _files(folder: Path, pattern: str) -> dict[str, tuple[int, int]]:
    """name -> (inode, mtime) of the files matching ``pattern`` (one removed meanwhile is left out)."""
    out = {}
    for p in sorted(folder.glob(pattern)):
        try:
            st = p.stat()
        except FileNotFoundError:  # the run being watched consolidated the chunks meanwhile
            continue
        out[p.name] = (st.st_ino, st.st_mtime_ns)
    return out


@pytest.fixture(scope="module")
def killed_and_resumed(processed, tmp_path_factory):
    """The flight (its boxes from the processed fixture's cache: the kills are in the later steps) processed by
    ``skycap process`` killed in the keypoints, run again and killed in the fit, run again to the end."""
    src = processed["flight"]
    span_s = float((processed["runs"][1][0].t_ns[-1] - processed["runs"][1][0].t_ns[0]) * 1e-9)
    # two fit windows (the second kill falls between them), a short fit: the reference below fits them again
    cfg = make_config(**{"windows.window_s": span_s * 0.6, "windows.overlap_s": span_s / 8, "export.extra": [],
                         "multiview.fit.iters": 15})
    base = tmp_path_factory.mktemp("kill_resume")
    cfg_path = base / "process.toml"
    from skycap.config import save_config

    save_config(cfg, cfg_path)
    flight = copy_flight(src, base / "flight")
    shutil.copytree(src / "processing" / "boxes", flight / "processing" / "boxes")
    kp_dir = flight / "processing" / "keypoints"
    fit_dir = flight / "processing" / "fit"

    # run 1: killed once a few keypoint chunks are written
    p = _start(flight, cfg_path)
    _kill_when(p, lambda: len(list(kp_dir.glob("*.chunks/chunk_*.npz"))) >= 3)
    chunks = {d.name: _files(d, "chunk_*.npz") for d in kp_dir.glob("*.chunks")}
    # run 2: resumes the keypoints, killed once the first fit window is written; meanwhile, every 10 ms, whether run
    # 1's chunks are still the same files (inode, mtime) while run 2 writes new ones beside them
    seen = {"new_beside_old": 0, "old_rewritten": []}

    def watch() -> bool:
        for name, files in chunks.items():
            now = _files(kp_dir / name, "chunk_*.npz")
            if set(now) - set(files) and all(now.get(k) == v for k, v in files.items()):
                seen["new_beside_old"] += 1
            seen["old_rewritten"] += [k for k, v in files.items() if k in now and now[k] != v]
        return any(fit_dir.glob("*-w000.npz"))

    p = _start(flight, cfg_path)
    _kill_when(p, watch)
    time.sleep(0.05)
    windows_before = _files(fit_dir, "*-w*.npz")
    # run 3: to the end
    p = _start(flight, cfg_path)
    out, err = p.communicate(timeout=300)
    assert p.returncode == 0, err[-5000:]
    summary = json.loads(out[out.index("{"):])
    return {"flight": flight, "cfg": cfg, "chunks": chunks, "seen": seen, "windows_before": windows_before,
            "summary": summary, "stderr": err}


def test_a_killed_process_resumes_without_recomputing_and_equals_an_uninterrupted_run(killed_and_resumed, processed,
                                                                                   tmp_path):
    from reconstruction.process import process

    r = killed_and_resumed
    flight, s = r["flight"], r["summary"]
    assert s["steps"]["boxes"]["cached"] and s["keypoints_source"] == "movenet_lightning+blazepose_full"
    assert r["chunks"] and sum(len(v) for v in r["chunks"].values()) >= 3
    # the keypoints: run 2 wrote new chunks beside run 1's, which stayed the same files until consolidated, and
    # the result equals the uninterrupted keypoints of the processed fixture (the same cache key)
    assert r["seen"]["new_beside_old"] > 0 and not r["seen"]["old_rewritten"], r["seen"]
    assert not list((flight / "processing" / "keypoints").glob("*.chunks")), "chunks left after consolidation"
    assert not list(flight.rglob(".*.tmp")), "a temporary file of the killed runs is left in the cache"
    kp_files = sorted((flight / "processing" / "keypoints").glob("*.npz"))
    assert len(kp_files) == 2
    for f in kp_files:
        ref = processed["flight"] / "processing" / "keypoints" / f.name
        assert ref.is_file(), f"{f.name}: another key than the uninterrupted run's"
        np.testing.assert_allclose(np.load(f)["kp"], np.load(ref)["kp"], atol=1e-3)
    # run 3 ran no keypoint model (all from the cache) and the fit windows written before the second kill untouched
    assert s["stats"].get("frames_computed", 0) == 0 and s["steps"]["keypoints"]["cached"], s["stats"]
    assert r["windows_before"] and s["steps"]["fit"]["windows"] == 2
    assert 1 <= s["steps"]["fit"]["windows_cached"] == len(r["windows_before"]) < 2, (s["steps"]["fit"], r["windows_before"])
    after = _files(flight / "processing" / "fit", "*-w*.npz")
    assert all(after[k] == v for k, v in r["windows_before"].items()), "a finished window was written again"
    assert len(after) == s["steps"]["fit"]["windows"]
    # the same motion as an uninterrupted run of the same config (keypoints from the processed fixture's cache)
    ref_flight = copy_flight(processed["flight"], tmp_path / "ref", with_cache=True)
    ref = process(ref_flight, r["cfg"])
    assert ref.steps["fit"]["windows_cached"] == 0
    with np.load(s["outputs"]["npz"]) as z:
        np.testing.assert_array_equal(z["t_ns"], ref.t_ns)
        np.testing.assert_allclose(z["joints_ned"], ref.joints_ned, atol=1e-4)
